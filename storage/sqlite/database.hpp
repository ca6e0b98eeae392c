// The SQLite connection of magcal (the embedded backend): opening, pragmas, schema migrations,
// transactions.
//
// Errors: StorageError (storage/storage_error.hpp), with SQLite's extended result code mapped to
// its backend-neutral condition (busy, I/O, disk full, file moved, corrupt, ...).
//
// Threads: a Database and the stores built on it belong to one thread at a time (prepared
// statements are per connection). Give each thread (ingest worker, refit scheduler, CLI) its own
// Database; WAL lets them read and write concurrently, the busy timeout serialises writers.
//
// Schema: numbered migrations (storage/migrations/NNNN_name.sql, embedded in the binary), each
// applied in one transaction that also sets PRAGMA user_version = NNNN. PRAGMA application_id =
// kApplicationId marks a magcal file; any other non-zero id is refused, as is a user_version
// newer than this code knows. Opening an older file read-write upgrades it.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>

#include "storage/connection.hpp"
#include "storage/sql_statement.hpp"
#include "storage/storage_error.hpp"

struct sqlite3;  // <sqlite3.h> stays out of public headers

namespace magcal::storage {

// SQLITE_READONLY_DBMOVED, used for a database file deleted, renamed or replaced while open
// (Database::check_file_in_place()); equals SQLite's own code.
constexpr int kSqliteReadonlyDbMoved = 8 | (4 << 8);

class Database final : public Connection, public SqlSession {
 public:
  // `path` may be ":memory:". Throws StorageError.
  explicit Database(const std::string& path, const OpenOptions& options = {});
  ~Database();

  // The newest schema this build's SQLite migrations make (storage/migrations/*.sql).
  static int latest_schema_version();
  // PRAGMA user_version of the open file.
  int schema_version() const;

  const std::string& path() const { return path_; }
  const std::string& name() const override { return path_; }
  bool read_only() const override { return read_only_; }
  // Read-only open without locks or -shm (see OpenOptions::read_only): nothing stops a writer
  // from opening the file meanwhile, so a reader checks changed_since_open() after reading.
  bool immutable() const { return immutable_file_.has_value(); }
  // Immutable opens only (false otherwise): a writer has opened the file since this connection
  // did (its -wal or -shm exists, or the file's size, time or inode changed), so what was read
  // may mix two states of the file. Reopen and read again: the new connection reads through
  // the writer's -shm.
  bool changed_since_open() const override;

  // Runs one or more SQL statements without results (DDL, pragmas, tests).
  void exec(std::string_view sql) override;
  // rowid of the last INSERT on this connection.
  int64_t last_insert_id() const;
  // Runs `PRAGMA integrity_check`; returns "ok" on a sound file, else SQLite's report.
  std::string integrity_check();
  // Throws a transient StorageError (condition kFileMoved, SQLITE_READONLY_DBMOVED) when the
  // file at path() is no longer the one this connection has open (deleted, renamed or replaced
  // underneath). In WAL mode SQLite keeps committing into the unlinked file without an error, so
  // every write Transaction checks this at its start (one stat; no-op for ":memory:").
  void check_file_in_place();

  std::unique_ptr<SampleWindowStore> make_sample_window_store() override;

  // SqlSession (storage/sqlite/sqlite_sql_session.cpp): statements on this connection.
  std::unique_ptr<SqlStatement> prepare(std::string_view sql) override;
  const char* byte_order() const override { return ""; }
  const char* lock_rows_shared() const override { return ""; }
  const char* json_array_texts() const override { return "SELECT value FROM json_each(?1)"; }

 private:
  friend class Statement;  // the one user of the raw connection
  sqlite3* handle() const { return db_; }
  SqlSession& sql_session() override { return *this; }

  // BEGIN IMMEDIATE (a writer; checks check_file_in_place() first) or BEGIN DEFERRED (a read
  // snapshot); a SAVEPOINT inside an open transaction.
  bool begin_transaction(TransactionMode mode) override;
  void commit_transaction(bool nested) override;
  void end_transaction(bool nested, bool committed) noexcept override;

  void configure(const OpenOptions& options);
  void check_and_migrate(const OpenOptions& options);

  // What identifies the file's content without reading it: an immutable connection's check.
  struct FileIdentity {
    uint64_t device = 0, inode = 0;
    int64_t size = 0, mtime_ns = 0;
    bool operator==(const FileIdentity&) const = default;
  };
  static std::optional<FileIdentity> identity_of(const std::string& path);
  // Opens db_ read-only: shared (through -shm) or immutable (see OpenOptions::read_only).
  int open_read_only(int flags);

  sqlite3* db_ = nullptr;
  std::string path_;
  bool read_only_ = false;
  std::optional<FileIdentity> immutable_file_;  // set for an immutable open
};

}  // namespace magcal::storage
