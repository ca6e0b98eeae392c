// Parameters and results of PostgreSQL statements (storage/postgres/pg_database.hpp runs them).
//
// Numbers travel in PostgreSQL's binary format both ways where the caller asks for it: no text
// conversion, exact int64 and IEEE doubles (the text format is exact too since PostgreSQL 12,
// shortest round-trip digits, but costs a conversion per value and 2.4-5.3x more read time,
// toolchain.md). A PgParams is reusable: clear() keeps its buffers, so a writer that binds a
// batch per call allocates nothing once warmed up.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

struct pg_result;  // libpq's PGresult; <libpq-fe.h> stays out of public headers

namespace magcal::storage {

// $1, $2, ... of one statement, in order.
class PgParams {
 public:
  PgParams& add(int64_t value);  // bigint, binary
  PgParams& add(int value) { return add(int64_t{value}); }
  PgParams& add(double value);           // double precision, binary
  PgParams& add(std::string_view text);  // text
  PgParams& add(const char* text) { return add(std::string_view(text)); }
  PgParams& add_bytes(std::span<const std::byte> bytes);  // bytea, binary
  PgParams& add_null();                                   // NULL of a type the statement implies
  // One-dimensional arrays (bigint[], text[]), binary: a statement takes any number of values
  // in one parameter (WHERE x = ANY($1), unnest($1, $2)).
  PgParams& add_array(std::span<const int64_t> values);
  PgParams& add_array(std::span<const std::string> values);
  template <typename T>
  PgParams& add(const std::optional<T>& value) {
    return value ? add(*value) : add_null();
  }
  void clear();
  int size() const { return static_cast<int>(types_.size()); }

  // For PgDatabase: libpq's parallel arrays (valid until the next add or clear).
  const unsigned* types() const { return types_.data(); }
  const char* const* values() const;
  const int* lengths() const { return lengths_.data(); }
  const int* formats() const { return formats_.data(); }

 private:
  PgParams& push(unsigned type, const void* data, std::size_t size, int format);
  // An array of n elements of `element_type`, each written by put(i, bytes_) after its length
  // (length(i) bytes).
  template <typename Length, typename Put>
  PgParams& push_array(unsigned array_type, unsigned element_type, std::size_t n, Length length,
                       Put put);

  std::vector<unsigned> types_;
  std::vector<int> lengths_, formats_;
  std::vector<std::ptrdiff_t> offsets_;  // into bytes_; -1 for NULL
  std::vector<char> bytes_;
  mutable std::vector<const char*> values_;
};

enum class PgFormat { kText, kBinary };

// Multi-row statements: one statement per batch instead of one per row (a round trip and a
// statement's overhead each, ~90 % of a small insert's cost), with few distinct statements to
// prepare (parsing one of thousands of parameters costs more than running it).
//
// `head` + "($p, ..., $p+columns-1<row_tail>), (...), ..." for `rows` rows + `tail`, the row
// parameters numbered from `first_param`.
std::string multi_row_values_sql(std::string_view head, std::size_t rows, int columns,
                                 int first_param, std::string_view row_tail, std::string_view tail);
// SQL written once for both dialects, in SQLite's ?N parameters, as PostgreSQL's $N (no other
// '?' in it).
std::string dollar_params(std::string sql);

// Splits n rows into statements of 2^max_log2 rows and the rest in its binary digits (2^k,
// ..., 2, 1 rows): max_log2 + 1 statements serve every batch size. Calls
// statement(first_row, log2_rows) for each, in row order.
template <typename Statement>
void for_each_power_of_two_run(std::size_t n, std::size_t max_log2, Statement statement) {
  for (std::size_t begin = 0; begin < n;) {
    std::size_t k = max_log2;
    while ((std::size_t{1} << k) > n - begin) --k;
    statement(begin, k);
    begin += std::size_t{1} << k;
  }
}

// The rows of one statement (RAII over a PGresult). Getters accept either result format and
// the integer / float widths PostgreSQL may send (int2/int4/int8, float4/float8); a NULL, a
// row or column out of range, or a value of another type throws StorageError(kInvalidArgument).
class PgResult {
 public:
  explicit PgResult(pg_result* result = nullptr) : result_(result) {}
  ~PgResult();
  PgResult(PgResult&& other) noexcept;
  PgResult& operator=(PgResult&& other) noexcept;
  PgResult(const PgResult&) = delete;
  PgResult& operator=(const PgResult&) = delete;

  int rows() const;
  int columns() const;
  // Rows an INSERT / UPDATE / DELETE touched.
  int64_t affected_rows() const;

  bool is_null(int row, int column) const;
  int64_t get_int64(int row, int column) const;
  double get_double(int row, int column) const;
  bool get_bool(int row, int column) const;
  std::string get_text(int row, int column) const;
  std::vector<std::byte> get_bytes(int row, int column) const;
  std::optional<int64_t> get_optional_int64(int row, int column) const;
  std::optional<double> get_optional_double(int row, int column) const;

  // Hot loops (a window of thousands of rows): check_binary_column() checks a column's type and
  // format once (throws as the getters do); then its values are read without per-value type
  // checks. A NULL or a row out of range throws.
  enum class BinaryColumn { kBigint, kDouble };
  void check_binary_column(int column, BinaryColumn type) const;
  int64_t bigint_at(int row, int column) const;
  double double_at(int row, int column) const;

 private:
  // The value's bytes; throws on NULL or out of range.
  std::string_view raw(int row, int column) const;
  bool binary(int column) const;
  unsigned type(int column) const;
  [[noreturn]] void wrong_type(int column, const char* wanted) const;

  pg_result* result_ = nullptr;
};

}  // namespace magcal::storage
