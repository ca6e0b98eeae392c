#include "storage/postgres/pg_database.hpp"

#include <libpq-fe.h>
#include <poll.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <string_view>
#include <thread>
#include <unordered_map>
#include <utility>

#include "pipeline/time_utc.hpp"
#include "storage/postgres/pg_calibration_history.hpp"
#include "storage/postgres/pg_filter_state_store.hpp"
#include "storage/postgres/pg_lease_store.hpp"
#include "storage/postgres/pg_migrations.hpp"
#include "storage/postgres/pg_sample_window_store.hpp"

namespace magcal::storage {
namespace {

// libpq's message on one line (it continues lines with "\n\t" hints): a caller prints one line.
std::string one_line(std::string_view text) {
  std::string out;
  while (!text.empty()) {
    const std::size_t end = std::min(text.find('\n'), text.size());
    std::string_view line = text.substr(0, end);
    text.remove_prefix(std::min(end + 1, text.size()));
    const std::size_t first = line.find_first_not_of(" \t");
    if (first == std::string_view::npos) continue;
    line = line.substr(first, line.find_last_not_of(" \t") - first + 1);
    // libpq's continuation lines are sentences ("Is the server running ...?"): one ends where
    // a line did, unless it ended with punctuation already.
    if (!out.empty()) {
      out += std::string_view(".:;?!").find(out.back()) == std::string_view::npos ? ". " : " ";
    }
    out += line;
  }
  return out;
}

// A statement for messages: its first line, at most 60 characters.
std::string statement_summary(std::string_view sql) {
  const std::size_t first = sql.find_first_not_of(" \t\n");
  sql = first == std::string_view::npos ? std::string_view() : sql.substr(first);
  sql = sql.substr(0, sql.find('\n'));
  if (sql.size() <= 60) return std::string(sql);
  return std::string(sql.substr(0, 57)) + "...";
}

// "10 s", "2.5 s", "250 ms".
std::string duration_text(double seconds) {
  if (seconds < 1.0) return std::to_string(std::lround(seconds * 1000.0)) + " ms";
  std::string text = std::to_string(std::round(seconds * 10.0) / 10.0);
  text.erase(text.find_last_not_of('0') + 1);
  if (text.back() == '.') text.pop_back();
  return text + " s";
}

// The bookkeeping table: one row per applied migration. Created with migration 1 (the code's
// counterpart of SQLite's PRAGMA user_version / application_id).
constexpr const char* kCreateVersionTable = R"sql(
CREATE TABLE magcal_schema_version (
  version          bigint NOT NULL PRIMARY KEY,
  name             text   NOT NULL,
  application_id   bigint NOT NULL,  -- kApplicationId: this is a magcal database
  software_version text   NOT NULL,  -- magcal that applied it
  applied_utime    bigint NOT NULL   -- wall clock
))sql";

}  // namespace

struct PgDatabase::PendingConnect {
  std::mutex mutex;
  std::condition_variable done_cv;
  pg_conn* conn = nullptr;
  bool done = false;
  bool abandoned = false;  // its PgDatabase is gone: the thread closes what it opened
  std::chrono::steady_clock::time_point started = std::chrono::steady_clock::now();

  // This process's connects to each URI that its server left unanswered past an open's wait.
  // An open meanwhile waits as a reconnect does: a daemon opens three connections (worker,
  // refit, operations server) one after the other, and a frozen server must not hold its start
  // up for three waits.
  static std::shared_ptr<PendingConnect> unanswered(const std::string& uri) {
    std::lock_guard lock(unanswered_mutex);
    const auto it = unanswered_by_uri.find(uri);
    if (it == unanswered_by_uri.end()) return nullptr;
    auto pending = it->second.lock();
    if (!pending) unanswered_by_uri.erase(it);
    return pending;
  }
  static void set_unanswered(const std::string& uri, const std::shared_ptr<PendingConnect>& p) {
    std::lock_guard lock(unanswered_mutex);
    unanswered_by_uri[uri] = p;
  }
  bool answered() {
    std::lock_guard lock(mutex);
    return done;
  }
  static inline std::mutex unanswered_mutex;
  static inline std::unordered_map<std::string, std::weak_ptr<PendingConnect>> unanswered_by_uri;
};

PgDatabase::PgDatabase(const std::string& uri, const OpenOptions& options)
    : uri_(uri),
      name_(database_name(uri)),
      read_only_(options.read_only),
      lock_timeout_ms_(options.busy_timeout_ms),
      reply_timeout_ms_(options.reply_timeout_ms),
      open_options_(options) {
  char* error = nullptr;
  PQconninfoOption* parsed = PQconninfoParse(uri.c_str(), &error);
  if (parsed == nullptr || !is_postgres_uri(uri)) {
    const std::string why = error ? without_database_secrets(uri, one_line(error))
                                  : "not a postgresql:// or postgres:// URI";
    PQfreemem(error);
    PQconninfoFree(parsed);
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "invalid PostgreSQL URI " + name_ + ": " + why);
  }
  PQconninfoFree(parsed);
  try {
    open_session();
  } catch (const StorageError& e) {
    // Unreachable now: the first statement opens the session (OpenOptions::connect_later).
    if (!options.connect_later || !e.transient()) throw;
  }
}

void PgDatabase::open_session() {
  connect();
  try {
    configure();
    check_and_migrate(open_options_);
  } catch (...) {
    // A connection set aside stays open until its reply (settle_set_aside): closing it now would
    // leave its statement running in the server and open another session at each retry.
    if (!set_aside_) drop_connection();
    throw;
  }
  schema_checked_ = true;
}

PgDatabase::~PgDatabase() {
  PQfinish(conn_);
  abandon_pending_connect();
}

void PgDatabase::abandon_pending_connect() noexcept {
  if (!pending_connect_) return;
  std::lock_guard lock(pending_connect_->mutex);
  pending_connect_->abandoned = true;
  PQfinish(std::exchange(pending_connect_->conn, nullptr));  // done but not taken
}

void PgDatabase::connect() {
  if (!pending_connect_) {
    auto pending = std::make_shared<PendingConnect>();
    std::thread([pending, uri = uri_] {
      // Defaults the URI may override (keywords before dbname yield to the expanded URI): a
      // dead network fails a connect in 10 s and a statement in about 30 s (TCP keepalives,
      // user timeout) instead of the kernel's ~15 min, so the caller's retry policy decides.
      const char* keywords[] = {"connect_timeout",
                                "keepalives_idle",
                                "keepalives_interval",
                                "keepalives_count",
                                "tcp_user_timeout",
                                "fallback_application_name",
                                "dbname",
                                nullptr};
      const char* values[] = {"10", "30", "10", "3", "30000", "magcal", uri.c_str(), nullptr};
      pg_conn* conn = PQconnectdbParams(keywords, values, 1);
      std::lock_guard lock(pending->mutex);
      if (pending->abandoned) {
        PQfinish(conn);
        return;
      }
      pending->conn = conn;
      pending->done = true;
      pending->done_cv.notify_all();
    }).detach();
    pending_connect_ = std::move(pending);
  }
  {
    // (Before the lock: answered() locks another connect's mutex.)
    const bool reconnect = schema_checked_ || conn_attempted_;
    const auto unanswered = reconnect ? nullptr : PendingConnect::unanswered(uri_);
    const bool short_wait = reconnect || (unanswered != nullptr && !unanswered->answered());
    std::unique_lock lock(pending_connect_->mutex);
    const auto done = [this] { return pending_connect_->done; };
    if (!open_options_.connect_later) {
      pending_connect_->done_cv.wait(lock, done);
    } else if (!pending_connect_->done_cv.wait_for(
                   lock,
                   short_wait ? std::chrono::milliseconds(100) : std::chrono::milliseconds(2000),
                   done)) {
      lock.unlock();
      PendingConnect::set_unanswered(uri_, pending_connect_);
      conn_attempted_ = true;
      const double connecting_s = std::chrono::duration<double>(std::chrono::steady_clock::now() -
                                                                pending_connect_->started)
                                      .count();
      throw StorageError(StorageError::Kind::kEngine,
                         "cannot connect to " + name_ + ": no answer after " +
                             duration_text(connecting_s) +
                             " (still connecting; libpq's connect_timeout, 10 s a host, ends it)",
                         StorageError::Condition::kUnavailable);
    }
    conn_ = std::exchange(pending_connect_->conn, nullptr);
  }
  pending_connect_.reset();
  conn_attempted_ = true;
  if (conn_ == nullptr) throw std::bad_alloc();
  if (PQstatus(conn_) == CONNECTION_OK) return;
  // libpq gives no SQLSTATE for a refused connection: the server's reasons that a retry
  // cannot heal are told by their (English) text; anything else (no server, starting up, too
  // many clients, network) is transient.
  const std::string why = without_database_secrets(uri_, one_line(PQerrorMessage(conn_)));
  PQfinish(conn_);
  conn_ = nullptr;
  const bool no_database = why.find("database \"") != std::string::npos &&
                           why.find("does not exist") != std::string::npos;
  const bool refused = why.find("does not exist") != std::string::npos ||
                       why.find("authentication failed") != std::string::npos ||
                       why.find("pg_hba.conf") != std::string::npos ||
                       why.find("password") != std::string::npos;
  std::string message = "cannot connect to " + name_ + ": " + why;
  // libpq's bare words for its connect_timeout: a server that accepts the connection and never
  // answers (frozen, overloaded, a silent network), not a refused one.
  if (why.ends_with("timeout expired")) {
    message +=
        " (no answer within libpq's connect_timeout, 10 s a host unless the URI sets it: the "
        "server accepts connections but does not answer: frozen, overloaded or a silent "
        "network)";
  }
  // The two refusals a new fleet meets first: say where the fix is.
  if (no_database || (why.find("role \"") != std::string::npos &&
                      why.find("does not exist") != std::string::npos)) {
    message +=
        " (create the role and the database as docs/fleet.md \"Create the database and its "
        "role\" shows: deploy/fleet/create-database.sql)";
  }
  if (no_database) throw StorageError::postgres(StorageError::Kind::kNotFound, message, "3D000");
  if (refused) throw StorageError::postgres(StorageError::Kind::kEngine, message, "28000");
  throw StorageError::postgres(StorageError::Kind::kEngine, message, "08001");
}

void PgDatabase::ensure_connected() {
  if (set_aside_) settle_set_aside();
  if (conn_ != nullptr && PQstatus(conn_) == CONNECTION_OK) return;
  if (open_transactions_ > 0) {
    // The transaction is gone with the connection: its caller must start over.
    throw StorageError::postgres(StorageError::Kind::kEngine,
                                 name_ + ": connection lost inside a transaction", "08006");
  }
  drop_connection();
  if (!schema_checked_) {
    // Unreachable at the open (connect_later), or lost during its checks: all of them now.
    open_session();
    return;
  }
  connect();
  configure();
}

void PgDatabase::configure() {
  // Notices (e.g. "table exists, skipping") are not errors; storage/ does not log.
  PQsetNoticeProcessor(
      conn_, [](void*, const char*) {}, nullptr);
  // extra_float_digits > 0: doubles in text are exact (shortest round trip) whatever the
  // server's configuration says.
  std::string settings = "SET extra_float_digits = 3; SET client_encoding = 'UTF8'; ";
  settings += "SET lock_timeout = " + std::to_string(lock_timeout_ms_);
  if (read_only_) settings += "; SET default_transaction_read_only = on";
  // Statements are sent and their replies awaited without blocking (await_reply).
  if (PQsetnonblocking(conn_, 1) != 0) fail("PQsetnonblocking");
  checked(await_reply(PQsendQuery(conn_, settings.c_str()), settings), settings);
}

pg_result* PgDatabase::await_reply(int sent, std::string_view sql) {
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  const bool bounded = reply_timeout_ms_ > 0;
  const auto deadline = start + std::chrono::milliseconds(reply_timeout_ms_);
  pg_result* kept = nullptr;
  const auto failed = [](const pg_result* r) {
    return PQresultStatus(r) != PGRES_COMMAND_OK && PQresultStatus(r) != PGRES_TUPLES_OK;
  };
  int flush = sent == 0 ? -1 : 1;  // PQflush: 1 while output is queued, -1 on failure
  while (flush >= 0) {
    if (flush == 1) flush = PQflush(conn_);
    if (flush < 0) break;
    if (flush == 0 && !PQisBusy(conn_)) {
      pg_result* r = PQgetResult(conn_);
      if (r == nullptr) return kept;  // the whole reply
      // PQexec's rule: the last result, but an error one is kept over later ones.
      if (kept != nullptr && failed(kept) && !failed(r)) {
        PQclear(r);
      } else {
        PQclear(kept);
        kept = r;
      }
      continue;
    }
    int wait_ms = -1;
    if (bounded) {
      const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - clock::now());
      if (left.count() <= 0) {
        PQclear(kept);
        set_aside_ = true;
        set_aside_since_ = start;
        set_aside_statement_ = statement_summary(sql);
        throw StorageError(
            StorageError::Kind::kEngine,
            name_ + ": no reply within " + duration_text(reply_timeout_ms_ / 1000.0) + " to " +
                set_aside_statement_ +
                " (the server accepts the connection but does not answer: frozen or overloaded, "
                "or holding commits for a synchronous standby that is down)",
            StorageError::Condition::kUnavailable);
      }
      wait_ms = static_cast<int>(left.count());
    }
    pollfd fd{PQsocket(conn_), static_cast<short>(POLLIN | (flush == 1 ? POLLOUT : 0)), 0};
    const int ready = ::poll(&fd, 1, wait_ms);
    if (ready < 0 && errno != EINTR) break;
    if (ready > 0 && (fd.revents & (POLLIN | POLLERR | POLLHUP)) != 0 &&
        PQconsumeInput(conn_) == 0) {
      break;
    }
  }
  // Not sent, or the connection broke: the server's reply is lost with it.
  PQclear(kept);
  const std::string why = one_line(PQerrorMessage(conn_));
  drop_connection();
  throw StorageError::postgres(
      StorageError::Kind::kEngine,
      name_ + ": " + (why.empty() ? statement_summary(sql) + " failed" : why) + " (SQLSTATE 08006)",
      "08006");
}

void PgDatabase::settle_set_aside() {
  const auto waited = std::chrono::steady_clock::now() - set_aside_since_;
  // Everything the server sent so far (an error and then the end of the connection come apart).
  bool alive = true;
  for (pollfd fd{PQsocket(conn_), POLLIN, 0}; alive;) {
    alive = PQconsumeInput(conn_) != 0 && PQflush(conn_) >= 0;
    while (alive && !PQisBusy(conn_)) {
      pg_result* r = PQgetResult(conn_);
      // A FATAL error ends the session (the server closes it next).
      const char* severity = r ? PQresultErrorField(r, PG_DIAG_SEVERITY_NONLOCALIZED) : nullptr;
      const bool fatal = severity != nullptr && std::string_view(severity) != "ERROR";
      PQclear(r);
      if (r == nullptr || fatal) {
        drop_connection();  // answered at last: a new session from here (no transaction left)
        return;
      }
    }
    if (::poll(&fd, 1, 0) <= 0 || (fd.revents & (POLLIN | POLLERR | POLLHUP)) == 0) break;
  }
  if (alive && PQstatus(conn_) == CONNECTION_OK) {
    if (waited < kSetAsideLimit) {
      throw StorageError(
          StorageError::Kind::kEngine,
          name_ + ": still no reply to " + set_aside_statement_ + ", sent " +
              duration_text(std::chrono::duration<double>(waited).count()) +
              " ago (the server accepts the connection but does not answer); no new session "
              "before it answers or " +
              duration_text(static_cast<double>(kSetAsideLimit.count())) + " have passed",
          StorageError::Condition::kUnavailable);
    }
  }
  drop_connection();  // broke, or waited kSetAsideLimit
}

void PgDatabase::drop_connection() noexcept {
  PQfinish(conn_);
  conn_ = nullptr;
  set_aside_ = false;
  prepared_.clear();
}

void PgDatabase::fail(std::string_view context, const pg_result* result) {
  const char* state = result ? PQresultErrorField(result, PG_DIAG_SQLSTATE) : nullptr;
  const char* primary = result ? PQresultErrorField(result, PG_DIAG_MESSAGE_PRIMARY) : nullptr;
  std::string sqlstate = state ? state : "";
  std::string message = primary ? primary : "";
  if (message.empty()) {
    message = one_line(result ? PQresultErrorMessage(result) : "");
    if (message.empty() && conn_ != nullptr) message = one_line(PQerrorMessage(conn_));
  }
  if (sqlstate.empty()) {
    // Failed in libpq, not on the server: a lost connection is connection_failure.
    const bool lost = conn_ == nullptr || PQstatus(conn_) == CONNECTION_BAD;
    sqlstate = lost ? "08006" : "XX000";
  }
  if (message.empty()) message = std::string(context) + " failed";
  const auto kind =
      sqlstate == "3D000" ? StorageError::Kind::kNotFound : StorageError::Kind::kEngine;
  throw StorageError::postgres(kind, name_ + ": " + message + " (SQLSTATE " + sqlstate + ")",
                               sqlstate);
}

PgResult PgDatabase::checked(pg_result* raw, std::string_view sql) {
  PgResult result(raw);
  const ExecStatusType status = raw ? PQresultStatus(raw) : PGRES_FATAL_ERROR;
  if (status != PGRES_COMMAND_OK && status != PGRES_TUPLES_OK) fail(sql, raw);
  return result;
}

void PgDatabase::exec(std::string_view sql) {
  simple_query(sql);
}

PgResult PgDatabase::simple_query(std::string_view sql) {
  ensure_connected();
  const std::string text(sql);
  return checked(await_reply(PQsendQuery(conn_, text.c_str()), sql), sql);
}

PgResult PgDatabase::execute(std::string_view sql, const PgParams& params, PgFormat format) {
  ensure_connected();
  const std::string text(sql);
  return checked(await_reply(PQsendQueryParams(conn_, text.c_str(), params.size(), params.types(),
                                               params.values(), params.lengths(), params.formats(),
                                               format == PgFormat::kBinary ? 1 : 0),
                             sql),
                 sql);
}

PgResult PgDatabase::execute_prepared(std::string_view sql, const PgParams& params,
                                      PgFormat format) {
  ensure_connected();
  std::string text(sql);
  auto it = prepared_.find(text);
  if (it == prepared_.end()) {
    std::string name = "magcal_" + std::to_string(prepared_.size() + 1);
    checked(
        await_reply(PQsendPrepare(conn_, name.c_str(), text.c_str(), params.size(), params.types()),
                    sql),
        sql);
    it = prepared_.emplace(std::move(text), std::move(name)).first;
  }
  return checked(
      await_reply(PQsendQueryPrepared(conn_, it->second.c_str(), params.size(), params.values(),
                                      params.lengths(), params.formats(),
                                      format == PgFormat::kBinary ? 1 : 0),
                  sql),
      sql);
}

int PgDatabase::backend_pid() const {
  return conn_ ? PQbackendPID(conn_) : 0;
}

bool PgDatabase::in_transaction() const {
  return conn_ != nullptr && PQtransactionStatus(conn_) != PQTRANS_IDLE &&
         PQtransactionStatus(conn_) != PQTRANS_UNKNOWN;
}

Connection::CommitOutcome PgDatabase::commit_outcome(int64_t transaction_id) {
  PgParams p;
  p.add(std::to_string(transaction_id));
  const PgResult r = execute("SELECT pg_xact_status($1::xid8)", p);
  if (r.is_null(0, 0)) return CommitOutcome::kRolledBack;  // too old to know
  const std::string status = r.get_text(0, 0);
  if (status == "committed") return CommitOutcome::kCommitted;
  if (status == "aborted") return CommitOutcome::kRolledBack;
  throw StorageError(StorageError::Kind::kEngine,
                     name_ + ": the COMMIT of transaction " + std::to_string(transaction_id) +
                         " is still in progress on the server (held, e.g. for a synchronous "
                         "standby that is down)",
                     StorageError::Condition::kUnavailable);
}

int PgDatabase::latest_schema_version() {
  return static_cast<int>(pg_migrations().size());
}

namespace {

// What the database's current schema holds, as far as opening it is concerned.
struct SchemaState {
  bool has_version_table = false;
  int64_t relations = 0;     // tables, views, ... in the current schema
  int64_t version = 0;       // newest applied migration
  int64_t foreign_rows = 0;  // version rows with another application_id
  std::string schema;        // current_schema()
};

SchemaState read_schema_state(PgDatabase& db) {
  SchemaState s;
  const PgResult r = db.execute(
      "SELECT cs.name, "
      "       count(c.oid) FILTER (WHERE c.relname = 'magcal_schema_version'), count(c.oid) "
      "FROM (SELECT current_schema() AS name) cs "
      "LEFT JOIN pg_namespace n ON n.nspname = cs.name "
      "LEFT JOIN pg_class c ON c.relnamespace = n.oid AND c.relkind IN ('r', 'p', 'v', 'm', 'f') "
      "GROUP BY cs.name");
  if (r.is_null(0, 0)) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       db.name() + ": no schema to use (search_path names none that exists)");
  }
  s.schema = r.get_text(0, 0);
  s.has_version_table = r.get_int64(0, 1) > 0;
  s.relations = r.get_int64(0, 2);
  if (s.has_version_table) {
    PgParams p;
    p.add(int64_t{kApplicationId});
    const PgResult v = db.execute(
        "SELECT coalesce(max(version), 0), count(*) FILTER (WHERE application_id <> $1) "
        "FROM magcal_schema_version",
        p);
    s.version = v.get_int64(0, 0);
    s.foreign_rows = v.get_int64(0, 1);
  }
  return s;
}

}  // namespace

int PgDatabase::schema_version() {
  return static_cast<int>(read_schema_state(*this).version);
}

void PgDatabase::check_and_migrate(const OpenOptions& options) {
  const auto all = pg_migrations();
  const int latest = static_cast<int>(all.size());
  const int target = migration_target(options, latest);
  auto check = [&](const SchemaState& s) {
    if (!s.has_version_table && s.relations == 0) return;  // empty: ours to initialise
    if (!s.has_version_table) {
      throw StorageError(StorageError::Kind::kForeignFile,
                         name_ + " is not a magcal database (schema " + s.schema + " holds " +
                             std::to_string(s.relations) +
                             " tables or views, none magcal_schema_version)");
    }
    if (s.foreign_rows > 0) {
      throw StorageError(StorageError::Kind::kForeignFile,
                         name_ +
                             " is not a magcal database (magcal_schema_version has another "
                             "application_id)");
    }
    if (s.version > latest) {
      throw StorageError(StorageError::Kind::kNewerSchema,
                         name_ + " has schema version " + std::to_string(s.version) +
                             ", newer than this magcal knows (" + std::to_string(latest) +
                             "): upgrade magcal");
    }
  };

  if (target == 0) return;  // no schema wanted: nothing to check (see OpenOptions::migrate_to)
  SchemaState state = read_schema_state(*this);
  check(state);
  if (state.version >= target) return;
  if (options.read_only) {
    // magcald's own read-only connection (connect_later) opens while its worker may still be
    // migrating (a migration that outlasted the reply deadline): not yet, rather than never.
    const auto condition = options.connect_later ? StorageError::Condition::kUnavailable
                                                 : StorageError::Condition::kNone;
    if (state.version == 0) {
      throw StorageError(StorageError::Kind::kForeignFile,
                         name_ +
                             " has no magcal tables yet (a new database): magcald creates "
                             "them on its first start",
                         condition);
    }
    throw StorageError(StorageError::Kind::kOlderSchema,
                       name_ + " has schema version " + std::to_string(state.version) +
                           "; open it once read-write (magcald or magcal refit) to upgrade",
                       condition);
  }
  // Each migration in its own transaction under the advisory lock; re-read the version under
  // the lock because another daemon may have migrated meanwhile. The lock is released at
  // commit, or by the server when a holder dies. A migration (or the wait for another daemon's)
  // that outlasts the reply deadline goes on in the server: the connection is set aside, the
  // open fails transient (a daemon rides it out as an outage) and finds it done later.
  for (const Migration& m : all) {
    if (m.version > target) break;
    PgTransaction tx(*this);
    // A migrating process is making progress (or dead, which frees the lock): a command waits
    // for it. A daemon (connect_later) does not: a wait past its lock timeout is an outage it
    // rides out, and a wait of its own connection set aside past the reply deadline would, once
    // granted, leave the lock held by a session no thread reads (another of its connections
    // then waited for it for ever: a first start while the standby held the migration).
    if (!open_options_.connect_later) exec("SET LOCAL lock_timeout = 0");
    exec("SELECT pg_advisory_xact_lock(" + std::to_string(kPgLockClass) + ", " +
         std::to_string(kPgMigrationLock) + ")");
    state = read_schema_state(*this);
    check(state);
    if (m.version <= state.version) continue;
    if (m.version != state.version + 1) {
      throw StorageError::postgres(StorageError::Kind::kEngine,
                                   "migration gap before " + std::string(m.name), "XX000");
    }
    if (!state.has_version_table) exec(kCreateVersionTable);
    exec(m.sql);
    PgParams p;
    p.add(int64_t{m.version}).add(m.name).add(int64_t{kApplicationId}).add(MAGCAL_VERSION);
    p.add(magcal::now_utime());
    execute(
        "INSERT INTO magcal_schema_version "
        "(version, name, application_id, software_version, applied_utime) "
        "VALUES ($1, $2, $3, $4, $5)",
        p);
    tx.commit();
  }
}

bool PgDatabase::begin(Isolation isolation) {
  if (open_transactions_ == 0) ensure_connected();
  const bool nested = in_transaction();
  if (nested) {
    exec("SAVEPOINT magcal_tx_" + std::to_string(open_transactions_));
  } else {
    // A writer learns its transaction id in the same round trip: a COMMIT without a reply is
    // then resolved by commit_outcome().
    transaction_id_ = 0;
    switch (isolation) {
      case Isolation::kReadCommitted:
        transaction_id_ =
            simple_query("BEGIN; SELECT pg_current_xact_id()::text::bigint").get_int64(0, 0);
        break;
      case Isolation::kRepeatableRead:
        exec("BEGIN ISOLATION LEVEL REPEATABLE READ");
        break;
      case Isolation::kSerializable:
        transaction_id_ =
            simple_query(
                "BEGIN ISOLATION LEVEL SERIALIZABLE; SELECT pg_current_xact_id()::text::bigint")
                .get_int64(0, 0);
        break;
    }
  }
  ++open_transactions_;
  return nested;
}

bool PgDatabase::begin_transaction(TransactionMode mode) {
  return begin(mode == TransactionMode::kWrite ? Isolation::kReadCommitted
                                               : Isolation::kRepeatableRead);
}

void PgDatabase::commit_transaction(bool nested) {
  // COMMIT of a transaction an earlier statement aborted "succeeds" as a ROLLBACK: refuse it.
  if (conn_ != nullptr && PQtransactionStatus(conn_) == PQTRANS_INERROR) {
    throw StorageError::postgres(
        StorageError::Kind::kEngine,
        name_ + ": cannot commit, an earlier statement of the transaction failed", "25P02");
  }
  if (nested) {
    exec("RELEASE SAVEPOINT magcal_tx_" + std::to_string(open_transactions_ - 1));
    return;
  }
  const bool sendable = conn_ != nullptr && PQstatus(conn_) == CONNECTION_OK && !set_aside_;
  try {
    exec("COMMIT");
  } catch (StorageError& e) {
    // Sent, and no reply (none in time, or the connection broke): it may have committed.
    const bool unanswered = set_aside_ || conn_ == nullptr || PQstatus(conn_) != CONNECTION_OK;
    if (sendable && unanswered && transaction_id_ != 0) e.set_in_doubt_transaction(transaction_id_);
    throw;
  }
}

void PgDatabase::end_transaction(bool nested, bool committed) noexcept {
  --open_transactions_;
  if (!nested) transaction_id_ = 0;
  // A connection set aside still owes a reply: the server rolls back what it holds open when
  // the connection is closed (settle_set_aside).
  if (committed || set_aside_ || conn_ == nullptr || PQstatus(conn_) != CONNECTION_OK) return;
  const std::string savepoint = "magcal_tx_" + std::to_string(open_transactions_);
  const std::string sql =
      nested ? "ROLLBACK TO SAVEPOINT " + savepoint + "; RELEASE SAVEPOINT " + savepoint
             : "ROLLBACK";
  try {
    PQclear(await_reply(PQsendQuery(conn_, sql.c_str()), sql));
  } catch (const StorageError&) {
    // No reply, or the connection broke: the server rolls back when the connection goes.
  }
}

std::unique_ptr<SampleWindowStore> PgDatabase::make_sample_window_store() {
  return std::make_unique<PgSampleWindowStore>(*this);
}

std::unique_ptr<FilterStateStore> PgDatabase::make_filter_state_store() {
  return std::make_unique<PgFilterStateStore>(*this);
}

std::unique_ptr<CalibrationHistory> PgDatabase::make_calibration_history() {
  return std::make_unique<PgCalibrationHistory>(*this);
}

std::unique_ptr<LeaseStore> PgDatabase::make_lease_store() {
  return std::make_unique<PgLeaseStore>(*this);
}

}  // namespace magcal::storage
