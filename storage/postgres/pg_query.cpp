#include "storage/postgres/pg_query.hpp"

#include <algorithm>

#include <endian.h>
#include <libpq-fe.h>

#include <charconv>
#include <cstdlib>
#include <cstring>
#include <utility>

#include "storage/sqlite/database.hpp"

namespace magcal::storage {
namespace {

// Type OIDs (server/catalog/pg_type_d.h, which libpq-dev does not ship; fixed since 7.x).
constexpr unsigned kBoolOid = 16, kByteaOid = 17, kNameOid = 19, kInt8Oid = 20, kInt2Oid = 21,
                   kInt4Oid = 23, kTextOid = 25, kFloat4Oid = 700, kFloat8Oid = 701,
                   kBpcharOid = 1042, kVarcharOid = 1043, kNumericOid = 1700, kTextArrayOid = 1009,
                   kInt8ArrayOid = 1016;
// An unspecified parameter type: the server infers it from the statement, as for a literal.
constexpr unsigned kInferredOid = 0;

template <typename Int>
Int big_endian(std::string_view bytes) {
  Int value = 0;
  for (const char c : bytes) value = static_cast<Int>((value << 8) | static_cast<uint8_t>(c));
  return value;
}

}  // namespace

PgParams& PgParams::push(unsigned type, const void* data, std::size_t size, int format) {
  types_.push_back(type);
  lengths_.push_back(static_cast<int>(size));
  formats_.push_back(format);
  if (data == nullptr) {
    offsets_.push_back(-1);
  } else {
    offsets_.push_back(static_cast<std::ptrdiff_t>(bytes_.size()));
    const char* begin = static_cast<const char*>(data);
    bytes_.insert(bytes_.end(), begin, begin + size);
  }
  return *this;
}

PgParams& PgParams::add(int64_t value) {
  const uint64_t wire = htobe64(static_cast<uint64_t>(value));
  return push(kInt8Oid, &wire, sizeof wire, 1);
}

PgParams& PgParams::add(double value) {
  uint64_t bits = 0;
  std::memcpy(&bits, &value, sizeof bits);
  const uint64_t wire = htobe64(bits);
  return push(kFloat8Oid, &wire, sizeof wire, 1);
}

PgParams& PgParams::add(std::string_view text) {
  // Text-format parameters are read up to their NUL (libpq ignores their length). An empty
  // view may have no data at all: still '', not NULL.
  static const char kEmpty = 0;
  push(kInferredOid, text.empty() ? &kEmpty : text.data(), text.size(), 0);
  bytes_.push_back('\0');
  return *this;
}

PgParams& PgParams::add_bytes(std::span<const std::byte> bytes) {
  // A non-null pointer also for an empty value: an empty bytea is not NULL.
  static const char kEmpty = 0;
  return push(kByteaOid, bytes.empty() ? static_cast<const void*>(&kEmpty) : bytes.data(),
              bytes.size(), 1);
}

template <typename Length, typename Put>
PgParams& PgParams::push_array(unsigned array_type, unsigned element_type, std::size_t n,
                               Length length, Put put) {
  // PostgreSQL's binary array (array_recv): ndim, has-nulls flag, element type, then per
  // dimension its size and lower bound, then each element as a 32-bit length and its bytes; all
  // big-endian.
  const auto offset = static_cast<std::ptrdiff_t>(bytes_.size());
  auto put32 = [this](uint32_t v) {
    const uint32_t wire = htobe32(v);
    const char* p = reinterpret_cast<const char*>(&wire);
    bytes_.insert(bytes_.end(), p, p + sizeof wire);
  };
  put32(1);
  put32(0);
  put32(element_type);
  put32(static_cast<uint32_t>(n));
  put32(1);
  for (std::size_t i = 0; i < n; ++i) {
    put32(static_cast<uint32_t>(length(i)));
    put(i);
  }
  types_.push_back(array_type);
  lengths_.push_back(static_cast<int>(bytes_.size() - static_cast<std::size_t>(offset)));
  formats_.push_back(1);
  offsets_.push_back(offset);
  return *this;
}

PgParams& PgParams::add_array(std::span<const int64_t> values) {
  return push_array(
      kInt8ArrayOid, kInt8Oid, values.size(), [](std::size_t) { return sizeof(uint64_t); },
      [&](std::size_t i) {
        const uint64_t wire = htobe64(static_cast<uint64_t>(values[i]));
        const char* p = reinterpret_cast<const char*>(&wire);
        bytes_.insert(bytes_.end(), p, p + sizeof wire);
      });
}

PgParams& PgParams::add_array(std::span<const std::string> values) {
  return push_array(
      kTextArrayOid, kTextOid, values.size(), [&](std::size_t i) { return values[i].size(); },
      [&](std::size_t i) { bytes_.insert(bytes_.end(), values[i].begin(), values[i].end()); });
}

PgParams& PgParams::add_null() {
  return push(kInferredOid, nullptr, 0, 0);
}

void PgParams::clear() {
  types_.clear();
  lengths_.clear();
  formats_.clear();
  offsets_.clear();
  bytes_.clear();
}

const char* const* PgParams::values() const {
  values_.resize(offsets_.size());
  for (std::size_t i = 0; i < offsets_.size(); ++i) {
    values_[i] = offsets_[i] < 0 ? nullptr : bytes_.data() + offsets_[i];
  }
  return values_.data();
}

std::string dollar_params(std::string sql) {
  std::replace(sql.begin(), sql.end(), '?', '$');
  return sql;
}

std::string multi_row_values_sql(std::string_view head, std::size_t rows, int columns,
                                 int first_param, std::string_view row_tail,
                                 std::string_view tail) {
  std::string sql(head);
  int param = first_param;
  for (std::size_t row = 0; row < rows; ++row) {
    sql += row == 0 ? "(" : ", (";
    for (int c = 0; c < columns; ++c, ++param) {
      if (c > 0) sql += ", ";
      sql += '$';
      sql += std::to_string(param);
    }
    sql += row_tail;
    sql += ')';
  }
  sql += tail;
  return sql;
}

PgResult::~PgResult() {
  PQclear(result_);
}

PgResult::PgResult(PgResult&& other) noexcept : result_(std::exchange(other.result_, nullptr)) {}

PgResult& PgResult::operator=(PgResult&& other) noexcept {
  if (this != &other) {
    PQclear(result_);
    result_ = std::exchange(other.result_, nullptr);
  }
  return *this;
}

int PgResult::rows() const {
  return result_ ? PQntuples(result_) : 0;
}

int PgResult::columns() const {
  return result_ ? PQnfields(result_) : 0;
}

int64_t PgResult::affected_rows() const {
  const char* n = result_ ? PQcmdTuples(result_) : "";
  int64_t value = 0;
  std::from_chars(n, n + std::strlen(n), value);
  return value;
}

bool PgResult::binary(int column) const {
  return PQfformat(result_, column) == 1;
}

unsigned PgResult::type(int column) const {
  return PQftype(result_, column);
}

void PgResult::wrong_type(int column, const char* wanted) const {
  throw StorageError(StorageError::Kind::kInvalidArgument,
                     std::string("column ") + PQfname(result_, column) + " (type oid " +
                         std::to_string(type(column)) + ") read as " + wanted);
}

std::string_view PgResult::raw(int row, int column) const {
  if (result_ == nullptr || row < 0 || row >= rows() || column < 0 || column >= columns()) {
    throw StorageError(
        StorageError::Kind::kInvalidArgument,
        "result has no row " + std::to_string(row) + " column " + std::to_string(column));
  }
  if (PQgetisnull(result_, row, column)) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       std::string("column ") + PQfname(result_, column) + " is NULL");
  }
  return {PQgetvalue(result_, row, column),
          static_cast<std::size_t>(PQgetlength(result_, row, column))};
}

bool PgResult::is_null(int row, int column) const {
  return result_ == nullptr || PQgetisnull(result_, row, column) == 1;
}

int64_t PgResult::get_int64(int row, int column) const {
  const std::string_view value = raw(row, column);
  const unsigned t = type(column);
  if (t != kInt8Oid && t != kInt4Oid && t != kInt2Oid) wrong_type(column, "an integer");
  if (binary(column)) {
    switch (value.size()) {
      case 8:
        return static_cast<int64_t>(big_endian<uint64_t>(value));
      case 4:
        return static_cast<int32_t>(big_endian<uint32_t>(value));
      case 2:
        return static_cast<int16_t>(big_endian<uint16_t>(value));
      default:
        wrong_type(column, "an integer");
    }
  }
  int64_t out = 0;
  const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), out);
  if (ec != std::errc() || end != value.data() + value.size()) wrong_type(column, "an integer");
  return out;
}

double PgResult::get_double(int row, int column) const {
  const unsigned t = type(column);
  if (t == kInt8Oid || t == kInt4Oid || t == kInt2Oid) {
    return static_cast<double>(get_int64(row, column));
  }
  const std::string_view value = raw(row, column);
  if (binary(column)) {
    if (t == kFloat8Oid && value.size() == 8) {
      const uint64_t bits = big_endian<uint64_t>(value);
      double out = 0;
      std::memcpy(&out, &bits, sizeof out);
      return out;
    }
    if (t == kFloat4Oid && value.size() == 4) {
      const uint32_t bits = big_endian<uint32_t>(value);
      float out = 0;
      std::memcpy(&out, &bits, sizeof out);
      return out;
    }
    wrong_type(column, "a double");
  }
  if (t != kFloat8Oid && t != kFloat4Oid && t != kNumericOid) wrong_type(column, "a double");
  // Shortest round-trip digits (extra_float_digits > 0, set by PgDatabase): exact. strtod
  // also reads "NaN", "Infinity" and "-Infinity".
  const std::string text(value);
  char* end = nullptr;
  const double out = std::strtod(text.c_str(), &end);
  if (end != text.c_str() + text.size()) wrong_type(column, "a double");
  return out;
}

bool PgResult::get_bool(int row, int column) const {
  const std::string_view value = raw(row, column);
  if (type(column) != kBoolOid) wrong_type(column, "a boolean");
  return binary(column) ? value == std::string_view("\1", 1) : value == "t";
}

std::string PgResult::get_text(int row, int column) const {
  const std::string_view value = raw(row, column);
  const unsigned t = type(column);
  if (binary(column) && t != kTextOid && t != kVarcharOid && t != kNameOid && t != kBpcharOid) {
    wrong_type(column, "text");
  }
  return std::string(value);
}

std::vector<std::byte> PgResult::get_bytes(int row, int column) const {
  const std::string_view value = raw(row, column);
  if (type(column) != kByteaOid) wrong_type(column, "bytea");
  if (binary(column)) {
    const auto* begin = reinterpret_cast<const std::byte*>(value.data());
    return {begin, begin + value.size()};
  }
  std::size_t size = 0;
  unsigned char* decoded =
      PQunescapeBytea(reinterpret_cast<const unsigned char*>(value.data()), &size);
  if (decoded == nullptr) throw std::bad_alloc();
  const auto* begin = reinterpret_cast<const std::byte*>(decoded);
  std::vector<std::byte> out(begin, begin + size);
  PQfreemem(decoded);
  return out;
}

void PgResult::check_binary_column(int column, BinaryColumn type) const {
  if (result_ == nullptr || column < 0 || column >= columns()) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "result has no column " + std::to_string(column));
  }
  const bool bigint = type == BinaryColumn::kBigint;
  if (!binary(column) || PQfsize(result_, column) != 8 ||
      this->type(column) != (bigint ? kInt8Oid : kFloat8Oid)) {
    wrong_type(column, bigint ? "a binary bigint" : "a binary double");
  }
}

int64_t PgResult::bigint_at(int row, int column) const {
  // The one check left per value: 8 bytes (a NULL has none), so nothing is read out of bounds.
  if (PQgetlength(result_, row, column) != 8) {
    raw(row, column);  // throws for a NULL, or a row out of range
    wrong_type(column, "8 bytes");
  }
  return static_cast<int64_t>(
      big_endian<uint64_t>(std::string_view(PQgetvalue(result_, row, column), 8)));
}

double PgResult::double_at(int row, int column) const {
  const int64_t bits = bigint_at(row, column);
  double out = 0;
  std::memcpy(&out, &bits, sizeof out);
  return out;
}

std::optional<int64_t> PgResult::get_optional_int64(int row, int column) const {
  if (is_null(row, column)) return std::nullopt;
  return get_int64(row, column);
}

std::optional<double> PgResult::get_optional_double(int row, int column) const {
  if (is_null(row, column)) return std::nullopt;
  return get_double(row, column);
}

}  // namespace magcal::storage
