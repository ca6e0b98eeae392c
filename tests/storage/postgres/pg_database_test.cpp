// The PostgreSQL connection against a real server started by the test (pg_test_server.hpp):
// migrations on an empty database, re-open without migrating, newer / foreign / older schemas,
// concurrent openers migrating once, the same tables and columns as SQLite in 64-bit types,
// transient and permanent errors from real failures, and exact values both ways.
#include "storage/postgres/pg_database.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cctype>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <future>
#include <limits>
#include <map>
#include <optional>
#include <regex>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>

#include "storage/migrations.hpp"
#include "storage/postgres/pg_migrations.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"
#include "tests/process_support.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

using namespace magcal::storage;
using magcal::test::pg_server_or_skip;
using magcal::test::PgTestServer;

namespace {

int64_t query_int(PgDatabase& db, const std::string& sql) {
  const PgResult r = db.execute(sql);
  REQUIRE(r.rows() == 1);
  return r.get_int64(0, 0);
}

// The error of `action`, which must throw a StorageError.
template <typename Action>
StorageError error_of(Action&& action) {
  try {
    action();
  } catch (const StorageError& e) {
    return e;
  }
  FAIL("no StorageError");
  throw std::logic_error("unreachable");
}

StorageError open_error(const std::string& uri, OpenOptions options = {}) {
  return error_of([&] { PgDatabase db(uri, options); });
}

// table -> [(column, type, not null)] with SQLite's declared types written as PostgreSQL's.
using Columns = std::map<std::string, std::vector<std::string>>;

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

Columns sqlite_columns() {
  Database db(":memory:");
  const std::map<std::string, std::string> as_postgres = {
      {"INTEGER", "bigint"}, {"REAL", "double precision"}, {"TEXT", "text"}, {"BLOB", "bytea"}};
  Columns out;
  Statement tables(db, "SELECT name FROM sqlite_schema WHERE type = 'table' ORDER BY name");
  while (tables.step()) {
    const std::string table = tables.column_text(0);
    Statement cols(db, "SELECT name, type, \"notnull\" OR pk > 0 FROM pragma_table_info(?1)");
    cols.bind(1, std::string_view(table));
    while (cols.step()) {
      const std::string type = cols.column_text(1);
      INFO(table << "." << cols.column_text(0) << " " << type);
      REQUIRE(as_postgres.count(type) == 1);
      out[table].push_back(lower(cols.column_text(0)) + " " + as_postgres.at(type) +
                           (cols.column_int64(2) ? " not null" : ""));
    }
  }
  return out;
}

Columns postgres_columns(PgDatabase& db) {
  const PgResult r = db.execute(
      "SELECT table_name, column_name, data_type, is_nullable = 'NO' FROM "
      "information_schema.columns "
      "WHERE table_schema = current_schema() AND table_name <> 'magcal_schema_version' "
      "ORDER BY table_name, ordinal_position");
  Columns out;
  for (int i = 0; i < r.rows(); ++i) {
    out[r.get_text(i, 0)].push_back(r.get_text(i, 1) + " " + r.get_text(i, 2) +
                                    (r.get_bool(i, 3) ? " not null" : ""));
  }
  return out;
}

}  // namespace

TEST_CASE("PostgreSQL schema: migrations, re-open, foreign / newer / older schemas, openers") {
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  const std::string uri = server->create_database();

  SECTION("an empty database gets every migration once, marked as magcal's") {
    PgDatabase db(uri);
    CHECK(db.schema_version() == PgDatabase::latest_schema_version());
    CHECK(PgDatabase::latest_schema_version() == static_cast<int>(pg_migrations().size()));
    CHECK(query_int(db, "SELECT count(*) FROM magcal_schema_version") ==
          PgDatabase::latest_schema_version());
    CHECK(query_int(db, "SELECT count(*) FROM magcal_schema_version WHERE application_id = " +
                            std::to_string(kApplicationId)) == PgDatabase::latest_schema_version());
  }

  SECTION("version N is SQLite's version N: the same tables and columns, 64-bit types") {
    REQUIRE(pg_migrations().size() == migrations().size());
    for (std::size_t i = 0; i < migrations().size(); ++i) {
      CHECK(std::string(pg_migrations()[i].name) == migrations()[i].name);
    }
    PgDatabase db(uri);
    CHECK(postgres_columns(db) == sqlite_columns());
  }

  SECTION("re-opening an up-to-date database neither migrates nor waits for the migration lock") {
    { PgDatabase first(uri); }
    PgDatabase holder(uri);
    const int64_t applied_before =
        query_int(holder, "SELECT sum(applied_utime)::bigint FROM magcal_schema_version");
    holder.exec("SELECT pg_advisory_lock(" + std::to_string(kPgLockClass) + ", " +
                std::to_string(kPgMigrationLock) + ")");
    auto reopen = std::async(std::launch::async, [&] { PgDatabase again(uri); });
    const bool finished = reopen.wait_for(std::chrono::seconds(10)) == std::future_status::ready;
    holder.exec("SELECT pg_advisory_unlock_all()");
    reopen.get();
    CHECK(finished);
    CHECK(query_int(holder, "SELECT sum(applied_utime)::bigint FROM magcal_schema_version") ==
          applied_before);
  }

  SECTION("three openers at once on an empty database: each migration applied exactly once") {
    // Without the lock the losers fail (duplicate tables) or apply a migration twice.
    std::atomic<int> ready{0};
    std::vector<std::future<int>> openers;
    for (int i = 0; i < 3; ++i) {
      openers.push_back(std::async(std::launch::async, [&] {
        ++ready;
        while (ready < 3) std::this_thread::yield();
        PgDatabase db(uri);
        return db.schema_version();
      }));
    }
    for (auto& f : openers) CHECK(f.get() == PgDatabase::latest_schema_version());
    PgDatabase db(uri);
    CHECK(query_int(db, "SELECT count(*) FROM magcal_schema_version") ==
          PgDatabase::latest_schema_version());
  }

  SECTION("a database with a newer schema is refused, read-write and read-only") {
    {
      PgDatabase db(uri);
      db.exec("INSERT INTO magcal_schema_version VALUES (" +
              std::to_string(PgDatabase::latest_schema_version() + 1) + ", '9999_future', " +
              std::to_string(kApplicationId) + ", 'future', 0)");
    }
    CHECK(open_error(uri).kind() == StorageError::Kind::kNewerSchema);
    OpenOptions read_only;
    read_only.read_only = true;
    CHECK(open_error(uri, read_only).kind() == StorageError::Kind::kNewerSchema);
  }

  SECTION("a foreign database is refused and left untouched") {
    {
      PgDatabase db(uri, [] {
        OpenOptions none;
        none.migrate_to = 0;
        return none;
      }());
      db.exec("CREATE TABLE invoices (id bigint PRIMARY KEY)");
    }
    const StorageError e = open_error(uri);
    CHECK(e.kind() == StorageError::Kind::kForeignFile);
    CHECK_FALSE(e.transient());
    CHECK_THAT(e.what(), Catch::Contains("not a magcal database"));
    OpenOptions none;
    none.migrate_to = 0;
    PgDatabase db(uri, none);
    CHECK(query_int(db, "SELECT count(*) FROM pg_tables WHERE schemaname = current_schema()") == 1);
  }

  SECTION("version rows of another application are refused") {
    {
      PgDatabase db(uri);
      db.exec("UPDATE magcal_schema_version SET application_id = 42 WHERE version = 1");
    }
    CHECK(open_error(uri).kind() == StorageError::Kind::kForeignFile);
  }

  SECTION("read-only: an empty database has no tables yet, an old one needs an upgrade first") {
    OpenOptions read_only;
    read_only.read_only = true;
    const StorageError empty = open_error(uri, read_only);
    CHECK(empty.kind() == StorageError::Kind::kForeignFile);
    // The state right after createdb: say what to do, not that it is someone else's.
    CHECK_THAT(empty.what(), Catch::Contains("no magcal tables yet") &&
                                 Catch::Contains("magcald creates them on its first start"));
    OpenOptions v1;
    v1.migrate_to = 1;
    { PgDatabase db(uri, v1); }
    CHECK(open_error(uri, read_only).kind() == StorageError::Kind::kOlderSchema);
    {
      PgDatabase upgraded(uri);
      CHECK(upgraded.schema_version() == PgDatabase::latest_schema_version());
    }
    PgDatabase reader(uri, read_only);
    CHECK(reader.schema_version() == PgDatabase::latest_schema_version());
    const StorageError write = error_of([&] { reader.exec("DELETE FROM meta"); });
    CHECK(write.sqlstate() == "25006");  // read_only_sql_transaction
  }

  SECTION("names without the password; bad URIs and missing databases are permanent") {
    const auto at = uri.find('@');
    const std::string with_password = uri.substr(0, at) + ":s3cret" + uri.substr(at);
    PgDatabase db(with_password);
    CHECK(db.name().find("s3cret") == std::string::npos);
    CHECK_THAT(db.name(), Catch::Contains(":***@"));
    PgDatabase by_parameter(uri + "&password=s3cret&application_name=t");
    CHECK(by_parameter.name() == uri + "&password=***&application_name=t");

    const StorageError bad = open_error("postgresql://magcal@/x?nonsense=1");
    CHECK(bad.kind() == StorageError::Kind::kInvalidArgument);
    const StorageError missing = open_error(server->uri("no_such_database"));
    CHECK(missing.kind() == StorageError::Kind::kNotFound);
    CHECK_FALSE(missing.transient());
    // A missing database or role says where the fix is.
    const std::string hint = "docs/fleet.md \"Create the database and its role\"";
    CHECK(std::string(missing.what()).find(hint) != std::string::npos);
    std::string no_role = uri;
    no_role.replace(no_role.find("magcal@"), 7, "nobody@");
    const StorageError unknown_role = open_error(no_role);
    INFO(unknown_role.what());
    CHECK_FALSE(unknown_role.transient());
    CHECK(std::string(unknown_role.what()).find(hint) != std::string::npos);
    CHECK(is_postgres_uri(uri));
    CHECK(is_postgres_uri("postgres://h/db"));
    CHECK_FALSE(is_postgres_uri("/var/lib/magcal/magcal.db"));
  }
}

TEST_CASE("PostgreSQL errors: what a retry heals is transient, the rest is not") {
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  const std::string uri = server->create_database();
  PgDatabase db(uri);
  db.exec("INSERT INTO meta VALUES ('a', '1'), ('b', '2')");

  SECTION("a terminated session: transient, and the next statement reconnects") {
    PgDatabase admin(uri);
    const int pid = db.backend_pid();
    const std::string count = "SELECT count(*) FROM meta";
    CHECK(db.execute_prepared(count).get_int64(0, 0) == 2);
    admin.exec("SELECT pg_terminate_backend(" + std::to_string(pid) + ")");
    const StorageError lost = error_of([&] { db.execute_prepared(count); });
    INFO(lost.what());
    CHECK(lost.transient());
    CHECK(lost.kind() == StorageError::Kind::kEngine);
    CHECK((lost.sqlstate() == "57P01" || lost.sqlstate() == "08006"));
    // A new session: the statement is prepared again there.
    CHECK(db.execute_prepared(count).get_int64(0, 0) == 2);
    CHECK(db.backend_pid() != pid);

    // Inside a transaction the work is gone with the connection: every statement of that
    // transaction fails transient, and nothing of it is committed.
    {
      PgTransaction tx(db);
      db.exec("INSERT INTO meta VALUES ('c', '3')");
      admin.exec("SELECT pg_terminate_backend(" + std::to_string(db.backend_pid()) + ")");
      CHECK(error_of([&] { db.exec("INSERT INTO meta VALUES ('d', '4')"); }).transient());
      CHECK(error_of([&] { db.exec("SELECT 1"); }).transient());
      CHECK(error_of([&] { tx.commit(); }).transient());
    }
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 2);
  }

  SECTION("the server stopped: transient until it is back") {
    server->stop();
    const StorageError stopped = error_of([&] { db.execute("SELECT 1"); });
    INFO(stopped.what());
    CHECK(stopped.transient());
    const StorageError refused = open_error(uri);
    INFO(refused.what());
    CHECK(refused.transient());
    CHECK(error_of([&] { db.execute("SELECT 1"); }).transient());  // reconnect refused
    server->start();
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 2);
  }

  SECTION("down at the open: with connect_later the first statement that reaches it opens") {
    const std::string fresh = server->create_database();
    server->stop();
    OpenOptions later;
    later.connect_later = true;
    PgDatabase waiting(fresh, later);
    const StorageError down = error_of([&] { waiting.execute("SELECT 1"); });
    INFO(down.what());
    CHECK(down.condition() == StorageError::Condition::kUnavailable);
    CHECK(down.transient());
    server->start();
    // Opened as the open would have: the new database migrated. (Its connect runs on its own
    // thread and a statement waits 100 ms for it: on a loaded machine the first may still fail
    // transient, and the caller retries, as the daemon's retry policy does.)
    CHECK(magcal::test::wait_until(
        [&] {
          try {
            return waiting.schema_version() == PgDatabase::latest_schema_version();
          } catch (const StorageError& e) {
            if (!e.transient()) throw;
            return false;
          }
        },
        10));
    CHECK(query_int(waiting, "SELECT count(*) FROM samples") == 0);
    // A permanent refusal is thrown by the open itself.
    const StorageError missing = open_error(server->uri("no_such_database"), later);
    INFO(missing.what());
    CHECK_FALSE(missing.transient());
    CHECK(missing.kind() == StorageError::Kind::kNotFound);
  }

  SECTION("serialization failure, lock timeout and deadlock are transient") {
    PgDatabase other(uri, [] {
      OpenOptions quick;
      quick.busy_timeout_ms = 100;
      return quick;
    }());
    {
      PgTransaction t1(db, PgTransaction::Isolation::kRepeatableRead);
      PgTransaction t2(other, PgTransaction::Isolation::kRepeatableRead);
      CHECK(query_int(db, "SELECT count(*) FROM meta") == 2);
      CHECK(query_int(other, "SELECT count(*) FROM meta") == 2);
      db.exec("UPDATE meta SET value = 'x' WHERE key = 'a'");
      t1.commit();
      const StorageError e =
          error_of([&] { other.exec("UPDATE meta SET value = 'y' WHERE key = 'a'"); });
      CHECK(e.sqlstate() == "40001");
      CHECK(e.condition() == StorageError::Condition::kConflict);
      CHECK(e.transient());
    }
    {
      PgTransaction holder(db);
      db.exec("UPDATE meta SET value = 'z' WHERE key = 'a'");
      const StorageError e =
          error_of([&] { other.exec("UPDATE meta SET value = 'w' WHERE key = 'a'"); });
      CHECK(e.sqlstate() == "55P03");  // lock_timeout = busy_timeout_ms
      CHECK(e.condition() == StorageError::Condition::kBusy);
      CHECK(e.transient());
    }
    {
      // Rows taken in opposite orders: the server breaks the cycle by failing one of them.
      PgDatabase second(uri);
      for (PgDatabase* d : {&db, &second}) d->exec("SET deadlock_timeout = '50ms'");
      PgTransaction ta(db);
      PgTransaction tb(second);
      db.exec("UPDATE meta SET value = '1' WHERE key = 'a'");
      second.exec("UPDATE meta SET value = '2' WHERE key = 'b'");
      auto a = std::async(std::launch::async, [&]() -> std::string {
        try {
          db.exec("UPDATE meta SET value = '1' WHERE key = 'b'");
          return "";
        } catch (const StorageError& e) {
          return e.sqlstate() + (e.transient() ? " transient" : "");
        }
      });
      std::string b;
      try {
        second.exec("UPDATE meta SET value = '2' WHERE key = 'a'");
      } catch (const StorageError& e) {
        b = e.sqlstate() + (e.transient() ? " transient" : "");
      }
      if (b.empty()) tb.commit();  // frees the other side, should it be the one waiting
      const std::string a_error = a.get();
      CHECK(a_error + b == "40P01 transient");
    }
  }

  SECTION("SQL errors and constraint violations are permanent; the connection stays usable") {
    const StorageError syntax = error_of([&] { db.exec("SELEC 1"); });
    CHECK(syntax.sqlstate() == "42601");
    CHECK_FALSE(syntax.transient());
    const StorageError duplicate = error_of([&] { db.exec("INSERT INTO meta VALUES ('a', '9')"); });
    CHECK(duplicate.sqlstate() == "23505");
    CHECK(duplicate.condition() == StorageError::Condition::kConstraint);
    CHECK_FALSE(duplicate.transient());
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 2);
  }

  SECTION("a transaction is rolled back unless committed; a failed one cannot commit") {
    {
      PgTransaction tx(db);
      db.exec("INSERT INTO meta VALUES ('c', '3')");
      {
        PgTransaction nested(db);  // a savepoint
        db.exec("INSERT INTO meta VALUES ('d', '4')");
      }
      CHECK(query_int(db, "SELECT count(*) FROM meta") == 3);
      tx.commit();
    }
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 3);
    {
      PgTransaction tx(db);
      db.exec("INSERT INTO meta VALUES ('e', '5')");
      CHECK_THROWS_AS(db.exec("INSERT INTO meta VALUES ('a', '9')"), StorageError);
      CHECK(error_of([&] { tx.commit(); }).sqlstate() == "25P02");
    }
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 3);
  }
}

// The sessions of the test's database other than the caller's.
int64_t other_sessions(PgDatabase& admin) {
  return query_int(admin,
                   "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() AND "
                   "pid <> pg_backend_pid()");
}

// Whether server session `pid` has run `sql` (its last statement) to the end: the reply the
// client stopped waiting for has been sent.
bool session_finished(PgDatabase& admin, int pid, const std::string& sql) {
  return query_int(admin,
                   "SELECT count(*) FROM pg_stat_activity WHERE pid = " + std::to_string(pid) +
                       " AND state <> 'active' AND query = '" + sql + "'") == 1;
}

TEST_CASE("PostgreSQL without a reply: transient at the deadline, one session, commits in doubt") {
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  const std::string uri = server->create_database();
  OpenOptions quick;
  quick.reply_timeout_ms = 500;
  quick.busy_timeout_ms = 200;
  PgDatabase db(uri, quick);
  PgDatabase admin(uri);
  using clock = std::chrono::steady_clock;
  const auto seconds_since = [](clock::time_point t0) {
    return std::chrono::duration<double>(clock::now() - t0).count();
  };

  SECTION("a statement past the deadline fails transient; no second session until it answers") {
    const int pid = db.backend_pid();
    const auto t0 = clock::now();
    const StorageError late = error_of([&] { db.execute("SELECT pg_sleep(2.5)"); });
    const double waited_s = seconds_since(t0);
    INFO(late.what());
    CHECK(waited_s >= 0.45);
    CHECK(waited_s < 1.5);
    CHECK(late.transient());
    CHECK(late.condition() == StorageError::Condition::kUnavailable);
    CHECK(late.in_doubt_transaction() == 0);
    CHECK(std::string(late.what()).find("no reply within 500 ms to SELECT pg_sleep(2.5)") !=
          std::string::npos);
    // Set aside: every statement fails at once, on no new session.
    const auto t1 = clock::now();
    const StorageError waiting = error_of([&] { db.execute("SELECT 1"); });
    INFO(waiting.what());
    CHECK(seconds_since(t1) < 0.2);
    CHECK(waiting.transient());
    CHECK(std::string(waiting.what()).find("still no reply to SELECT pg_sleep(2.5), sent") !=
          std::string::npos);
    CHECK(other_sessions(admin) == 1);
    // Once it has answered: a new session.
    REQUIRE(magcal::test::wait_until(
        [&] { return session_finished(admin, pid, "SELECT pg_sleep(2.5)"); }, 10));
    CHECK(query_int(db, "SELECT 7") == 7);
    CHECK(db.backend_pid() != pid);
    CHECK(other_sessions(admin) == 1);
  }

  SECTION("inside a transaction: nothing of it is committed, the connection is replaced") {
    const int pid = db.backend_pid();
    {
      PgTransaction tx(db);
      db.exec("INSERT INTO meta VALUES ('a', '1')");
      CHECK(error_of([&] { db.execute("SELECT pg_sleep(1)"); }).transient());
      CHECK(error_of([&] { tx.commit(); }).in_doubt_transaction() == 0);  // never sent
    }
    // Once it has answered, the next statement runs on a new session.
    REQUIRE(magcal::test::wait_until(
        [&] { return session_finished(admin, pid, "SELECT pg_sleep(1)"); }, 10));
    CHECK(query_int(db, "SELECT count(*) FROM meta") == 0);
    CHECK(db.backend_pid() != pid);
  }

  SECTION("a connection set aside that breaks is replaced at once") {
    const int pid = db.backend_pid();
    CHECK(error_of([&] { db.execute("SELECT pg_sleep(30)"); }).transient());
    admin.exec("SELECT pg_terminate_backend(" + std::to_string(pid) + ")");
    REQUIRE(magcal::test::wait_until([&] { return other_sessions(admin) == 0; }, 10));
    CHECK(query_int(db, "SELECT 8") == 8);
    CHECK(db.backend_pid() != pid);
  }

  SECTION("a COMMIT held for a synchronous standby that is down is in doubt until released") {
    magcal::test::wait_for_standby_commits(uri);
    magcal::test::set_absent_synchronous_standby(uri, true);
    PgDatabase writer(uri, quick);
    int64_t held = 0;
    {
      PgTransaction tx(writer);
      writer.exec("INSERT INTO meta VALUES ('held', '1')");
      const auto t0 = clock::now();
      const StorageError e = error_of([&] { tx.commit(); });
      INFO(e.what());
      CHECK(seconds_since(t0) < 1.5);
      CHECK(e.transient());
      held = e.in_doubt_transaction();
      CHECK(held > 0);
    }
    // Not known yet, and not visible: the server holds it until the standby confirms.
    CHECK(error_of([&] { writer.commit_outcome(held); }).transient());
    CHECK(query_int(admin, "SELECT count(*) FROM meta WHERE key = 'held'") == 0);
    // A new session (as after kSetAsideLimit) is told it is still in progress: transient too.
    const StorageError in_progress = error_of([&] { db.commit_outcome(held); });
    INFO(in_progress.what());
    CHECK(in_progress.transient());
    CHECK(std::string(in_progress.what()).find("still in progress") != std::string::npos);
    magcal::test::set_absent_synchronous_standby(uri, false);
    std::optional<Connection::CommitOutcome> outcome;
    REQUIRE(magcal::test::wait_until(
        [&] {
          try {
            outcome = writer.commit_outcome(held);
          } catch (const StorageError& e) {
            if (!e.transient()) throw;
          }
          return outcome.has_value();
        },
        10));
    CHECK(*outcome == Connection::CommitOutcome::kCommitted);
    CHECK(query_int(writer, "SELECT count(*) FROM meta WHERE key = 'held'") == 1);

    // A transaction rolled back is told as such.
    int64_t rolled_back = 0;
    {
      PgTransaction tx(writer);
      rolled_back = query_int(writer, "SELECT pg_current_xact_id()::text::bigint");
      writer.exec("INSERT INTO meta VALUES ('gone', '1')");
    }
    CHECK(writer.commit_outcome(rolled_back) == Connection::CommitOutcome::kRolledBack);
  }

  SECTION("SQLite has no commit in doubt") {
    const auto sqlite = open_database(":memory:");
    CHECK(error_of([&] { sqlite->commit_outcome(1); }).kind() ==
          StorageError::Kind::kInvalidArgument);
  }
}

TEST_CASE("PostgreSQL: a daemon's migration never leaves the lock to a session no one reads") {
  // A daemon (connect_later) whose first migration waits for another process's migration lock
  // past its reply deadline would set that connection aside still waiting; once granted, the
  // lock stayed with a session whose thread (an idle refit thread) never read it again, and
  // the daemon's other connections waited for it for good. Its wait ends at its lock timeout.
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  const std::string uri = server->create_database();
  OpenOptions bare;
  bare.migrate_to = 0;
  PgDatabase holder(uri, bare);  // another process migrating: holds the lock
  holder.exec("BEGIN");
  holder.exec("SELECT pg_advisory_xact_lock(" + std::to_string(kPgLockClass) + ", " +
              std::to_string(kPgMigrationLock) + ")");
  OpenOptions daemon;
  daemon.connect_later = true;
  daemon.reply_timeout_ms = 500;
  daemon.busy_timeout_ms = 200;
  PgDatabase idle(uri, daemon);  // tried while the lock is held, then left alone
  const auto t0 = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - t0 < std::chrono::milliseconds(1500)) {
    const StorageError e = error_of([&] { idle.execute("SELECT 1"); });
    INFO(e.what());
    CHECK(e.transient());
  }
  holder.exec("COMMIT");
  // Another connection of the daemon migrates and answers, while `idle` is not touched.
  PgDatabase worker(uri, daemon);
  CHECK(magcal::test::wait_until(
      [&] {
        try {
          return query_int(worker, "SELECT count(*) FROM meta") >= 0;
        } catch (const StorageError&) {
          return false;
        }
      },
      5));
  CHECK(query_int(idle, "SELECT 3") == 3);
}

TEST_CASE("PostgreSQL: a server that answers no connect holds a process's opens up once") {
  // A daemon opens its connections one after the other (worker, refit thread, operations
  // server): once an open has waited for a server that accepts connections and answers nothing,
  // the next opens wait as a reconnect does, and each connects once the server answers.
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  const std::string uri = server->create_database();
  struct Thaw {
    PgTestServer& server;
    ~Thaw() { server.freeze(false); }
  } thaw{*server};
  server->freeze(true);
  OpenOptions daemon;
  daemon.connect_later = true;
  using clock = std::chrono::steady_clock;
  const auto t0 = clock::now();
  PgDatabase worker(uri, daemon);
  const auto t1 = clock::now();
  PgDatabase refit(uri, daemon);
  PgDatabase api(uri, daemon);
  const double first_s = std::chrono::duration<double>(t1 - t0).count();
  const double others_s = std::chrono::duration<double>(clock::now() - t1).count();
  INFO("first open " << first_s << " s, the next two " << others_s << " s");
  CHECK(first_s >= 1.9);  // the open's wait for an answer (2 s)
  CHECK(others_s < first_s);
  server->freeze(false);
  for (PgDatabase* db : {&worker, &refit, &api}) {
    CHECK(magcal::test::wait_until(
        [&] {
          try {
            return query_int(*db, "SELECT 1") == 1;
          } catch (const StorageError& e) {
            if (!e.transient()) throw;
            return false;
          }
        },
        30));
  }
}

TEST_CASE("PostgreSQL values: bigint, double precision, bytea and text exactly, both formats") {
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  PgDatabase db(server->create_database());

  const std::vector<int64_t> integers = {1'800'000'000'123'457,  // a utime in 2027
                                         std::numeric_limits<int64_t>::max(),
                                         std::numeric_limits<int64_t>::min(),
                                         0,
                                         -1,
                                         int64_t{1} << 53 | 1};  // not exact as a double
  const std::vector<double> doubles = {1.0 / 3.0,
                                       M_PI,
                                       std::nextafter(1.0, 2.0),
                                       -48123.456789012345,
                                       std::numeric_limits<double>::max(),
                                       std::numeric_limits<double>::lowest(),
                                       std::numeric_limits<double>::min(),
                                       std::numeric_limits<double>::denorm_min(),
                                       -0.0,
                                       1e-310,
                                       std::numeric_limits<double>::infinity(),
                                       -std::numeric_limits<double>::infinity(),
                                       std::numeric_limits<double>::quiet_NaN()};
  // Bit for bit (-0.0 is not 0.0), any NaN for NaN.
  auto same = [](double a, double b) {
    return (std::isnan(a) && std::isnan(b)) || std::memcmp(&a, &b, sizeof a) == 0;
  };
  // Sample rows: the schema's bigint times and double precision fields keep every value.
  const std::size_t n = std::max(integers.size(), doubles.size());
  PgParams p;
  for (std::size_t k = 0; k < n; ++k) {
    p.clear();
    p.add("SAT-" + std::to_string(k)).add(integers[k % integers.size()]);
    p.add(doubles[k % doubles.size()]);
    db.execute_prepared(
        "INSERT INTO samples (sat_id, utime, seq, receive_utime, bx_nT, by_nT, bz_nT, "
        "has_direction, h_norm_nT) VALUES ($1, $2, $2, $2, $3, $3, $3, 0, $3)",
        p);
  }
  for (const PgFormat format : {PgFormat::kText, PgFormat::kBinary}) {
    INFO((format == PgFormat::kBinary ? "binary" : "text") << " results");
    const PgResult r = db.execute(
        "SELECT substr(sat_id, 5)::bigint, utime, seq, receive_utime, bx_nT, bz_nT, h_norm_nT "
        "FROM samples",
        {}, format);
    REQUIRE(r.rows() == static_cast<int>(n));
    for (int row = 0; row < r.rows(); ++row) {
      const auto k = static_cast<std::size_t>(r.get_int64(row, 0));
      INFO("sample " << k);
      for (int c = 1; c <= 3; ++c) CHECK(r.get_int64(row, c) == integers[k % integers.size()]);
      for (int c = 4; c <= 6; ++c) CHECK(same(r.get_double(row, c), doubles[k % doubles.size()]));
    }
    // The hot-loop readers: the same values, the column checked once; text refused.
    using Column = PgResult::BinaryColumn;
    if (format == PgFormat::kText) {
      CHECK_THROWS_AS(r.check_binary_column(1, Column::kBigint), StorageError);
      continue;
    }
    r.check_binary_column(1, Column::kBigint);
    r.check_binary_column(4, Column::kDouble);
    CHECK_THROWS_AS(r.check_binary_column(4, Column::kBigint), StorageError);
    CHECK_THROWS_AS(r.check_binary_column(7, Column::kDouble), StorageError);
    for (int row = 0; row < r.rows(); ++row) {
      const auto k = static_cast<std::size_t>(r.get_int64(row, 0));
      CHECK(r.bigint_at(row, 1) == integers[k % integers.size()]);
      CHECK(same(r.double_at(row, 4), doubles[k % doubles.size()]));
    }
    CHECK_THROWS_AS(r.bigint_at(r.rows(), 1), StorageError);
  }

  std::vector<std::byte> all_bytes(256);
  for (int i = 0; i < 256; ++i) all_bytes[i] = static_cast<std::byte>(i);
  const std::string text = "Ørsted 'quoted' \"double\" \\ back\tslash";
  for (const PgFormat format : {PgFormat::kText, PgFormat::kBinary}) {
    INFO((format == PgFormat::kBinary ? "binary" : "text") << " results");
    for (const int64_t i : integers) {
      for (const double d : doubles) {
        p.clear();
        p.add(i).add(d).add_bytes(all_bytes).add(text);
        const PgResult r = db.execute_prepared(
            "SELECT $1::bigint, $2::double precision, $3::bytea, $4::text", p, format);
        CHECK(r.get_int64(0, 0) == i);
        CHECK(same(r.get_double(0, 1), d));
        CHECK(r.get_bytes(0, 2) == all_bytes);
        CHECK(r.get_text(0, 3) == text);
      }
    }
    p.clear();
    p.add_bytes({}).add_null();
    const PgResult empty = db.execute("SELECT $1::bytea, $2::double precision", p, format);
    CHECK(empty.get_bytes(0, 0).empty());
    CHECK_FALSE(empty.is_null(0, 0));
    CHECK(empty.is_null(0, 1));
    CHECK_FALSE(empty.get_optional_double(0, 1).has_value());
    if (format == PgFormat::kBinary) CHECK_THROWS_AS(empty.double_at(0, 1), StorageError);
  }
}

// deploy/fleet/create-database.sql (docs/fleet.md) makes a role and a database that magcald can
// create its schema in as that role (PostgreSQL 15 lets only a database's owner create in its
// public schema). Run as the docs say, with psql; the role and database renamed, since the test
// server's superuser is already called magcal.
TEST_CASE("PostgreSQL: deploy/fleet/create-database.sql makes a database magcald migrates") {
  PgTestServer* server = pg_server_or_skip();
  if (server == nullptr) return;
  // Run by a superuser, and by an admin with only CREATEROLE and CREATEDB (a managed service).
  REQUIRE(
      magcal::test::run({server->pg_tool("psql"), server->uri("postgres"), "-v", "ON_ERROR_STOP=1",
                         "-c", "CREATE ROLE fleet_admin LOGIN CREATEROLE CREATEDB"},
                        server->dir() + "/psql_admin.log") == 0);
  for (const std::string admin : {"magcal", "fleet_admin"}) {
    const std::string name = admin == "magcal" ? "fleet_example" : "fleet_managed";
    INFO("run by " << admin);
    const std::string sql = std::regex_replace(
        magcal::test::slurp(MAGCAL_SOURCE_DIR "/deploy/fleet/create-database.sql"),
        std::regex("\\bmagcal\\b"), name);
    REQUIRE(sql.find("CREATE ROLE " + name) != std::string::npos);
    const std::string file = server->dir() + "/create-database.sql";
    std::ofstream(file) << sql;
    const std::string log = server->dir() + "/psql.log";
    std::string admin_uri = server->uri("postgres");
    admin_uri.replace(admin_uri.find("magcal@"), std::string("magcal").size(), admin);
    const int rc = magcal::test::run(
        {server->pg_tool("psql"), admin_uri, "-v", "ON_ERROR_STOP=1", "-f", file}, log);
    INFO(magcal::test::slurp(log));
    REQUIRE(rc == 0);
    std::string uri = server->uri(name);
    uri.replace(uri.find("magcal@"), std::string("magcal").size(), name);
    PgDatabase db(uri);  // connects as the new role and migrates
    CHECK(db.schema_version() == PgDatabase::latest_schema_version());
    CHECK(query_int(db,
                    "SELECT count(*) FROM pg_tables WHERE tablename = 'samples' AND "
                    "tableowner = '" +
                        name + "'") == 1);
  }
}
