// The sink and the row the table codecs (storage/row_codec.hpp, sample_row.hpp,
// calibration_row.hpp) bind to and read from, on an SQLite statement. Internal to storage/.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/blob_doubles.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

// Binds from `index` on, in order. `unowned_text`: texts bound without SQLite's copy (they must
// outlive the statement's use: a hot loop's rows).
struct SqliteBinder {
  Statement& st;
  int index = 1;
  bool unowned_text = false;
  void integer(int64_t v) { st.bind(index++, v); }
  void real(double v) { st.bind(index++, v); }  // NaN binds as NULL
  void text(std::string_view v) {
    if (unowned_text) {
      st.bind_unowned(index++, v);
    } else {
      st.bind(index++, v);
    }
  }
  void doubles(std::span<const double> v) { st.bind_blob(index++, v.data(), v.size_bytes()); }
  void bytes(std::span<const uint8_t> v) { st.bind_blob(index++, v.data(), v.size()); }
  void null() { st.bind_null(index++); }
};

struct SqliteRow {
  const Statement& st;
  bool is_null(int c) const { return st.is_null(c); }
  int64_t integer(int c) const { return st.column_int64(c); }
  double real(int c) const { return st.column_double(c); }  // NULL: NaN
  // NOT NULL columns: one SQLite call instead of two.
  double real_not_null(int c) const { return st.column_double_not_null(c); }
  std::string text(int c) const { return st.column_text(c); }
  // False when NULL, else exactly out.size() doubles (doubles_from_blob).
  bool blob(int c, std::span<double> out, const std::string& what) const {
    if (st.is_null(c)) return false;
    const auto bytes = st.column_blob(c);
    doubles_from_blob(bytes.data(), bytes.size(), out, what);
    return true;
  }
  void bytes(int c, std::vector<uint8_t>& out) const {
    const auto bytes = st.column_blob(c);
    out.assign(bytes.begin(), bytes.end());
  }
};

}  // namespace magcal::storage
