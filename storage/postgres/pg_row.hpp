// The sink and the rows the table codecs (storage/row_codec.hpp, sample_row.hpp,
// calibration_row.hpp) bind to and read from, on PostgreSQL parameters and results. Internal to
// storage/.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/blob_doubles.hpp"
#include "storage/postgres/pg_query.hpp"

namespace magcal::storage {

struct PgBinder {
  PgParams& params;
  void integer(int64_t v) { params.add(v); }
  void real(double v) {
    if (std::isnan(v)) {
      params.add_null();  // NaN is NULL, as on SQLite (a NOT NULL column then refuses it)
    } else {
      params.add(v);
    }
  }
  void text(std::string_view v) { params.add(v); }
  void doubles(std::span<const double> v) { params.add_bytes(std::as_bytes(v)); }
  void bytes(std::span<const uint8_t> v) { params.add_bytes(std::as_bytes(v)); }
  void null() { params.add_null(); }
};

// A row of a result in either format, each value's type checked.
struct PgRow {
  const PgResult& result;
  int row;
  bool is_null(int c) const { return result.is_null(row, c); }
  int64_t integer(int c) const { return result.get_int64(row, c); }
  double real(int c) const {
    return result.get_optional_double(row, c).value_or(std::numeric_limits<double>::quiet_NaN());
  }
  std::string text(int c) const { return is_null(c) ? std::string() : result.get_text(row, c); }
  bool blob(int c, std::span<double> out, const std::string& what) const {
    if (result.is_null(row, c)) return false;
    const auto bytes = result.get_bytes(row, c);
    doubles_from_blob(bytes.data(), bytes.size(), out, what);
    return true;
  }
  void bytes(int c, std::vector<uint8_t>& out) const {
    out.clear();
    if (is_null(c)) return;
    const auto bytes = result.get_bytes(row, c);
    out.resize(bytes.size());
    for (size_t i = 0; i < bytes.size(); ++i) out[i] = static_cast<uint8_t>(bytes[i]);
  }
};

// A row of a binary result whose column types were checked once (PgResult::
// check_binary_column): the hot loops read its values without a check each.
struct PgBinaryRow {
  const PgResult& result;
  int row;
  bool is_null(int c) const { return result.is_null(row, c); }
  int64_t integer(int c) const { return result.bigint_at(row, c); }
  double real_not_null(int c) const { return result.double_at(row, c); }
  double real(int c) const {
    return is_null(c) ? std::numeric_limits<double>::quiet_NaN() : result.double_at(row, c);
  }
};

}  // namespace magcal::storage
