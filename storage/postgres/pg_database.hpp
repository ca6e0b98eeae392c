// The PostgreSQL connection of magcal (fleet mode, design.md "Fleet"): opening a libpq URI,
// schema migrations, statements, transactions and errors. The counterpart of
// storage/sqlite/database.hpp, with the same error policy and the same threading rule.
//
// Errors: every failure is a StorageError (Kind kEngine unless a more specific kind applies)
// carrying the SQLSTATE, classified by storage_error.cpp; transient() is true for what a retry can
// heal: the connection lost or not established (class 08, and a lost connection without one), the
// server shutting down or starting (57P01-57P03), serialization failure and deadlock (40001,
// 40P01), a lock not granted in time (55P03), a query cancelled (57014), out of resources (class
// 53: disk full, too many connections, ...), I/O (class 58) and a read-only server (25006: a
// standby being promoted). Everything else (SQL, constraint, permission, a missing database or
// role, a foreign or newer schema) is permanent. After a lost connection the same PgDatabase
// reconnects at its next statement outside a transaction, so a caller heals a transient failure by
// retrying; with OpenOptions::connect_later that includes a server unreachable at the open.
//
// A statement without a reply within OpenOptions::reply_timeout_ms fails transient (08006) and
// its connection is set aside, not closed: no second session is opened while the server still
// owes the first its reply (a stalled server, or one holding commits for a synchronous standby,
// would otherwise fill up with magcal backends, one per retry), and every statement meanwhile
// fails at once. Once the reply comes (or the connection breaks, or kSetAsideLimit has passed:
// a frozen host may have been replaced by a standby the URI also reaches) the connection is
// replaced by a fresh one. A COMMIT set aside may still commit: its caller's retry must be
// idempotent (every magcal write is: ON CONFLICT on the natural keys). No cancel is sent: a
// cancel would have the server end a synchronous-replication wait by committing locally only.
//
// Threads: one PgDatabase (one connection) belongs to one thread at a time; give each thread its
// own, as with SQLite.
//
// Schema: numbered migrations (storage/postgres/pg_migrations.hpp), version N the same schema as
// SQLite's version N, recorded one row per version in magcal_schema_version with
// kApplicationId, the marker of a magcal database. A database whose current schema holds other
// tables but not that one is foreign and refused, as is a version newer than this code knows.
// Migrations run under a transaction-scoped advisory lock (kPgMigrationLock), each in its own
// transaction that re-reads the version under the lock: daemons starting together migrate once.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <unordered_map>

#include "storage/connection.hpp"
#include "storage/postgres/pg_query.hpp"
#include "storage/sql_statement.hpp"

struct pg_conn;  // libpq's PGconn; <libpq-fe.h> stays out of public headers

namespace magcal::storage {

// The advisory lock (two-key form: class, object) held while migrating. Other magcal advisory
// locks use kApplicationId as class too, with other objects.
constexpr int32_t kPgLockClass = kApplicationId;
constexpr int32_t kPgMigrationLock = 1;

class PgDatabase final : public Connection, public SqlSession {
 public:
  // `uri`: any libpq connection URI (postgresql:// or postgres://, e.g. with ?host=/socket/dir).
  // Options as for SQLite: read_only never migrates or writes (the session is read-only);
  // migrate_to builds an old schema for tests (0: connects without reading or checking the
  // schema, for administration such as CREATE DATABASE); busy_timeout_ms becomes lock_timeout (a
  // row or table lock not granted in time fails transient, as SQLite's busy timeout does). Throws
  // StorageError.
  explicit PgDatabase(const std::string& uri, const OpenOptions& options = {});
  ~PgDatabase();

  // The newest schema this build's PostgreSQL migrations make (postgres/migrations/*.sql).
  static int latest_schema_version();
  // The version recorded in the database (0: none).
  int schema_version();

  // The URI without its password, for messages and logs.
  const std::string& name() const override { return name_; }
  bool read_only() const override { return read_only_; }

  // Runs one or more SQL statements without parameters or results (DDL, SET, tests).
  void exec(std::string_view sql) override;
  // One statement with $1..$n parameters.
  PgResult execute(std::string_view sql, const PgParams& params = {},
                   PgFormat format = PgFormat::kText);
  // The same, prepared once per connection (keyed by the SQL text): for statements a writer or
  // reader repeats. Parameter types are taken from `params` at the first call.
  PgResult execute_prepared(std::string_view sql, const PgParams& params = {},
                            PgFormat format = PgFormat::kText);

  // How long a connection whose statement got no reply in time waits aside for that reply before
  // it is closed and a new session opened (see the header comment).
  static constexpr std::chrono::seconds kSetAsideLimit{300};

  // The server process of this connection (pg_stat_activity.pid, pg_terminate_backend).
  int backend_pid() const;
  // Inside a transaction (PgTransaction, or an explicit BEGIN).
  bool in_transaction() const;

  // pg_xact_status() of the transaction, on this connection once it can be used (a connection
  // set aside settles first). Its COMMIT may still be in progress (held for a synchronous
  // standby): transient StorageError then. A transaction too old for the server to know is taken
  // as rolled back (every magcal write is idempotent: see the header comment).
  CommitOutcome commit_outcome(int64_t transaction_id) override;

  std::unique_ptr<SampleWindowStore> make_sample_window_store() override;
  std::unique_ptr<FilterStateStore> make_filter_state_store() override;
  std::unique_ptr<CalibrationHistory> make_calibration_history() override;
  std::unique_ptr<LeaseStore> make_lease_store() override;

  // SqlSession (storage/postgres/pg_sql_session.cpp): statements run by execute_prepared(),
  // numbers in binary.
  std::unique_ptr<SqlStatement> prepare(std::string_view sql) override;
  const char* byte_order() const override { return " COLLATE \"C\""; }
  const char* lock_rows_shared() const override { return " FOR SHARE"; }
  const char* json_array_texts() const override {
    return "SELECT json_array_elements_text(?1::json)";
  }

 private:
  friend class PgTransaction;
  SqlSession& sql_session() override { return *this; }

  // Transactions (storage::Transaction, PgTransaction): BEGIN at the isolation level, or
  // SAVEPOINT magcal_tx_<depth> inside an open transaction (returns true then).
  enum class Isolation { kReadCommitted, kRepeatableRead, kSerializable };
  bool begin(Isolation isolation);
  // A write is READ COMMITTED (row locks as statements touch them), a read snapshot REPEATABLE
  // READ (one snapshot for all its statements).
  bool begin_transaction(TransactionMode mode) override;
  void commit_transaction(bool nested) override;
  void end_transaction(bool nested, bool committed) noexcept override;
  // One or more statements without parameters (the simple query protocol): the last result.
  PgResult simple_query(std::string_view sql);

  // connect(), configure() and check_and_migrate(): what the open does, at the first
  // statement when the server was unreachable then (OpenOptions::connect_later).
  void open_session();
  // Opens conn_. The connect runs on its own thread (libpq's blocking connect, which keeps its
  // connect_timeout per host and its multi-host order); this waits for it at most the open's
  // wait (OpenOptions::connect_later: 2 s at the open, 100 ms at a reconnect or at an open while
  // another connect of this process to the URI is unanswered, so a daemon's worker never blocks
  // on a server that does not answer; otherwise until it ends), and
  // throws transient while it is still in flight. The next call picks the same connect up.
  void connect();
  // Reconnects a lost connection, outside a transaction (see the header comment).
  void ensure_connected();
  void configure();
  void check_and_migrate(const OpenOptions& options);
  PgResult checked(pg_result* result, std::string_view sql);
  // The reply to a statement just sent (`sent`: what PQsend* returned), read without blocking
  // past the reply deadline: the last result, or the first error result. Past the deadline the
  // connection is set aside and a transient StorageError thrown.
  pg_result* await_reply(int sent, std::string_view sql);
  // A connection set aside: returns once it is closed (its reply came, it broke, or it waited
  // kSetAsideLimit), so that a new session may be opened; throws the transient error again while
  // it still waits.
  void settle_set_aside();
  // Closes the connection; the next statement opens a new session.
  void drop_connection() noexcept;
  // A connect still in flight is left to its thread, which closes what it opens.
  void abandon_pending_connect() noexcept;
  [[noreturn]] void fail(std::string_view context, const pg_result* result = nullptr);

  pg_conn* conn_ = nullptr;
  std::string uri_;
  std::string name_;
  bool read_only_ = false;
  int lock_timeout_ms_ = 5000;
  int reply_timeout_ms_ = 10000;
  // A statement sent on conn_ got no reply in time (see the header comment): since when, and
  // what it was (for messages).
  bool set_aside_ = false;
  std::chrono::steady_clock::time_point set_aside_since_;
  std::string set_aside_statement_;
  OpenOptions open_options_;
  bool schema_checked_ = false;  // open_session() went through once
  int open_transactions_ = 0;    // transactions and savepoints open on this connection
  // The id of the open top-level write transaction (0: none, or a read snapshot), for a COMMIT
  // in doubt (StorageError::in_doubt_transaction()).
  int64_t transaction_id_ = 0;
  std::unordered_map<std::string, std::string> prepared_;  // SQL text -> statement name
  struct PendingConnect;                                   // shared with the thread that connects
  std::shared_ptr<PendingConnect> pending_connect_;
  bool conn_attempted_ = false;  // a connect was tried (later ones wait less: see connect())
};

// storage::Transaction at a chosen isolation level (fleet code that needs REPEATABLE READ or
// SERIALIZABLE for a write). The same nesting and rollback as storage::Transaction.
class PgTransaction : public Transaction {
 public:
  using Isolation = PgDatabase::Isolation;
  explicit PgTransaction(PgDatabase& db, Isolation isolation = Isolation::kReadCommitted)
      : Transaction(db, db.begin(isolation)) {}
};

}  // namespace magcal::storage
