// One `samples` row: its field list, written once, that the SQLite and PostgreSQL stores and the
// spill file's binary encoding (service/daemon/intake/sample_spill.cpp) all walk. Adding a column
// is one line here (plus the StoredSample member and a migration per backend).
//
// fields(sample, f) calls, in column order:
//   f.key(column, text)                  the spacecraft: bound by an insert, known to a read
//   f.integer(column, int64_t)           bigint NOT NULL
//   f.reals(columns, array)              doubles NOT NULL
//   f.flag(column, bool)                 a presence flag stored as a column (0/1)
//   f.flagged(columns, array, flag)      doubles present when `flag` (stored before them) is
//                                        set: NULL otherwise, and NaN when read back
//   f.real(column, double)               a double NOT NULL (NaN binds as NULL: refused)
//   f.optional(columns, array, present)  doubles stored together or not at all: `present` is
//                                        whether its first column is not NULL
//   f.nullable_real(column, double)      a double, NaN <-> NULL
// An insert binds the station after these (storage/sample_window_store.hpp).
// Internal to storage/ (and the spill file).
#pragma once

#include <array>
#include <cstddef>
#include <limits>
#include <string>
#include <string_view>

#include "storage/sample_window_store.hpp"

namespace magcal::storage::sample_row {

template <typename Sample, typename Fields>
void fields(Sample& s, Fields& f) {
  f.key("sat_id", s.sat_id);
  f.integer("utime", s.utime);
  f.integer("seq", s.seq);
  f.integer("receive_utime", s.receive_utime);
  f.reals({"bx_nT", "by_nT", "bz_nT"}, s.b_sensor_nT);
  f.flag("has_direction", s.has_direction);
  f.flagged({"hx_nT", "hy_nT", "hz_nT"}, s.h_body_nT, s.has_direction);
  f.real("h_norm_nT", s.h_norm_nT);
  f.optional({"qw", "qx", "qy", "qz"}, s.q_body_from_eci, s.has_attitude);
  f.optional({"rx_m", "ry_m", "rz_m"}, s.r_ecef_m, s.has_position);
  f.nullable_real("temperature_C", s.temperature_C);
}

// What a column holds, for a backend that checks a result's column types once (PostgreSQL).
enum class ColumnType { kInteger, kReal };

// Walks the list by column: name(column, type) for each, the key included or not.
template <typename Name>
struct ByColumn {
  Name name;
  bool with_key;
  template <typename T>
  void key(const char* column, const T&) {
    if (with_key) name(column, ColumnType::kInteger);
  }
  template <typename T>
  void integer(const char* column, const T&) {
    name(column, ColumnType::kInteger);
  }
  template <typename T>
  void flag(const char* column, const T&) {
    name(column, ColumnType::kInteger);
  }
  template <typename T>
  void real(const char* column, const T&) {
    name(column, ColumnType::kReal);
  }
  template <typename T>
  void nullable_real(const char* column, const T&) {
    name(column, ColumnType::kReal);
  }
  template <size_t N, typename... Rest>
  void reals(const char* const (&columns)[N], const Rest&...) {
    for (const char* c : columns) name(c, ColumnType::kReal);
  }
  template <size_t N, typename... Rest>
  void flagged(const char* const (&columns)[N], const Rest&...) {
    reals(columns);
  }
  template <size_t N, typename... Rest>
  void optional(const char* const (&columns)[N], const Rest&...) {
    reals(columns);
  }
};

// Calls name(column, ColumnType) for each column in order: with the key (an insert's columns)
// or without (what a read selects).
template <typename Name>
void for_each_column(bool with_key, Name&& name) {
  StoredSample s;
  ByColumn<Name&> walk{name, with_key};
  fields(s, walk);
}

// "a, b, c": the columns, with the key or without.
inline std::string column_list(bool with_key) {
  std::string out;
  for_each_column(with_key, [&out](const char* column, ColumnType) {
    if (!out.empty()) out += ", ";
    out += column;
  });
  return out;
}

inline int column_count(bool with_key) {
  int n = 0;
  for_each_column(with_key, [&n](const char*, ColumnType) { ++n; });
  return n;
}

// The columns a read selects (the key is known), and an insert's (the key, then the station).
inline const std::string& read_columns() {
  static const std::string columns = column_list(false);
  return columns;
}
inline const std::string& insert_columns() {
  static const std::string columns = column_list(true) + ", station";
  return columns;
}

// Binds a sample's values in column order into a sink: text(string_view), integer(int64_t),
// real(double) (NaN binds as NULL), null().
template <typename Sink>
struct Writer {
  Sink& sink;
  void key(const char*, const std::string& v) { sink.text(v); }
  void integer(const char*, int64_t v) { sink.integer(v); }
  void flag(const char*, bool v) { sink.integer(v ? 1 : 0); }
  void real(const char*, double v) { sink.real(v); }
  void nullable_real(const char*, double v) { sink.real(v); }
  template <size_t N, size_t M>
  void reals(const char* const (&)[N], const std::array<double, M>& v) {
    static_assert(N == M);
    for (const double x : v) sink.real(x);
  }
  template <size_t N, size_t M>
  void flagged(const char* const (&columns)[N], const std::array<double, M>& v, bool flag) {
    optional(columns, v, flag);
  }
  template <size_t N, size_t M>
  void optional(const char* const (&columns)[N], const std::array<double, M>& v, bool present) {
    if (present) {
      reals(columns, v);
    } else {
      for (size_t i = 0; i < M; ++i) sink.null();
    }
  }
};

template <typename Sink>
void write(const StoredSample& s, Sink& sink) {
  Writer<Sink> writer{sink};
  fields(s, writer);
}

// Reads a row of read_columns() from column `first` on. Row: integer(c) and real_not_null(c)
// for NOT NULL columns (the hot loop: a 12 h window is 4320 rows, no NULL test), is_null(c),
// real(c) (NULL: NaN).
template <typename Row>
struct Reader {
  const Row& row;
  std::string_view sat_id;
  int c;
  void key(const char*, std::string& v) { v = sat_id; }
  void integer(const char*, int64_t& v) { v = row.integer(c++); }
  void flag(const char*, bool& v) { v = row.integer(c++) != 0; }
  void real(const char*, double& v) { v = row.real_not_null(c++); }
  void nullable_real(const char*, double& v) { v = row.real(c++); }
  template <size_t N, size_t M>
  void reals(const char* const (&)[N], std::array<double, M>& v) {
    for (double& x : v) x = row.real_not_null(c++);
  }
  template <size_t N, size_t M>
  void flagged(const char* const (&columns)[N], std::array<double, M>& v, bool flag) {
    if (flag) {
      reals(columns, v);
    } else {
      v.fill(std::numeric_limits<double>::quiet_NaN());
      c += static_cast<int>(M);
    }
  }
  template <size_t N, size_t M>
  void optional(const char* const (&columns)[N], std::array<double, M>& v, bool& present) {
    present = !row.is_null(c);
    if (present) {
      reals(columns, v);
    } else {
      c += static_cast<int>(M);
    }
  }
};

template <typename Row>
void read(const Row& row, int first, std::string_view sat_id, StoredSample& s) {
  Reader<Row> reader{row, sat_id, first};
  fields(s, reader);
}

}  // namespace magcal::storage::sample_row
