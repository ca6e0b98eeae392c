// The seam the backend-neutral stores (storage/sql_*_store.hpp, sql_refit_job_log.hpp) run their
// SQL through, so that a store is written once for SQLite and PostgreSQL: a statement prepared
// once, bound in order and read row by row, and the few spellings the two dialects do not share.
// SQL is written with SQLite's ?N parameters (PostgreSQL's session turns them into $N).
// storage/sqlite/database.cpp and storage/postgres/pg_sql_session.cpp implement it. Internal to
// storage/.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace magcal::storage {

// The current row of a statement: what the row codecs read (storage/row_codec.hpp).
class SqlRow {
 public:
  virtual ~SqlRow() = default;
  virtual bool is_null(int c) const = 0;
  virtual int64_t integer(int c) const = 0;
  virtual double real(int c) const = 0;       // NULL: NaN
  virtual std::string text(int c) const = 0;  // NULL: ""
  // False when NULL, else exactly out.size() doubles (doubles_from_blob).
  virtual bool blob(int c, std::span<double> out, const std::string& what) const = 0;
  virtual void bytes(int c, std::vector<uint8_t>& out) const = 0;  // NULL: empty
};

// A statement prepared once; its binding calls are the row codecs' sink (in order, from the
// first parameter on). Used through SqlRun, which resets it before and after each use.
class SqlStatement {
 public:
  virtual ~SqlStatement() = default;
  virtual void integer(int64_t v) = 0;
  virtual void real(double v) = 0;  // NaN binds as NULL
  virtual void text(std::string_view v) = 0;
  virtual void doubles(std::span<const double> v) = 0;
  virtual void bytes(std::span<const uint8_t> v) = 0;
  virtual void null() = 0;

  // The current row (after next() returned true).
  virtual const SqlRow& row() const = 0;
  // Runs the statement at the first call; then true while a row is current.
  virtual bool next() = 0;
  // Runs a statement without rows; the rows it changed.
  virtual int64_t changes() = 0;
  // Forgets the bindings and the rows.
  virtual void reset() = 0;
};

// A backend's row adapter (SqliteRow, PgRow) as an SqlRow.
template <typename Row>
class SqlRowOf final : public SqlRow {
 public:
  explicit SqlRowOf(Row row) : row_(row) {}
  bool is_null(int c) const override { return row_.is_null(c); }
  int64_t integer(int c) const override { return row_.integer(c); }
  double real(int c) const override { return row_.real(c); }
  std::string text(int c) const override { return row_.text(c); }
  bool blob(int c, std::span<double> out, const std::string& what) const override {
    return row_.blob(c, out, what);
  }
  void bytes(int c, std::vector<uint8_t>& out) const override { row_.bytes(c, out); }
  Row& adapter() { return row_; }

 private:
  Row row_;
};

// A statement whose bindings go to a backend's binder (SqliteBinder, PgBinder).
template <typename Binder>
class SqlStatementOf : public SqlStatement {
 public:
  void integer(int64_t v) override { binder_.integer(v); }
  void real(double v) override { binder_.real(v); }
  void text(std::string_view v) override { binder_.text(v); }
  void doubles(std::span<const double> v) override { binder_.doubles(v); }
  void bytes(std::span<const uint8_t> v) override { binder_.bytes(v); }
  void null() override { binder_.null(); }

 protected:
  explicit SqlStatementOf(Binder binder) : binder_(binder) {}
  Binder binder_;
};

// One use of a statement, its parameters bound in order: reset on entry and on exit (a
// half-read SELECT never keeps SQLite's read snapshot open).
class SqlRun {
 public:
  template <typename... Values>
  explicit SqlRun(SqlStatement& st, const Values&... values) : st_(st) {
    st_.reset();
    (bind(values), ...);
  }
  ~SqlRun() { st_.reset(); }
  SqlRun(const SqlRun&) = delete;
  SqlRun& operator=(const SqlRun&) = delete;

  bool next() { return st_.next(); }
  const SqlRow& row() const { return st_.row(); }
  int64_t changes() { return st_.changes(); }
  // The first row's first column; nullopt without rows or when NULL (max() of no rows).
  std::optional<int64_t> single_integer() {
    if (!next() || row().is_null(0)) return std::nullopt;
    return row().integer(0);
  }
  // Each row read by `read` (a row codec's read).
  template <typename T, typename Read>
  std::vector<T> all(Read read) {
    std::vector<T> out;
    while (next()) out.push_back(read(row()));
    return out;
  }
  template <typename T, typename Read>
  std::optional<T> first(Read read) {
    if (!next()) return std::nullopt;
    return read(row());
  }

 private:
  void bind(int64_t v) { st_.integer(v); }
  void bind(int v) { st_.integer(v); }
  void bind(std::string_view v) { st_.text(v); }
  void bind(const std::string& v) { st_.text(v); }
  void bind(const char* v) { st_.text(v); }
  void bind(const std::optional<int64_t>& v) {
    if (v) {
      st_.integer(*v);
    } else {
      st_.null();
    }
  }

  SqlStatement& st_;
};

// Prepares statements on one connection, and spells what the dialects write differently.
class SqlSession {
 public:
  virtual ~SqlSession() = default;
  // `sql` with ?N parameters. Throws StorageError.
  virtual std::unique_ptr<SqlStatement> prepare(std::string_view sql) = 0;
  // After a text expression in ORDER BY: sorted by its bytes (SQLite's default; PostgreSQL
  // sorts by the database's locale unless told COLLATE "C").
  virtual const char* byte_order() const = 0;
  // After a SELECT whose rows must not change until the transaction ends (PostgreSQL's
  // FOR SHARE; SQLite's write transaction already excludes every other writer).
  virtual const char* lock_rows_shared() const = 0;
  // A statement whose rows are the strings of the JSON array ?1.
  virtual const char* json_array_texts() const = 0;
};

}  // namespace magcal::storage
