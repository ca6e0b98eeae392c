// The walker of a table's field list (storage/refit_job_row.hpp, lease_row.hpp,
// filter_state_row.hpp): a codec lists its columns once, in order, as f(column, member), and the
// column list of its SQL, the values an insert binds and the struct a row reads back into are all
// made from that one list, on both backends. The member's type says how it is stored, as
// libpqxx's string_traits does:
//   int64_t                 bigint NOT NULL
//   std::optional<int64_t>  bigint, NULL for nullopt
//   std::string             text (a NULL reads back as "")
//   std::array<double, N>   a blob of exactly N doubles (storage/blob_doubles.hpp)
//   std::vector<uint8_t>    a blob of bytes (a NULL reads back empty)
//
// A backend supplies a sink (integer, text, doubles, bytes, null) and a row (is_null, integer,
// text, blob, bytes) over its own statements: storage/sqlite/sqlite_row.hpp,
// storage/postgres/pg_row.hpp. Internal to storage/.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "storage/blob_doubles.hpp"

namespace magcal::storage::row_codec {

template <typename Sink>
struct Writer {
  Sink& sink;
  void operator()(const char*, int64_t v) { sink.integer(v); }
  void operator()(const char*, const std::optional<int64_t>& v) {
    if (v) {
      sink.integer(*v);
    } else {
      sink.null();
    }
  }
  void operator()(const char*, const std::string& v) { sink.text(v); }
  template <size_t N>
  void operator()(const char*, const std::array<double, N>& v) {
    sink.doubles(v);
  }
  void operator()(const char*, const std::vector<uint8_t>& v) { sink.bytes(v); }
};

template <typename Row>
struct Reader {
  const Row& row;
  const char* table;
  int column = 0;
  void operator()(const char*, int64_t& v) { v = row.integer(column++); }
  void operator()(const char*, std::optional<int64_t>& v) {
    v = row.is_null(column) ? std::nullopt : std::optional<int64_t>(row.integer(column));
    ++column;
  }
  void operator()(const char*, std::string& v) { v = row.text(column++); }
  template <size_t N>
  void operator()(const char* name, std::array<double, N>& v) {
    const std::string what = std::string(table) + "." + name;
    // NOT NULL columns: a NULL is as corrupt as a blob of the wrong size.
    if (!row.blob(column++, v, what)) doubles_from_blob(nullptr, 0, v, what);
  }
  void operator()(const char*, std::vector<uint8_t>& v) { row.bytes(column++, v); }
};

struct Names {
  std::string list;
  int count = 0;
  template <typename T>
  void operator()(const char* name, const T&) {
    if (count++ > 0) list += ", ";
    list += name;
  }
};

// "a, b, c": the codec's columns in order.
template <typename Codec>
std::string column_list() {
  typename Codec::Record r;
  Names names;
  Codec::fields(r, names);
  return names.list;
}

template <typename Codec>
int column_count() {
  typename Codec::Record r;
  Names names;
  Codec::fields(r, names);
  return names.count;
}

// `SELECT <columns> FROM <table> <tail>`.
template <typename Codec>
std::string select_sql(std::string_view tail) {
  return "SELECT " + column_list<Codec>() + " FROM " + Codec::kTable + " " + std::string(tail);
}

template <typename Codec, typename Sink>
void write(const typename Codec::Record& r, Sink& sink) {
  Writer<Sink> writer{sink};
  Codec::fields(r, writer);
}

// The record in the row's columns `first`, `first` + 1, ...
template <typename Codec, typename Row>
typename Codec::Record read(const Row& row, int first = 0) {
  typename Codec::Record r;
  Reader<Row> reader{row, Codec::kTable, first};
  Codec::fields(r, reader);
  return r;
}

}  // namespace magcal::storage::row_codec
