#include "storage/sqlite/statement.hpp"

#include <sqlite3.h>

#include <cmath>
#include <limits>
#include <string>
#include <utility>

namespace magcal::storage {
namespace {

[[noreturn]] void fail(sqlite3* db, int rc, std::string_view context) {
  const auto kind =
      (rc & 0xff) == SQLITE_NOTADB ? StorageError::Kind::kForeignFile : StorageError::Kind::kEngine;
  std::string msg(context);
  msg += ": ";
  msg += db ? sqlite3_errmsg(db) : sqlite3_errstr(rc);
  throw StorageError::sqlite(kind, msg, rc);
}

int bind_text(sqlite3_stmt* stmt, int index, std::string_view text, sqlite3_destructor_type copy) {
  // An empty string_view may have a null data(), which SQLite would bind as NULL.
  const char* data = text.data() ? text.data() : "";
  return sqlite3_bind_text(stmt, index, data, static_cast<int>(text.size()), copy);
}

}  // namespace

Statement::Statement(Database& db, std::string_view sql) : db_(&db) {
  const int rc = sqlite3_prepare_v3(db.handle(), sql.data(), static_cast<int>(sql.size()),
                                    SQLITE_PREPARE_PERSISTENT, &stmt_, nullptr);
  if (rc != SQLITE_OK) fail(db.handle(), rc, "prepare '" + std::string(sql.substr(0, 60)) + "'");
}

Statement::~Statement() {
  sqlite3_finalize(stmt_);
}

Statement::Statement(Statement&& other) noexcept
    : db_(other.db_), stmt_(std::exchange(other.stmt_, nullptr)) {}

Statement& Statement::reset() {
  sqlite3_reset(stmt_);  // its return code repeats the last step's error, already reported
  sqlite3_clear_bindings(stmt_);
  return *this;
}

Statement& Statement::bind(int index, int64_t value) {
  const int rc = sqlite3_bind_int64(stmt_, index, value);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

Statement& Statement::bind(int index, double value) {
  if (std::isnan(value)) return bind_null(index);
  const int rc = sqlite3_bind_double(stmt_, index, value);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

Statement& Statement::bind(int index, std::string_view text) {
  const int rc = bind_text(stmt_, index, text, SQLITE_TRANSIENT);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

Statement& Statement::bind_unowned(int index, std::string_view text) {
  const int rc = bind_text(stmt_, index, text, SQLITE_STATIC);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

Statement& Statement::bind_blob(int index, const void* data, size_t size) {
  const int rc = sqlite3_bind_blob(stmt_, index, data, static_cast<int>(size), SQLITE_TRANSIENT);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

Statement& Statement::bind_null(int index) {
  const int rc = sqlite3_bind_null(stmt_, index);
  if (rc != SQLITE_OK) fail(db_->handle(), rc, "bind");
  return *this;
}

bool Statement::step() {
  const int rc = sqlite3_step(stmt_);
  if (rc == SQLITE_ROW) return true;
  if (rc == SQLITE_DONE) return false;
  const std::string sql = sqlite3_sql(stmt_) ? sqlite3_sql(stmt_) : "";
  sqlite3_reset(stmt_);
  fail(db_->handle(), rc, "step '" + sql.substr(0, 60) + "'");
}

int Statement::execute() {
  while (step()) {
  }
  return sqlite3_changes(db_->handle());
}

bool Statement::is_null(int col) const {
  return sqlite3_column_type(stmt_, col) == SQLITE_NULL;
}

int64_t Statement::column_int64(int col) const {
  return sqlite3_column_int64(stmt_, col);
}

double Statement::column_double(int col) const {
  if (is_null(col)) return std::numeric_limits<double>::quiet_NaN();
  return sqlite3_column_double(stmt_, col);
}

double Statement::column_double_not_null(int col) const {
  return sqlite3_column_double(stmt_, col);
}

std::string Statement::column_text(int col) const {
  return std::string(column_text_view(col));
}

std::string_view Statement::column_text_view(int col) const {
  const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(stmt_, col));
  if (!p) return {};
  return {p, static_cast<size_t>(sqlite3_column_bytes(stmt_, col))};
}

std::span<const unsigned char> Statement::column_blob(int col) const {
  const auto* p = static_cast<const unsigned char*>(sqlite3_column_blob(stmt_, col));
  if (!p) return {};
  return {p, static_cast<size_t>(sqlite3_column_bytes(stmt_, col))};
}

}  // namespace magcal::storage
