// One thread's connection to a magcal database, whichever engine holds it: an SQLite file (the
// embedded default, storage/sqlite/database.hpp) or a PostgreSQL database shared by a fleet
// (storage/postgres/pg_database.hpp, design.md "Fleet"). open_database() chooses by the --db /
// [storage] db_path value. A connection makes its stores (make_*: the sample window, the
// calibration history, the refit job log, the filter states, the meta values, the spacecraft
// leases), and groups their calls into one commit with a Transaction. Nothing of the engine shows
// here: errors are StorageError with a backend-neutral condition (storage/storage_error.hpp).
//
// Threads: a connection and the stores made on it belong to one thread at a time (prepared
// statements are per connection). Give each thread (ingest worker, refit scheduler, CLI) its own.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "storage/storage_error.hpp"

namespace magcal::storage {

class SampleWindowStore;
class RefitJobLog;
class FilterStateStore;
class MetaStore;
class CalibrationHistory;
class LeaseStore;
class SqlSession;

// 'MGCL': SQLite's `PRAGMA application_id` of a magcal file, and the application_id of
// PostgreSQL's magcal_schema_version rows.
constexpr int32_t kApplicationId = 0x4D47434C;

struct OpenOptions {
  // Read-only never creates, migrates or writes (magcal status/history/serve use it). SQLite:
  // also in a directory the user cannot write; a WAL database is read through its -shm file
  // (the index its writers share), which SQLite creates when the directory is writable and
  // otherwise needs present and readable. When it is absent and cannot be created, no
  // connection has the file open (a WAL connection keeps -shm while open), so it is opened
  // immutable: no locks, no -shm (see Database::immutable()). A -wal file holding commits
  // without its -shm (a writer crashed) cannot be read safely that way: refused, naming the file.
  // PostgreSQL: the session is read-only.
  bool read_only = false;
  // Migrate up to this version only (-1: the newest this code knows). For tests that build an
  // old database; production code leaves it alone.
  int migrate_to = -1;
  // How long a statement waits on another connection's lock before failing (SQLite's busy
  // timeout, PostgreSQL's lock_timeout): StorageError condition kBusy.
  int busy_timeout_ms = 5000;
  // PostgreSQL: a server that cannot be reached now (a transient failure: down, starting up,
  // refusing, timing out, a host name that does not resolve) does not fail the open. The
  // session is opened, and the schema checked and migrated, at the first statement, which fails
  // with that transient error until it can (the daemon starts during an outage and rides it out
  // as one that began later). A permanent failure (authentication, a missing database or role)
  // still throws here. SQLite: no effect.
  bool connect_later = false;
  // PostgreSQL: how long a statement waits for the server's reply (0: for ever). A server that
  // accepts connections but does not answer (frozen, overloaded, or holding every commit for a
  // synchronous standby that is down) keeps a live TCP connection, so neither the keepalives nor
  // tcp_user_timeout end the wait. Past this the statement fails transient (kUnavailable,
  // SQLSTATE 08006) and the connection is set aside until its reply comes (see
  // PgDatabase::settle_set_aside). A schema migration that outlasts it goes on in the server.
  // SQLite: no effect.
  int reply_timeout_ms = 10000;
};

// The schema version an open should reach: options.migrate_to, or `latest` when it is -1.
// Throws StorageError (kInvalidArgument) for a version beyond `latest`. Both backends use it.
int migration_target(const OpenOptions& options, int latest);

// A --db / db_path value naming a PostgreSQL database (a libpq URI) rather than an SQLite file.
inline bool is_postgres_uri(std::string_view db) {
  return db.starts_with("postgresql://") || db.starts_with("postgres://");
}

// What the engine behind a --db / db_path value means for a writer that must ride out its
// failures: each caller asks the question it has, never which engine it is. An SQLite file is
// local: its failure (disk full, file moved, a lock held too long) is this host's, so a commit
// waits through the retry backoff and liveness reports it. A PostgreSQL server is remote and
// shared by a fleet: its failure is an outage elsewhere (network, restart, failover) that a
// writer rides out without blocking, its samples in a local spill file, and that says nothing of
// this process's health (readiness reports it instead).
struct Capabilities {
  // A commit may block its caller through the retry backoff until storage answers (flush
  // before a refit or a handover). False: one attempt per call, never a wait through an outage.
  bool commit_may_block = true;
  // While commits fail, received samples go to a local spill file (written and fdatasync'ed at
  // each commit interval) and are committed when the database returns.
  bool spill_during_outage = false;
  // A storage failure means this process is unhealthy (/-/healthy 503, systemd may restart
  // it). False: the process stays healthy and is not ready (/-/ready 503) during the outage.
  bool failure_is_unhealthy = true;
  // A database that cannot be reached at start is an outage that began early (the writer
  // starts and rides it out), not a start error.
  bool unreachable_at_start_is_outage = false;
  // Opening a database that does not exist creates it (an SQLite file); false: it must have
  // been created first (a PostgreSQL database and its role: docs/fleet.md).
  bool open_creates_missing = true;
};

// The capabilities of the engine `db` names (see Capabilities); opens nothing.
Capabilities capabilities_of(std::string_view db);

// A --db / db_path value as messages and logs may show it: a PostgreSQL URI without its password
// (user:***@host, password=***), a file path as it is. Connection::name() of an open connection.
std::string database_name(const std::string& db);

// `text` (a message of the engine, which may quote the --db value: libpq's URI parse errors do)
// with every secret of `db` (its password, as written or percent-decoded) replaced by ***.
std::string without_database_secrets(const std::string& db, std::string text);

enum class TransactionMode {
  kWrite,         // a writer: SQLite takes its write lock up front, so it waits at the start
                  // (busy timeout) instead of failing half-way
  kReadSnapshot,  // several reads that must see one state of the database
};

class Connection {
 public:
  virtual ~Connection() = default;
  // A connection owns its engine's session and is an identity (its stores hold references to
  // it): neither copied nor moved.
  Connection(const Connection&) = delete;
  Connection& operator=(const Connection&) = delete;
  Connection(Connection&&) = delete;
  Connection& operator=(Connection&&) = delete;

  // The database for messages and logs: the file path, or the URI without its password.
  virtual const std::string& name() const = 0;
  virtual bool read_only() const = 0;
  // Runs SQL statements without parameters or results, in the engine's own dialect (DDL, tests).
  virtual void exec(std::string_view sql) = 0;
  // True when what this connection read may mix two states of the database and a reopen is
  // needed (an SQLite file read without locks that a writer opened meanwhile: see
  // Database::immutable()); false for every other connection.
  virtual bool changed_since_open() const { return false; }

  // Whether the transaction of a COMMIT in doubt (StorageError::in_doubt_transaction()) took
  // effect, asked on this connection once the server answers again: a caller that counts what
  // it committed, or must not write a result twice, asks before it retries. Throws StorageError
  // (transient) while the server cannot tell yet: unreachable, or the transaction still in
  // progress (a commit held for a synchronous standby). PostgreSQL only: SQLite never leaves a
  // commit in doubt (kInvalidArgument).
  enum class CommitOutcome { kCommitted, kRolledBack };
  virtual CommitOutcome commit_outcome(int64_t transaction_id);

  virtual std::unique_ptr<SampleWindowStore> make_sample_window_store() = 0;
  // The stores written once for both backends (storage/sql_*.hpp), unless a backend adds to them.
  virtual std::unique_ptr<RefitJobLog> make_refit_job_log();
  virtual std::unique_ptr<FilterStateStore> make_filter_state_store();
  virtual std::unique_ptr<MetaStore> make_meta_store();
  virtual std::unique_ptr<CalibrationHistory> make_calibration_history();
  virtual std::unique_ptr<LeaseStore> make_lease_store();

 protected:
  Connection() = default;

  // Where the stores written once prepare their statements (storage/sql_statement.hpp).
  virtual SqlSession& sql_session() = 0;

  friend class Transaction;
  // Opens a transaction, or a savepoint inside an open one (returns true then).
  virtual bool begin_transaction(TransactionMode mode) = 0;
  virtual void commit_transaction(bool nested) = 0;
  // Ends what begin_transaction opened: rolled back unless committed. Never throws.
  virtual void end_transaction(bool nested, bool committed) noexcept = 0;
};

// Why `db` is neither a PostgreSQL URI nor an SQLite file path: a scheme in upper case or
// mistyped ("postgress://", "postgres ql://"), libpq's key=value form; "" when it is one of them.
// A mistake in the value (a config or usage error), found without opening anything.
std::string database_value_error(const std::string& db);

// Opens `db`: a postgresql:// or postgres:// URI is a PostgreSQL database, anything else an
// SQLite file path (or ":memory:"); a value database_value_error() refuses is refused (condition
// kInvalidArgument) rather than created as a file of that name. Throws StorageError.
std::unique_ptr<Connection> open_database(const std::string& db, const OpenOptions& options = {});

// RAII transaction, rolled back on destruction unless commit() was called. Inside an already
// open transaction it becomes a savepoint, so a caller can group several store calls into one
// commit. A write transaction on SQLite first checks that the file is still the one open (in
// WAL mode SQLite keeps committing into a deleted or replaced file without an error): condition
// kFileMoved otherwise. PostgreSQL locks rows as statements touch them: writers that may touch
// the same rows keep one global key order, and retry kConflict (transient).
class Transaction {
 public:
  using Mode = TransactionMode;
  explicit Transaction(Connection& db, Mode mode = Mode::kWrite)
      : Transaction(db, db.begin_transaction(mode)) {}
  ~Transaction() { db_.end_transaction(nested_, committed_); }
  Transaction(const Transaction&) = delete;
  Transaction& operator=(const Transaction&) = delete;
  void commit() {
    db_.commit_transaction(nested_);
    committed_ = true;
  }

 protected:
  // A transaction the backend has begun (a backend's own kinds: PgTransaction).
  Transaction(Connection& db, bool nested) : db_(db), nested_(nested) {}

 private:
  Connection& db_;
  bool nested_;
  bool committed_ = false;
};

}  // namespace magcal::storage
