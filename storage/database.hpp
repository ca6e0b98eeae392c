// The SQLite connection of magcal: opening, pragmas, schema migrations, transactions.
//
// Error policy (whole storage/ library): every failure is thrown as the one exception type
// StorageError (with a Kind and, for SQLite failures, SQLite's extended result code), and the
// service catches it at its edge (CLI run_*, daemon start / worker loop) to print one line and
// choose an exit code. transient() separates what a retry can heal (a lock held past the busy
// timeout, I/O error, full disk, the file deleted / moved / made read-only underneath) from
// what it cannot (corrupt or foreign file, schema, constraint, bad argument): the daemon
// retries the first kind (service/daemon/storage_retry.hpp). Data outcomes that are not failures
// are values: duplicate samples are counted in InsertStats, "not found" is std::nullopt.
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
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>

struct sqlite3;  // <sqlite3.h> stays out of public headers

namespace magcal::storage {

// 'MGCL' — what `PRAGMA application_id` reads on a magcal database.
constexpr int32_t kApplicationId = 0x4D47434C;

class StorageError : public std::runtime_error {
 public:
  enum class Kind {
    kNotFound,     // read-only open of a missing file
    kForeignFile,  // not a SQLite file, or another application's (application_id)
    kNewerSchema,  // user_version newer than this code: refuse rather than guess
    kOlderSchema,  // read-only open of a database that needs a migration first
    kInvalidArgument,
    kSqlite,    // any other SQLite error (I/O, corrupt, busy after the timeout, ...)
    kPostgres,  // any other PostgreSQL error (connection, SQL, deadlock, ...): see sqlstate()
  };
  // sqlite_code: SQLite's extended result code (SQLITE_BUSY, SQLITE_IOERR_WRITE, ...), 0 when
  // the failure is not SQLite's (kNotFound, kNewerSchema, ...).
  StorageError(Kind kind, const std::string& what, int sqlite_code = 0)
      : std::runtime_error(what), kind_(kind), sqlite_code_(sqlite_code) {}
  // A PostgreSQL failure (storage/postgres): its SQLSTATE ("40P01", "08006", ...) and whether
  // a retry can heal it, which storage/postgres/pg_database.cpp decides from the SQLSTATE.
  StorageError(Kind kind, const std::string& what, std::string sqlstate, bool transient)
      : std::runtime_error(what),
        kind_(kind),
        sqlstate_(std::move(sqlstate)),
        postgres_transient_(transient) {}
  Kind kind() const { return kind_; }
  int sqlite_code() const { return sqlite_code_; }
  // "" unless the failure is PostgreSQL's.
  const std::string& sqlstate() const { return sqlstate_; }
  // May heal by itself: SQLITE_BUSY, SQLITE_LOCKED, SQLITE_IOERR, SQLITE_FULL, SQLITE_READONLY,
  // SQLITE_CANTOPEN, SQLITE_PROTOCOL (each with its extended codes). Everything else is
  // permanent for this file and this code. PostgreSQL: as decided at the throw (connection
  // lost, serialization failure, deadlock, server shutting down, ...).
  bool transient() const;

 private:
  Kind kind_;
  int sqlite_code_ = 0;
  std::string sqlstate_;
  bool postgres_transient_ = false;
};

// SQLITE_READONLY_DBMOVED, used for a database file deleted, renamed or replaced while open
// (Database::check_file_in_place()); equals SQLite's own code.
constexpr int kSqliteReadonlyDbMoved = 8 | (4 << 8);
// SQLITE_BUSY: what a read spoiled by a writer reports (a retry heals it).
constexpr int kSqliteBusy = 5;

struct OpenOptions {
  // Read-only never creates, migrates or writes a file (magcal status/history/serve use it),
  // also in a directory the user cannot write. A WAL database is read through its -shm file
  // (the index its writers share), which SQLite creates when the directory is writable and
  // otherwise needs present and readable. When it is absent and cannot be created, no
  // connection has the file open (a WAL connection keeps -shm while open), so it is opened
  // immutable: no locks, no -shm (see immutable()). A -wal file holding commits without its
  // -shm (a writer crashed) cannot be read safely that way: refused, naming the file.
  bool read_only = false;
  // Migrate up to this version only (-1: the newest this code knows). For tests that build an
  // old database; production code leaves it alone.
  int migrate_to = -1;
  // How long a statement waits on another connection's lock before failing.
  int busy_timeout_ms = 5000;
};

// The schema version an open should reach: options.migrate_to, or `latest` when it is -1.
// Throws StorageError (kInvalidArgument) for a version beyond `latest`. Both backends use it.
int migration_target(const OpenOptions& options, int latest);

class Database {
 public:
  // `path` may be ":memory:". Throws StorageError.
  explicit Database(const std::string& path, const OpenOptions& options = {});
  ~Database();
  Database(Database&& other) noexcept;
  Database& operator=(Database&& other) noexcept;
  Database(const Database&) = delete;
  Database& operator=(const Database&) = delete;

  // Newest schema version this code knows (= number of embedded migrations).
  static int latest_schema_version();
  // PRAGMA user_version of the open file.
  int schema_version() const;

  const std::string& path() const { return path_; }
  bool read_only() const { return read_only_; }
  // Read-only open without locks or -shm (see OpenOptions::read_only): nothing stops a writer
  // from opening the file meanwhile, so a reader checks changed_since_open() after reading.
  bool immutable() const { return immutable_file_.has_value(); }
  // Immutable opens only (false otherwise): a writer has opened the file since this connection
  // did (its -wal or -shm exists, or the file's size, time or inode changed), so what was read
  // may mix two states of the file. Reopen and read again: the new connection reads through
  // the writer's -shm.
  bool changed_since_open() const;

  // Runs one or more SQL statements without results (DDL, pragmas, tests).
  void exec(std::string_view sql);
  // rowid of the last INSERT on this connection.
  int64_t last_insert_id() const;
  // Runs `PRAGMA integrity_check`; returns "ok" on a sound file, else SQLite's report.
  std::string integrity_check();
  // Throws a transient StorageError (SQLITE_READONLY_DBMOVED) when the file at path() is no
  // longer the one this connection has open (deleted, renamed or replaced underneath). In WAL
  // mode SQLite keeps committing into the unlinked file without an error, so a writer that
  // must not lose data checks this before each commit (one stat; no-op for ":memory:").
  void check_file_in_place();

  sqlite3* handle() const { return db_; }

 private:
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

// RAII transaction: BEGIN IMMEDIATE (takes the write lock up front, so a writer waits on the
// busy timeout at BEGIN instead of failing half-way) or a deferred BEGIN for read snapshots.
// Rolled back on destruction unless commit() was called. Inside an already open transaction
// it becomes a SAVEPOINT, so a caller can group several store calls into one commit.
class Transaction {
 public:
  enum class Mode { kImmediate, kDeferred };
  explicit Transaction(Database& db, Mode mode = Mode::kImmediate);
  ~Transaction();
  Transaction(const Transaction&) = delete;
  Transaction& operator=(const Transaction&) = delete;
  void commit();

 private:
  Database& db_;
  bool open_ = false;
  bool nested_ = false;
};

}  // namespace magcal::storage
