// magcald and a PostgreSQL server that is down or silent when it starts, as real processes
// against a throwaway server (tests/storage/postgres/pg_test_server.hpp), and its start errors:
// - down when magcald starts: it receives and spills, not ready, both probes saying since when;
//   once the server is up every sample is stored once, and the refits and UKF snapshots are
//   those of SQLite. Before the server came up: SIGTERM exits 0 at once, SIGKILL loses at most a
//   commit interval, pg_max_failure_s exits 3, and the next start commits the spill; an earlier
//   run's spill file is committed ahead of this run's (said once, and counted by the spill
//   gauge). A database it cannot use (missing database or role) is still a start error at once
//   (exit 2), and so when the server first answers after being down at start;
// - a server that accepts connections but answers nothing at the start: up at once, an outage;
// - a spill_dir that cannot take the file (configured or $STATE_DIRECTORY), or a file another
//   magcald holds, or one written for another database: a start error (exit 2) naming the path
//   (and errno, or both databases), the file kept.
// Outages while magcald runs: daemon_pg_outage_test.cpp.
// Skipped without the PostgreSQL server programs (with CI=true it fails).
#include <signal.h>

#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "tests/service/daemon/pg_outage_support.hpp"

using namespace magcal::test::pg_outage;

TEST_CASE("a PostgreSQL server that answers nothing when magcald starts: up at once, an outage",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_unanswered");
  const std::string log = paced_log(dir, 3000, 300'000);  // 18 s of replay
  const std::string db = server->create_database();
  // Frozen: the connects hang until libpq's connect_timeout (10 s a host); holding commits: the
  // first migration's COMMIT waits for the standby. Either way the worker's connect and the
  // refit and HTTP connections must not hold the start up (connects run on their own threads).
  const bool frozen = GENERATE(true, false);
  struct Thaw {
    magcal::test::PgTestServer& server;
    std::string db;
    ~Thaw() {
      try {
        server.freeze(false);
        magcal::test::set_absent_synchronous_standby(db, false);
      } catch (const std::exception& e) {
        WARN(e.what());
      }
    }
  } thaw{*server, db};
  if (frozen) {
    server->freeze(true);
  } else {
    magcal::test::wait_for_standby_commits(db);
    magcal::test::set_absent_synchronous_standby(db, true);
  }
  const std::string log_path = dir.file("magcald.log");
  const auto t0 = std::chrono::steady_clock::now();
  const pid_t pid = spawn(
      {kBin + "/magcald", "--config", write_config(dir, "pg.toml", unanswered_config_text(db, dir)),
       "--http-listen", "127.0.0.1:0", "--lcm-url", "file://" + log + "?speed=1"},
      log_path);
  REQUIRE(pid > 0);
  const int port = wait_http_port(log_path, 30);
  REQUIRE(port > 0);
  const double up_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  INFO("up after " << up_s << " s");
  // Up before libpq's connect_timeout (10 s a host; the URI sets none) could have ended a
  // connect: the start waits for no answer (the worker's open waits 2 s, the others less).
  CHECK(up_s < 10);
  // Frozen: up while the worker's connect was still in flight, not after libpq gave up.
  if (frozen) CHECK(slurp(log_path).find("(still connecting; ") != std::string::npos);
  CHECK(http_get(port, "/-/ready").status == 503);
  CHECK(http_get(port, "/-/healthy").status == 200);
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 300; }, 30));
  if (frozen) {
    server->freeze(false);
  } else {
    magcal::test::set_absent_synchronous_standby(db, false);
  }
  const int rc = wait_exit(pid, 120);
  const std::string text = slurp(log_path);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(text.find("received=3000 stored=3000 rejected=0") != std::string::npos);
  CHECK(stored_samples(db) == 3000);
}

TEST_CASE("PostgreSQL down when magcald starts: it receives, and stores all once the server is up",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down");
  // 4000 samples (11 h of data) in 80 frames 0.2 s apart: 16 s of replay; refits that compute
  // (early ones from 300 samples, then every data hour; this log's field leaves them
  // unobservable, so rejected: the same windows and verdicts are what is compared) and the
  // UKF's snapshots, compared with a run into SQLite.
  const std::string log = paced_log(dir, 4000, 200'000);
  const std::string refits = kHourlyRefits + "min_samples = 300\n";
  const std::string reference = reference_db(log, dir, refits);
  const std::vector<int64_t> expected_refits = scheduled_refits(reference);
  const std::vector<storage::CalibrationRecord> expected_results = refit_rows(reference);
  const std::vector<int64_t> expected_snapshots = ukf_snapshot_times(reference);
  REQUIRE(expected_refits.size() >= 8);
  REQUIRE(expected_results.size() > expected_refits.size());  // early ones too
  REQUIRE(expected_snapshots.size() >= 100);

  // A new database, never opened: migrated when the server first answers.
  const std::string db = server->create_database();
  server->stop();
  const std::string spill_dir = dir.file("spill");
  std::filesystem::create_directories(spill_dir);
  const std::string config = write_config(
      dir, "pg.toml", "db_path = \"" + db + "\"\nspill_dir = \"" + spill_dir + "\"\n", 200, refits);
  const PacedDaemon daemon(log, config, dir, 0);  // (0: once it listens)
  const int port = daemon.port;
  // It receives: each commit interval's batch goes to the spill file. Alive, not ready, both
  // probes saying since when the database is unreachable; the API answers 503 (its own
  // connection waits for the server too).
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 1000; }, 20));
  const std::string since = "unreachable since magcald started at ";
  const auto ready = http_get(port, "/-/ready");
  CHECK(ready.status == 503);
  CHECK(ready.body.find(since) != std::string::npos);
  const auto healthy = http_get(port, "/-/healthy");
  CHECK(healthy.status == 200);
  CHECK(healthy.body.find(since) != std::string::npos);
  CHECK(healthy.body.find("[storage] pg_max_failure_s = 3600 s") != std::string::npos);
  CHECK(metric(port, "magcal_samples_stored_total") == 0);
  CHECK(http_get(port, "/api/v1/spacecraft").status == 503);
  server->start();

  // Reached: migrated, restored, the spill committed; ready, and the API answers.
  REQUIRE(wait_until([&] { return http_get(port, "/-/ready").status == 200; }, 30));
  CHECK(http_get(port, "/-/ready").body.find(since) == std::string::npos);
  // The API's own connection reconnects at its next request after its backoff: on a loaded
  // machine that can be a moment after the worker's made the daemon ready.
  CHECK(wait_until([&] { return http_get(port, "/api/v1/spacecraft").status == 200; }, 30));
  const int rc = wait_exit(daemon.pid, 120);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(text.find("database unreachable at start: magcald receives anyway") != std::string::npos);
  CHECK(text.find("database commit works again after") != std::string::npos);
  // Every sample once; the refits and the UKF's snapshots as without the outage.
  CHECK(stored_samples(db) == 4000);
  CHECK(text.find("received=4000 stored=4000 rejected=0") != std::string::npos);
  CHECK(scheduled_refits(db) == expected_refits);
  const std::vector<storage::CalibrationRecord> results = refit_rows(db);
  REQUIRE(results.size() == expected_results.size());
  for (size_t i = 0; i < results.size(); ++i) {
    const auto& got = results[i];
    const auto& want = expected_results[i];
    INFO("refit " << i << " at " << want.utime);
    CHECK(got.utime == want.utime);
    CHECK(got.n_samples == want.n_samples);
    CHECK(got.verdict == want.verdict);
    for (int k = 0; k < 3; ++k) CHECK(got.bias_nT[k] == Approx(want.bias_nT[k]).margin(1e-9));
  }
  CHECK(ukf_snapshot_times(db) == expected_snapshots);
  CHECK(std::filesystem::is_empty(spill_dir));
}

// magcald started while the server is down, on a database in use (its tables exist),
// replaying `n` samples, 250 a second; `extra` adds [storage] keys.
struct StartedWhileDown {
  magcal::test::PgTestServer& server;
  const TempDir& dir;
  std::string log, db;
  std::string database_keys;  // db_path and spill_dir
  std::string config_text;    // database_keys and `extra`
  std::unique_ptr<PacedDaemon> daemon;

  StartedWhileDown(magcal::test::PgTestServer& s, const TempDir& d, const std::string& extra,
                   int n = 6000)
      : server(s), dir(d), log(paced_log(d, n, 200'000)), db(s.create_database()) {
    storage::open_database(db);
    server.stop();
    database_keys = "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n";
    config_text = database_keys + extra;
    daemon = std::make_unique<PacedDaemon>(log, write_config(dir, "pg.toml", config_text), dir, 0);
  }

  // After it ended (its log `text`): it said why it started without the database; with the
  // server back, the next start commits every sample it received, all in its spill file.
  void check_next_start_commits_all(const std::string& text) {
    CHECK(text.find("database unreachable at start: magcald receives anyway") != std::string::npos);
    server.start();
    const int64_t held = check_next_start_commits_spill(dir, config_text, log, db, 0);
    CHECK(text.find("received=" + std::to_string(held) + " stored=0 rejected=0") !=
          std::string::npos);
  }
};

TEST_CASE("SIGTERM while PostgreSQL has been down since the start: exit 0, the next start commits",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down_stop");
  StartedWhileDown started(*server, dir, "");
  const int port = started.daemon->port;
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 500; }, 20));
  // (What was pending at the stop goes to the file too.)
  const std::string text = stop_during_outage(started.daemon->pid, started.daemon->log_path);
  INFO(text);
  started.check_next_start_commits_all(text);
}

TEST_CASE("SIGKILL while PostgreSQL has been down since the start: at most a commit interval lost",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down_kill");
  StartedWhileDown started(*server, dir, "");
  const int port = started.daemon->port;
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 1200; }, 20));
  const double received = metric(port, "magcal_samples_received_total");
  ::kill(started.daemon->pid, SIGKILL);
  CHECK(wait_exit(started.daemon->pid, 30) == -2);
  server->start();
  const int64_t held =
      check_next_start_commits_spill(dir, started.config_text, started.log, started.db, 0);
  // As in an outage that began later: what arrived since the last spill (a commit interval,
  // about 60 samples, plus a frame of 50).
  INFO("received " << received << ", spilled " << held);
  CHECK(received - static_cast<double>(held) <= 200);
}

TEST_CASE("PostgreSQL down from the start past pg_max_failure_s: exit 3, the next start commits",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down_exit");
  StartedWhileDown started(*server, dir, "pg_max_failure_s = 3\n");
  const int rc = wait_exit(started.daemon->pid, 30);
  const std::string text = slurp(started.daemon->log_path);
  INFO(text);
  CHECK(rc == 3);
  CHECK(text.find("[storage] pg_max_failure_s = 3;") != std::string::npos);
  // Every received sample is in the file: none counted as not committed.
  CHECK(text.find("were not committed") == std::string::npos);
  started.check_next_start_commits_all(text);
}

TEST_CASE("down at start with an earlier run's spill file: both committed once the server is up",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down_recover");
  // 2000 samples in 8 s; the first run gives up after 2 s (exit 3), its samples in the file.
  StartedWhileDown first(*server, dir, "pg_max_failure_s = 2\n", 2000);
  REQUIRE(wait_exit(first.daemon->pid, 30) == 3);
  const std::string spill_file =
      dir.file("magcal-spill-" + magcal::default_station_id() + ".spill");
  int64_t held = 0;
  {
    magcal::SampleSpill left(spill_file, "", int64_t{1} << 30);
    held = left.held_samples();
  }
  REQUIRE(held > 0);
  std::filesystem::rename(first.daemon->log_path, dir.file("first.log"));  // (the port's line)
  // Started again, still down, with pg_max_failure_s at its default (an hour: it waits for the
  // server however slow the machine): its samples go behind the earlier run's in the file (the
  // gauge counts all the file holds; the probes tell the earlier run's apart).
  const PacedDaemon again(first.log, write_config(dir, "again.toml", first.database_keys), dir, 0);
  REQUIRE(
      wait_until([&] { return metric(again.port, "magcal_samples_spilled_total") >= 200; }, 20));
  // The restore that commits the earlier run's samples tried again and again meanwhile.
  REQUIRE(wait_until(
      [&] { return count_of(slurp(again.log_path), "database commit failed (") >= 3; }, 30));
  const auto during = scrape(again.port);
  CHECK(during.sum("magcal_spill_samples") ==
        during.sum("magcal_samples_spilled_total") + static_cast<double>(held));
  CHECK(http_get(again.port, "/-/ready")
            .body.find(" (and " + std::to_string(held) + " an earlier run left there)") !=
        std::string::npos);
  server->start();
  const int rc = wait_exit(again.pid, 60);
  const std::string text = slurp(again.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  // The earlier run's samples first (the same log: this run's copies of them are duplicates),
  // then this run's; every sample once.
  CHECK(text.find("holds " + std::to_string(held) + " samples an earlier run received") !=
        std::string::npos);
  // Said once, though the restore that commits them was tried again and again meanwhile.
  CHECK(count_of(text, "samples an earlier run received") == 1);
  CHECK(text.find(std::to_string(held) + " samples committed (0 already stored); the ") !=
        std::string::npos);
  CHECK(text.find(" this run spilled follow") != std::string::npos);
  CHECK(text.find("received=2000 ") != std::string::npos);
  CHECK(stored_samples(first.db) == 2000);
  CHECK_FALSE(std::filesystem::exists(spill_file));
}

TEST_CASE("a spill file written for another database is a start error, and kept as it is",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_spill_other_db");
  // A run against database A, down from its start, leaves its samples in the spill file.
  StartedWhileDown first(*server, dir, "pg_max_failure_s = 2\n", 2000);
  REQUIRE(wait_exit(first.daemon->pid, 30) == 3);
  server->start();
  const std::string spill_file =
      dir.file("magcal-spill-" + magcal::default_station_id() + ".spill");
  const auto spill_bytes = std::filesystem::file_size(spill_file);
  // The next start names database B: refused, nothing committed anywhere, the file untouched.
  const std::string other = server->create_database();
  const std::string config_b = write_config(
      dir, "b.toml", "db_path = \"" + other + "\"\nspill_dir = \"" + dir.file("") + "\"\n");
  const std::string log_b = dir.file("magcald_b.log");
  const int rc = run({kBin + "/magcald", "--config", config_b, "--http-listen", "", "--lcm-url",
                      "file://" + first.log + "?speed=0"},
                     log_b, 60);
  const std::string text = slurp(log_b);
  INFO(text);
  CHECK(rc == 2);
  CHECK(text.find("received for database " + storage::database_name(first.db) +
                  ", not for [storage] db_path " + storage::database_name(other) +
                  ": start magcald once with that db_path") != std::string::npos);
  CHECK(std::filesystem::file_size(spill_file) == spill_bytes);
  CHECK(stored_samples(other) == 0);
  CHECK(stored_samples(first.db) == 0);
  // With database A again, they are committed there.
  check_next_start_commits_spill(dir, first.config_text, first.log, first.db, 0);
}

TEST_CASE("a PostgreSQL database magcald cannot use is a start error at once (exit 2)",
          "[daemon][postgres][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_refused");
  const std::string log = paced_log(dir, 100, 200'000);
  const std::string config = write_config(dir, "pg.toml", "spill_dir = \"" + dir.file("") + "\"\n");
  std::string no_role = server->create_database();
  no_role.replace(no_role.find("magcal@"), 7, "nobody@");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {server->uri("no_such_database"), "database \"no_such_database\" does not exist"},
      {no_role, "role \"nobody\" does not exist"}};
  for (const auto& [uri, why] : cases) {
    const auto t0 = std::chrono::steady_clock::now();
    const int rc = run({kBin + "/magcald", "--config", config, "--db", uri, "--http-listen", "",
                        "--lcm-url", "file://" + log + "?speed=0"},
                       dir.file("refused.log"), 30);
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const std::string text = slurp(dir.file("refused.log"));
    INFO(text);
    CHECK(rc == 2);
    CHECK(seconds < 10);
    CHECK(text.find(why) != std::string::npos);
    CHECK(text.find("unreachable at start") == std::string::npos);
    CHECK_FALSE(std::filesystem::exists(
        dir.file("magcal-spill-" + magcal::default_station_id() + ".spill")));
  }
}

TEST_CASE("a spill directory that cannot take the file is a start error (exit 2)",
          "[daemon][postgres][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_bad_spill_dir");
  const std::string log = paced_log(dir, 100, 200'000);
  const std::string db = server->create_database();
  // A regular file where the directory should be: ENOTDIR for root too (a permission is no
  // test as root: access() and open() both pass it).
  const std::string not_a_dir = dir.file("plain-file");
  std::ofstream(not_a_dir) << "x";
  const std::string file = not_a_dir + "/magcal-spill-" + magcal::default_station_id() + ".spill";
  auto start = [&](const std::string& extra, const std::string& name) {
    const std::string log_path = dir.file(name + ".log");
    const int rc = run({kBin + "/magcald", "--config",
                        write_config(dir, name + ".toml", "db_path = \"" + db + "\"\n" + extra),
                        "--http-listen", "", "--lcm-url", "file://" + log + "?speed=0"},
                       log_path, 30);
    return std::pair{rc, slurp(log_path)};
  };
  SECTION("configured") {
    const auto [rc, text] = start("spill_dir = \"" + not_a_dir + "\"\n", "configured");
    INFO(text);
    CHECK(rc == 2);
    CHECK(text.find("magcald: [storage] spill_dir '" + not_a_dir + "': spill file " + file +
                    ": cannot create: Not a directory (ENOTDIR)") != std::string::npos);
    CHECK(stored_samples(db) == 0);  // (refused before it stored anything)
  }
  SECTION("unset: $STATE_DIRECTORY (systemd's StateDirectory)") {
    ::setenv("STATE_DIRECTORY", not_a_dir.c_str(), 1);
    const auto [rc, text] = start("", "state_directory");
    ::unsetenv("STATE_DIRECTORY");
    INFO(text);
    CHECK(rc == 2);
    CHECK(text.find("magcald: [storage] spill_dir unset ($STATE_DIRECTORY): spill file " + file +
                    ": cannot create: Not a directory (ENOTDIR)") != std::string::npos);
    CHECK(stored_samples(db) == 0);  // (refused before it stored anything)
  }
  SECTION("a second magcald of this station and spill_dir, while the first runs") {
    // (8 s of replay.)
    const std::string long_log = dir.file("long.lcm");
    magcal::test::write_batch_log(long_log, kSat, log_start_utime(), 2000, 200'000);
    const PacedDaemon first(
        long_log,
        write_config(dir, "first.toml",
                     "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n"),
        dir, 0);
    const auto [rc, text] = start("spill_dir = \"" + dir.file("") + "\"\n", "second");
    INFO(text);
    CHECK(rc == 2);
    CHECK(text.find("locked by another process (another magcald with this [station] id and "
                    "spill_dir?)") != std::string::npos);
    ::kill(first.pid, SIGTERM);
    CHECK(wait_exit(first.pid, 30) == 0);
  }
}

TEST_CASE("PostgreSQL down at start, then refusing the database for good: exit 2, as at start",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_start_down_refused");
  const std::string log = paced_log(dir, 2000, 200'000);
  server->stop();
  const std::string config = write_config(dir, "pg.toml",
                                          "db_path = \"" + server->uri("no_such_database") +
                                              "\"\nspill_dir = \"" + dir.file("") + "\"\n");
  const PacedDaemon daemon(log, config, dir, 0);
  REQUIRE(
      wait_until([&] { return metric(daemon.port, "magcal_samples_spilled_total") >= 100; }, 20));
  server->start();
  const int rc = wait_exit(daemon.pid, 30);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  CHECK(rc == 2);
  CHECK(text.find("refused magcald when it first answered (unreachable at start; at start this "
                  "is a start error, exit 2)") != std::string::npos);
  CHECK(text.find("database \"no_such_database\" does not exist") != std::string::npos);
  // What it received is kept in the spill file for a start with the right database (but for a
  // frame still queued at the exit, counted as not committed).
  magcal::SampleSpill left(dir.file("magcal-spill-" + magcal::default_station_id() + ".spill"), "",
                           int64_t{1} << 30);
  CHECK(left.held_samples() >= 100);
}
