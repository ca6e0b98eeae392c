// RAII prepared statement: prepared once (in a store's constructor), reset and re-bound for
// every use. Binding indices are 1-based as in SQLite; column indices are 0-based.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "storage/sqlite/database.hpp"

struct sqlite3_stmt;

namespace magcal::storage {

class Statement {
 public:
  Statement(Database& db, std::string_view sql);  // throws StorageError
  ~Statement();
  Statement(Statement&& other) noexcept;
  Statement& operator=(Statement&&) = delete;
  Statement(const Statement&) = delete;
  Statement& operator=(const Statement&) = delete;

  // Resets the statement (keeps it prepared) and clears bindings.
  Statement& reset();

  // One use of the statement: reset on entry and on scope exit, so a half-read SELECT never
  // keeps its read snapshot open (which would pin the WAL and hide newer commits).
  class Use {
   public:
    explicit Use(Statement& st) : st_(st) { st_.reset(); }
    ~Use() { st_.reset(); }
    Use(const Use&) = delete;
    Use& operator=(const Use&) = delete;

   private:
    Statement& st_;
  };
  [[nodiscard]] Use use() { return Use(*this); }

  Statement& bind(int index, int64_t value);
  Statement& bind(int index, int value) { return bind(index, static_cast<int64_t>(value)); }
  Statement& bind(int index, double value);  // NaN is stored as NULL
  Statement& bind(int index, std::string_view text);
  // The same without SQLite's copy of the text, which must then stay valid and unchanged until
  // the statement is reset (the end of its use): a hot loop's rows.
  Statement& bind_unowned(int index, std::string_view text);
  Statement& bind_blob(int index, const void* data, size_t size);
  Statement& bind_null(int index);
  template <typename T>
  Statement& bind(int index, const std::optional<T>& value) {
    return value ? bind(index, *value) : bind_null(index);
  }

  // Advances: true while a row is available, false when done. Throws on error.
  bool step();
  // Runs a statement without result rows; returns sqlite3_changes().
  int execute();

  bool is_null(int col) const;
  int64_t column_int64(int col) const;
  double column_double(int col) const;  // NULL reads as NaN
  // Hot path for NOT NULL columns (one SQLite call instead of two; a NULL would read 0.0).
  double column_double_not_null(int col) const;
  std::string column_text(int col) const;
  std::string_view column_text_view(int col) const;           // valid until the next step/reset
  std::span<const unsigned char> column_blob(int col) const;  // valid until the next step/reset

 private:
  Database* db_;
  sqlite3_stmt* stmt_ = nullptr;
};

}  // namespace magcal::storage
