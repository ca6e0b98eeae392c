// The storage faults of daemon_fault_injection_test.cpp against PostgreSQL (issue 19), where
// they apply, with magcald on a throwaway server (tests/storage/postgres/pg_test_server.hpp;
// skipped without the server programs, with CI=true failing): the samples table locked by
// another session past lock_timeout; the daemon's server processes terminated
// (pg_terminate_backend); a permanent error (INSERT revoked from its role, the table dropped);
// kill -9 at random points. Not here: a full disk (the server's own filesystem; the data
// directory full makes PostgreSQL stop, which is an outage) and the file deleted, moved or made
// read-only (no file on the daemon's side). The server restarted or down (for 2 minutes, past
// pg_max_failure_s, with SIGTERM or SIGKILL meanwhile: the spill file) is in
// daemon_pg_outage_test.cpp.
#include <catch2/catch.hpp>

#include <signal.h>
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>

#include "service/config/daemon_config.hpp"
#include "tests/service/daemon/storage_fault_support.hpp"
#include "tests/storage/storage_backends.hpp"
#include "tests/test_skip.hpp"

namespace {

using namespace magcal::test;
using namespace magcal::test::storage_faults;

// A new database on the test's PostgreSQL server and a replay log, for a PostgreSQL case
// (uri empty: skipped, return at once). The spill file of an outage goes to the temp folder.
struct PgScenario {
  TempDir tmp;
  std::string log;
  std::string uri;
  PgScenario(const std::string& name, int n, int64_t frame_spacing_us)
      : tmp(name), log(tmp.file("day.lcm")) {
    magcal::test::PostgresBackend backend;
    uri = backend.new_database();
    write_log(log, n, frame_spacing_us);
  }
  // [storage] keys of every run: the spill file in the temp folder, then `extra`.
  std::string storage(const std::string& extra = "") const {
    return "spill_dir = \"" + tmp.path.string() + "\"\n" + extra;
  }
  std::string spill_file() const {
    return tmp.file("magcal-spill-" + magcal::default_station_id() + ".spill");
  }
};

// The one integer `sql` returns on `uri` (a count), on a connection of its own.
int64_t pg_query_int(const std::string& uri, const std::string& sql) {
  magcal::storage::OpenOptions schema_unread;
  schema_unread.migrate_to = 0;
  return query_int(*magcal::storage::open_database(uri, schema_unread), sql);
}

// psql running the statements of `script` on `uri` (stops at the first error; rows only, one
// value per line), in the background: its pid; script and output in tmp as NAME.sql, NAME.log.
pid_t spawn_psql(const TempDir& tmp, const std::string& uri, const std::string& name,
                 const std::string& script) {
  std::ofstream(tmp.file(name + ".sql")) << script;
  return spawn({"psql", "-X", "-q", "-At", "-v", "ON_ERROR_STOP=1", "-d", uri, "-f",
                tmp.file(name + ".sql")},
               tmp.file(name + ".log"));
}

// The same, waited for; it must succeed.
void run_psql(const TempDir& tmp, const std::string& uri, const std::string& name,
              const std::string& script) {
  const pid_t p = spawn_psql(tmp, uri, name, script);
  REQUIRE(p > 0);
  const int rc = wait_exit(p, 30);
  INFO(slurp(tmp.file(name + ".log")));
  REQUIRE(rc == 0);
}

// Sessions other than the caller's on the database of `uri` holding a granted lock of `mode`
// on its samples table.
int64_t samples_locks(const std::string& uri, const std::string& mode) {
  return pg_query_int(uri,
                      "SELECT count(*) FROM pg_locks l JOIN pg_class c ON c.oid = l.relation "
                      "WHERE l.database = (SELECT oid FROM pg_database WHERE datname = "
                      "current_database()) AND c.relname = 'samples' AND l.granted AND l.mode = '" +
                          mode + "' AND l.pid <> pg_backend_pid()");
}

// Another session (psql in the background, its output in tmp as lock.log) holding the samples
// table locked against everything, reads and writes alike, while it runs `statements`: its pid,
// once the lock is granted.
pid_t lock_samples(const PgScenario& sc, const std::string& statements) {
  const pid_t locker = spawn_psql(
      sc.tmp, sc.uri, "lock",
      "BEGIN;\nLOCK TABLE samples IN ACCESS EXCLUSIVE MODE;\n" + statements + "COMMIT;\n");
  REQUIRE(locker > 0);
  REQUIRE(wait_until([&] { return samples_locks(sc.uri, "AccessExclusiveLock") == 1; }, 10));
  return locker;
}

}  // namespace

TEST_CASE("PostgreSQL: samples locked by another session past lock_timeout: retried, all once",
          "[daemon][fault][postgres]") {
  constexpr int kN = 3000;
  // 60 frames over 6 s: the lock and the retries' backoff (up to 1.6 s) end before the replay
  // does (a stop while commits fail spills: the SIGTERM case below).
  const PgScenario sc("magcald_pgfault_lock", kN, 100'000);
  if (sc.uri.empty()) return;
  const auto& tmp = sc.tmp;
  const std::string out = tmp.file("out.lcm");
  const pid_t d =
      start_daemon_until_stored(tmp, sc.uri, sc.log, sc.storage("busy_timeout_ms = 100\n"), 200);

  // Another session locks the table for 2 s (20x lock_timeout), and counts its rows when it
  // took the lock and before it lets go.
  const pid_t locker = lock_samples(sc,
                                    "SELECT count(*) FROM samples;\nSELECT pg_sleep(2);\n"
                                    "SELECT count(*) FROM samples;\n");
  REQUIRE(wait_exit(locker, 20) == 0);
  std::istringstream counts(slurp(tmp.file("lock.log")));
  int64_t stored_at_lock = -1, stored_at_release = -2;
  counts >> stored_at_lock >> stored_at_release;

  const int rc = wait_exit(d, 60);
  const std::string daemon_log = slurp(tmp.file("magcald.log"));
  INFO(daemon_log);
  CHECK(rc == 0);
  // Named as what it is: the lock not granted in time, kept and retried.
  CHECK_THAT(daemon_log, Catch::Contains("SQLSTATE 55P03"));
  CHECK_THAT(daemon_log, Catch::Contains("works again"));
  const auto [last, unhealthy] = expect_lock_ridden_out(out, kN);
  // Nothing was committed while the other session held the lock.
  CHECK(stored_at_lock >= 200);
  CHECK(stored_at_release == stored_at_lock);
  const auto st = read_stored(sc.uri);
  CHECK(st.count == kN);
  CHECK(st.distinct == kN);
  WARN("PostgreSQL lock: held 2 s, "
       << last.storage_failures << " failed operations, " << last.storage_retries << " retries, "
       << unhealthy << " unhealthy status messages, stored " << st.count << "/" << kN);
}

TEST_CASE("PostgreSQL: the daemon's server processes terminated: it reconnects, nothing lost",
          "[daemon][fault][postgres]") {
  constexpr int kN = 3000;
  constexpr int kTerminations = 6;
  constexpr int64_t kEvery = 200;                                 // stored samples per round
  const PgScenario sc("magcald_pgfault_terminate", kN, 200'000);  // 60 frames over 12 s
  if (sc.uri.empty()) return;
  const auto& tmp = sc.tmp;
  const std::string out = tmp.file("out.lcm");
  const pid_t d = start_daemon_until_stored(tmp, sc.uri, sc.log, sc.storage(), kEvery);
  // Every session on its database but the caller's (the daemon's connections: its worker, its
  // refit thread), at every kEvery samples stored, in the first half of the replay:
  // mid-transaction, between, idle. A terminated connection comes back at its next statement:
  // each round waits for the daemon to have stored again, so the rounds follow the replay
  // however slow the machine, and the replay goes on long after the last (at its end, a commit
  // still failing leaves the samples to the spill file and the next start).
  const char* const kSessions =
      "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() AND "
      "pid <> pg_backend_pid()";
  int64_t terminated = 0;
  for (int i = 0; i < kTerminations; ++i) {
    REQUIRE(wait_until(
        [&] {
          return read_stored(sc.uri).count >= kEvery * (i + 1) &&
                 pg_query_int(sc.uri, kSessions) > 0;
        },
        30));
    terminated += pg_query_int(sc.uri,
                               "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                               "WHERE datname = current_database() AND pid <> pg_backend_pid()");
  }
  const int rc = wait_exit(d, 60);
  const std::string daemon_log = slurp(tmp.file("magcald.log"));
  INFO(daemon_log);
  CHECK(rc == 0);
  CHECK(terminated >= kTerminations);
  const auto pub = read_published(out);
  REQUIRE_FALSE(pub.statuses.empty());
  const auto& last = pub.statuses.back();
  CHECK(last.storage_healthy);
  CHECK(last.received == kN);
  CHECK(last.stored == kN);
  CHECK(last.rejected == 0);
  CHECK(last.storage_failures >= 1);
  const auto st = read_stored(sc.uri);
  CHECK(st.count == kN);
  CHECK(st.distinct == kN);
  WARN("PostgreSQL sessions terminated: "
       << terminated << " server processes in " << kTerminations << " rounds, "
       << last.storage_failures << " failed operations, " << last.storage_retries
       << " retries, stored " << st.count << "/" << kN << ", exit " << rc);
}

TEST_CASE("PostgreSQL: a permanent error (INSERT revoked, table dropped): exit 3 at once, spilled",
          "[daemon][fault][postgres]") {
  // A privilege taken away or a table dropped is an operator's act that no retry heals: the
  // daemon stops at once with the server's reason (systemd alerts), its pending samples in the
  // spill file, instead of retrying for pg_max_failure_s (an hour).
  constexpr int kN = 3000;
  for (const bool revoked : {true, false}) {
    DYNAMIC_SECTION((revoked ? "INSERT revoked" : "table dropped")) {
      const PgScenario sc(revoked ? "magcald_pgfault_revoked" : "magcald_pgfault_dropped", kN,
                          50'000);  // 60 frames over 3 s
      if (sc.uri.empty()) return;
      const auto& tmp = sc.tmp;
      // The daemon logs in as a role of its own, allowed to read and write the tables (the
      // schema made first by the superuser): what a fleet's config does.
      magcal::storage::open_database(sc.uri);
      const std::string name =
          sc.uri.substr(sc.uri.find("@/") + 2, sc.uri.find('?') - sc.uri.find("@/") - 2);
      const std::string role = "station_" + name;
      run_psql(tmp, sc.uri, "grant",
               "CREATE ROLE " + role + " LOGIN;\n" +
                   "GRANT SELECT, INSERT, UPDATE, DELETE ON ALL TABLES IN SCHEMA public TO " +
                   role + ";\nGRANT USAGE, SELECT ON ALL SEQUENCES IN SCHEMA public TO " + role +
                   ";\n");
      std::string station_uri = sc.uri;
      station_uri.replace(station_uri.find("magcal@"), 6, role);
      const std::string out = tmp.file("out.lcm");
      const auto cfg = write_config(tmp, "d.toml", out, sc.storage());
      const pid_t d = start_daemon(cfg, station_uri, sc.log, "1", tmp.file("magcald.log"));
      REQUIRE(d > 0);
      REQUIRE(wait_until([&] { return read_stored(sc.uri).count >= 300; }, 20));
      run_psql(tmp, sc.uri, "break",
               revoked ? "REVOKE INSERT ON samples FROM " + role + ";\n" : "DROP TABLE samples;\n");
      const auto stop = expect_storage_stop(d, tmp.file("magcald.log"), out,
                                            revoked ? "permanent error (other, SQLSTATE 42501)"
                                                    : "permanent error (other, SQLSTATE 42P01)",
                                            sc.spill_file());
      // Not retried: far sooner than pg_max_failure_s, the pending batch kept in the file.
      CHECK(stop.seconds < 10.0);
      CHECK(stop.last.storage_retries == 0);
      CHECK(stop.spilled > 0);
      // At most the frame the replay was handing over when the daemon stopped: it never
      // reached the worker, so it is not in the spill but counted as not committed (the
      // re-run below fills it).
      CHECK(stop.not_committed <= kBatch);

      // The next start commits the spill first: with the privilege given back it does, and the
      // same replay fills the rest, every sample once; with the table gone it refuses to start,
      // saying so, and the file keeps the samples.
      if (revoked) run_psql(tmp, sc.uri, "regrant", "GRANT INSERT ON samples TO " + role + ";\n");
      const auto cfg2 = write_config(tmp, "d2.toml", tmp.file("out2.lcm"), sc.storage());
      const int rc2 = run_daemon(cfg2, station_uri, sc.log, tmp.file("run2.log"));
      const std::string run2_log = slurp(tmp.file("run2.log"));
      INFO(run2_log);
      if (revoked) {
        CHECK(rc2 == 0);
        CHECK_THAT(run2_log, Catch::Contains(std::to_string(stop.spilled) +
                                             " samples committed (0 already stored)"));
        CHECK_FALSE(fs::exists(sc.spill_file()));
        const auto st = read_stored(sc.uri);
        CHECK(st.count == kN);
        CHECK(st.distinct == kN);
      } else {
        CHECK(rc2 == 2);  // refused at start, as for any database it cannot use
        CHECK_THAT(run2_log,
                   Catch::Contains("relation \"samples\" does not exist (SQLSTATE 42P01)"));
        CHECK(magcal::SampleSpill(sc.spill_file(), "", int64_t{1} << 30).held_samples() ==
              stop.spilled);
      }
      WARN((revoked ? "INSERT revoked" : "table dropped")
           << ": exit " << stop.rc << " after " << stop.seconds << " s, " << stop.last.stored
           << " stored before, " << stop.spilled << " spilled, " << stop.not_committed
           << " counted not committed; next start exit " << rc2);
    }
  }
}

TEST_CASE(
    "PostgreSQL: kill -9 at 10 random points of a replay: after a re-replay every sample once",
    "[daemon][fault][postgres]") {
  constexpr int kN = 1500;
  constexpr int kKills = 10;
  const PgScenario sc("magcald_pgfault_kill", kN, 40'000);  // 30 frames over 1.2 s at speed 1
  if (sc.uri.empty()) return;
  const auto& tmp = sc.tmp;
  std::mt19937 rng(20261202);
  // Kill points by progress (as the SQLite case): a random share of the replay committed, then
  // anywhere within the next commit interval.
  std::uniform_int_distribution<int> target_samples(1, kN - 1);
  std::uniform_int_distribution<int> jitter_ms(0, 100);  // commit_every_ms below
  KillTally tally(kN);
  for (int k = 0; k < kKills; ++k) {
    INFO("kill " << k);
    const std::string db = magcal::test::pg_server_or_skip()->create_database();
    const std::string out = tmp.file("out" + std::to_string(k) + ".lcm");
    const auto cfg = write_config(tmp, "d.toml", out, sc.storage("commit_every_ms = 100\n"));
    // What survived: a prefix of the replay (only the uncommitted tail is missing), at least
    // what the daemon reported stored before it died.
    const int64_t target = target_samples(rng);
    const auto before = kill_replay_after(
        tmp, cfg, db, sc.log, [&] { return read_stored(db).count >= target; }, jitter_ms(rng));
    const int64_t k_stored = std::max<int64_t>(before.count, 0);
    CHECK(before.is_prefix());
    tally.add(k_stored, out);
    // No outage: nothing spilled (the kill left the file, open since the start, empty).
    CHECK(magcal::SampleSpill(sc.spill_file(), "", int64_t{1} << 30).held_samples() == 0);

    // The killed process's heartbeat is still live: the restart says so and goes on.
    expect_rerun_fills(tmp, sc.storage(), db, sc.log, k_stored, kN);
  }
  CHECK(tally.mid_stream >= kKills / 4);
  WARN("PostgreSQL kill -9: " << tally.summary(kKills));
}

TEST_CASE(
    "PostgreSQL: SIGTERM while samples are locked: stops at once, spilled, next start commits",
    "[daemon][fault][postgres]") {
  // SQLite retries through max_failure_s at a stop (SIGTERM case above); with a spill file the
  // pending samples go to it at once, as in an outage (daemon_pg_outage_test.cpp), here with the
  // server up and only the table locked.
  constexpr int kN = 3000;
  const PgScenario sc("magcald_pgfault_sigterm", kN, 50'000);  // 60 frames over 3 s
  if (sc.uri.empty()) return;
  const auto& tmp = sc.tmp;
  const std::string out = tmp.file("out.lcm");
  const pid_t d =
      start_daemon_until_stored(tmp, sc.uri, sc.log, sc.storage("busy_timeout_ms = 100\n"), 200);
  const pid_t locker = lock_samples(sc, "SELECT pg_sleep(3);\n");
  // Commits are failing now (the retry's first error line).
  REQUIRE(wait_until(
      [&] { return slurp(tmp.file("magcald.log")).find("kept, retry in") != std::string::npos; },
      20));
  const auto t0 = Clock::now();
  ::kill(d, SIGTERM);
  const int rc = wait_exit(d, 30);
  const double stop_s = std::chrono::duration<double>(Clock::now() - t0).count();
  CHECK(wait_exit(locker, 10) == 0);  // the lock is gone
  const std::string daemon_log = slurp(tmp.file("magcald.log"));
  INFO(daemon_log);
  CHECK(rc == 0);
  CHECK(stop_s < 5.0);
  // Why, as it is: the lock (not an unreachable server).
  CHECK_THAT(daemon_log, Catch::Contains("SQLSTATE 55P03"));
  CHECK_THAT(daemon_log, Catch::Contains("database commit failing: "));
  const auto s = read_published(out).statuses.back();
  const int64_t spilled = magcal::SampleSpill(sc.spill_file(), "", int64_t{1} << 30).held_samples();
  CHECK(spilled > 0);
  CHECK(s.rejected == 0);
  CHECK(s.received == s.stored + spilled + s.queue_overflow);
  CHECK(read_stored(sc.uri).count == s.stored);

  // The next start commits the spill, the same replay fills the rest: every sample once.
  const auto s2 = expect_rerun_fills(tmp, sc.storage(), sc.uri, sc.log, s.stored + spilled, kN);
  CHECK_FALSE(fs::exists(sc.spill_file()));
  WARN("PostgreSQL SIGTERM during a lock: exit "
       << rc << " after " << stop_s << " s, " << s.stored << " stored, " << spilled
       << " spilled; re-replay stored " << s2.stored << ", " << rejected(s2, "duplicate")
       << " duplicates");
}
