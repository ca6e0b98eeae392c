// magcald rides out PostgreSQL outages (issue 19, "Network faults"), as real processes against a
// throwaway PostgreSQL server (tests/storage/postgres/pg_test_server.hpp) that the test restarts
// or stops under a paced replay (write_batch_log, ?speed=1):
// - restarted (pg_ctl stop -m fast + start) mid-replay: no sample lost (as many stored as a
//   reference run into SQLite stores), no daemon exit;
// - unreachable for 2 minutes with a small [storage] max_pending_samples: the pending samples go
//   to the spill file, intake goes on, /-/healthy stays 200 while /-/ready answers 503 with the
//   outage in both bodies; afterwards nothing is lost, the file is gone and /metrics counted it;
// - killed (SIGKILL) during an outage: the next start commits the spill file it left, exactly;
// - down past [storage] pg_max_failure_s: exit 3, the pending samples spilled, not lost;
// - stopped (SIGTERM) during an outage: at once, exit 0, the pending samples spilled;
// - data-clock refits due during an outage: run after it, each once, as on SQLite;
// - stopped (SIGTERM) during an outage without a spill file ([storage] spill_max_bytes = 0):
//   exit 3 once [storage] stop_max_failure_s has passed, the held samples counted as not
//   committed (storage_error), never a hang until systemd's SIGKILL;
// - a server that accepts connections but does not answer ([storage] pg_reply_timeout_s): one
//   holding every commit for a synchronous standby that is down, and one frozen (SIGSTOP), are
//   ridden out as outages (spilled, not ready, alive); the commit in doubt when the standby
//   returns is found committed, so every sample is stored and counted once and no UKF snapshot
//   is written twice; a SIGTERM while frozen stops at once, the next start commits the spill.
// A server down when magcald starts, and start errors: daemon_pg_down_at_start_test.cpp.
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

TEST_CASE("PostgreSQL restarted mid-replay: no sample lost, magcald rides it out",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_restart");
  // 3000 samples in 60 frames 0.2 s apart: 12 s of replay.
  const std::string log = paced_log(dir, 3000, 200'000);
  const int64_t expected = reference_count(log, dir);
  REQUIRE(expected == 3000);

  const std::string db = server->create_database();
  const std::string config = write_config(
      dir, "pg.toml", "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n");
  const PacedDaemon daemon(log, config, dir, 500);
  // pg_ctl restart: a fast stop (sessions terminated) and a start.
  server->stop();
  server->start();
  const int rc = wait_exit(daemon.pid, 120);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(stored_samples(db) == expected);
  // It did see the restart (its session was terminated), and recovered from it.
  CHECK(text.find("database commit failed") != std::string::npos);
  CHECK(text.find("database commit works again") != std::string::npos);
  CHECK(text.find("received=3000 stored=3000 rejected=0") != std::string::npos);
}

TEST_CASE("PostgreSQL unreachable for 2 minutes: samples spilled, none lost, magcald alive",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_outage");
  // 15000 samples in 300 frames 0.5 s apart: 150 s of replay at 100 samples/s, so a 120 s
  // outage receives ~12000 samples, 12 times max_pending_samples. Commits of 10 samples: the
  // spill takes more than one drain slice (IngestWorker: 1 s) to go back, while samples come.
  const std::string log = paced_log(dir, 15000, 500'000);
  const int64_t expected = reference_count(log, dir);
  REQUIRE(expected == 15000);

  const std::string db = server->create_database();
  const std::string spill_dir = dir.file("spill");
  std::filesystem::create_directories(spill_dir);
  const std::string config = write_config(
      dir, "pg.toml",
      "db_path = \"" + db + "\"\nmax_pending_samples = 1000\nspill_dir = \"" + spill_dir + "\"\n",
      10);
  const PacedDaemon daemon(log, config, dir, 500);
  const int port = daemon.port;
  CHECK(http_get(port, "/-/ready").status == 200);

  const auto outage_start = std::chrono::steady_clock::now();
  server->stop();
  // Within seconds the failing commit shows: alive (a liveness probe must not restart it), not
  // ready, both bodies saying why.
  REQUIRE(wait_until([&] { return http_get(port, "/-/ready").status == 503; }, 20));
  const auto healthy = http_get(port, "/-/healthy");
  CHECK(healthy.status == 200);
  CHECK(healthy.body.find("storage failing for") != std::string::npos);
  CHECK(healthy.body.find("[storage] pg_max_failure_s = 3600 s") != std::string::npos);
  CHECK(http_get(port, "/-/ready").body.find("storage failing for") != std::string::npos);
  // The pending batch reaches max_pending_samples and goes to the spill file, again and again.
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 5000; }, 100));
  const auto during = scrape(port);
  CHECK(during.sum("magcal_storage_healthy") == 0);
  CHECK(during.sum("magcal_storage_failing_seconds") > 10);
  CHECK(during.sum("magcal_spill_samples") >= 5000);
  CHECK(during.sum("magcal_spill_bytes") > 5000 * 100);
  CHECK(during.sum("magcal_queue_overflow_total") == 0);
  const std::string spill_file =
      spill_dir + "/magcal-spill-" + magcal::default_station_id() + ".spill";
  CHECK(std::filesystem::exists(spill_file));
  std::this_thread::sleep_until(outage_start + std::chrono::seconds(120));
  server->start();

  // Back: the spill is committed and removed while the replay goes on.
  REQUIRE(wait_until([&] { return metric(port, "magcal_spill_samples") == 0; }, 60));
  // (Ready once the commit that emptied the spill ends: it goes on with the pending batch.)
  CHECK(wait_until([&] { return http_get(port, "/-/ready").status == 200; }, 20));
  const double spilled = metric(port, "magcal_samples_spilled_total");
  const int rc = wait_exit(daemon.pid, 120);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(stored_samples(db) == expected);
  CHECK(text.find("received=15000 stored=15000 rejected=0") != std::string::npos);
  CHECK(text.find("pending samples spilled to " + spill_file) != std::string::npos);
  CHECK(spilled >= 5000);
  CHECK_FALSE(std::filesystem::exists(spill_file));
  CHECK(std::filesystem::is_empty(spill_dir));
}

TEST_CASE("an idle station is not ready while PostgreSQL is down: its lease rounds fail",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_idle");
  // 10 frames, then nothing for 20 s (a station between passes), then a last frame.
  const std::string log = dir.file("idle.lcm");
  {
    lcm::LogFile out(log, "w");
    REQUIRE(out.good());
    const int64_t t0 = log_start_utime();
    for (int f = 0; f <= 10; ++f) {
      magcal::mag_batch_t batch;
      batch.sat_id = kSat;
      for (int k = f * magcal::test::kLogBatch; k < (f + 1) * magcal::test::kLogBatch; ++k) {
        batch.samples.push_back(magcal::test::turning_field_sample(kSat, t0, k));
      }
      batch.n = static_cast<int32_t>(batch.samples.size());
      magcal::test::write_log_event(out, f, t0 + (f < 10 ? f * 100'000 : 20'000'000),
                                    "MAGCAL_BATCH", batch);
    }
  }
  const std::string db = server->create_database();
  const std::string config = write_config(
      dir, "idle.toml", "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n", 200,
      "[fleet]\nlease_s = 3\n");
  const PacedDaemon daemon(log, config, dir, 10 * magcal::test::kLogBatch);
  CHECK(http_get(daemon.port, "/-/ready").status == 200);
  server->stop();
  // Nothing to commit, but its heartbeat and lease renewals fail (every lease_s / 3).
  CHECK(wait_until([&] { return http_get(daemon.port, "/-/ready").status == 503; }, 10));
  CHECK(http_get(daemon.port, "/-/healthy").status == 200);
  CHECK(metric(daemon.port, "magcal_storage_healthy") == 0);
  server->start();
  CHECK(wait_until([&] { return http_get(daemon.port, "/-/ready").status == 200; }, 20));
  const int rc = wait_exit(daemon.pid, 60);
  INFO(slurp(daemon.log_path));
  CHECK(rc == 0);
  CHECK(stored_samples(db) == 11 * magcal::test::kLogBatch);
}

TEST_CASE("magcald killed during a PostgreSQL outage: the next start commits its spill file",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_spill_kill");
  // 6000 samples in 120 frames 0.2 s apart: 24 s of replay.
  const std::string log = paced_log(dir, 6000, 200'000);
  const std::string db = server->create_database();
  // Memory could hold 4000 samples: the spill must not wait for that.
  const std::string config_text = "db_path = \"" + db +
                                  "\"\nmax_pending_samples = 4000\nspill_dir = \"" + dir.file("") +
                                  "\"\n";
  const PacedDaemon daemon(log, write_config(dir, "pg.toml", config_text), dir, 400);
  server->stop();
  REQUIRE(
      wait_until([&] { return metric(daemon.port, "magcal_samples_spilled_total") >= 1200; }, 30));
  // Nothing is committed while the server is down: what is stored now stays so.
  const auto before_kill = scrape(daemon.port);
  const double stored = before_kill.sum("magcal_samples_stored_total");
  const double received = before_kill.sum("magcal_samples_received_total");
  ::kill(daemon.pid, SIGKILL);
  CHECK(wait_exit(daemon.pid, 30) == -2);
  server->start();
  const int64_t held =
      check_next_start_commits_spill(dir, config_text, log, db, static_cast<int64_t>(stored));
  // The crash lost at most what arrived since the last spill (a commit interval, 250 ms, here
  // about 60 samples, plus a frame of 50): the batch is spilled at each interval while
  // commits fail, not once memory is full.
  INFO("received " << received << ", stored " << stored << ", spilled " << held);
  CHECK(received - stored - static_cast<double>(held) <= 200);
}

TEST_CASE("PostgreSQL down past pg_max_failure_s: exit 3 with the pending samples spilled",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_spill_exit");
  const std::string log = paced_log(dir, 6000, 200'000);
  const std::string db = server->create_database();
  // Each commit interval's batch goes to the spill file while commits fail; what is still
  // pending at the exit too.
  const std::string config_text =
      "db_path = \"" + db + "\"\npg_max_failure_s = 3\nspill_dir = \"" + dir.file("") + "\"\n";
  const PacedDaemon daemon(log, write_config(dir, "pg.toml", config_text), dir, 400);
  server->stop();
  const double stored = metric(daemon.port, "magcal_samples_stored_total");
  const int rc = wait_exit(daemon.pid, 30);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  CHECK(rc == 3);
  CHECK(text.find("[storage] pg_max_failure_s = 3;") != std::string::npos);
  CHECK(text.find("database commit failing: ") != std::string::npos);
  CHECK(text.find(" pending samples spilled to ") != std::string::npos);
  server->start();
  check_next_start_commits_spill(dir, config_text, log, db, static_cast<int64_t>(stored));
}

TEST_CASE("SIGTERM during a PostgreSQL outage: magcald stops at once, its samples spilled",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_spill_stop");
  const std::string log = paced_log(dir, 6000, 200'000);
  const std::string db = server->create_database();
  // The default max_pending_samples: nothing is spilled for its size, all of it at the stop.
  const std::string config_text =
      "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n";
  const PacedDaemon daemon(log, write_config(dir, "pg.toml", config_text), dir, 400);
  server->stop();
  REQUIRE(wait_until([&] { return http_get(daemon.port, "/-/ready").status == 503; }, 20));
  const double stored = metric(daemon.port, "magcal_samples_stored_total");
  const std::string text = stop_during_outage(daemon.pid, daemon.log_path);
  INFO(text);
  CHECK(text.find("database commit failing: ") != std::string::npos);
  // The final books say where the rest went: the spill file.
  CHECK(final_status(text, "spill_held") > 0);
  CHECK(final_status(text, "spill_held") == final_status(text, "received") -
                                                final_status(text, "stored") -
                                                final_status(text, "rejected"));
  server->start();
  check_next_start_commits_spill(dir, config_text, log, db, static_cast<int64_t>(stored));
}

TEST_CASE("PostgreSQL holding every commit (its synchronous standby down): an outage, nothing lost",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_held");
  // 6000 samples in 120 frames 0.3 s apart: 36 s of replay, about 15 s of it held.
  const std::string log = paced_log(dir, 6000, 300'000);
  const std::string reference = reference_db(log, dir);
  REQUIRE(stored_samples(reference) == 6000);
  const std::string db = server->create_database();
  magcal::test::wait_for_standby_commits(db);
  const PacedDaemon daemon(log, write_config(dir, "pg.toml", unanswered_config_text(db, dir)), dir,
                           500);
  magcal::test::set_absent_synchronous_standby(db, true);
  check_rides_out_unanswered(daemon);
  // Held for 5 s of replay more (800 samples at 50 per 0.3 s), counted as received: the replay's
  // clock, not the wall's.
  const double received_held = metric(daemon.port, "magcal_samples_received_total");
  REQUIRE(wait_until(
      [&] { return metric(daemon.port, "magcal_samples_received_total") >= received_held + 800; },
      60));
  // The standby back (the list emptied): the held commits complete, one of them in doubt.
  magcal::test::set_absent_synchronous_standby(db, false);
  const int rc = wait_exit(daemon.pid, 120);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(text.find("no reply within 1 s to ") != std::string::npos);
  CHECK(text.find("did commit: its samples are stored") != std::string::npos);
  // Every sample once, counted as stored (not as a duplicate of itself), no snapshot twice.
  CHECK(stored_samples(db) == 6000);
  CHECK(text.find("received=6000 stored=6000 rejected=0") != std::string::npos);
  const auto snapshots = ukf_snapshot_times(db);
  CHECK(snapshots.size() > 3);
  CHECK(std::adjacent_find(snapshots.begin(), snapshots.end()) == snapshots.end());
  CHECK(snapshots == ukf_snapshot_times(reference));
}

TEST_CASE(
    "a frozen PostgreSQL server (SIGSTOP) is an outage, a stop during it is bounded, none lost",
    "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_frozen");
  const std::string log = paced_log(dir, 6000, 500'000);
  const std::string db = server->create_database();
  const std::string config_text = unanswered_config_text(db, dir);
  const PacedDaemon daemon(log, write_config(dir, "pg.toml", config_text), dir, 500);
  struct Thaw {
    magcal::test::PgTestServer& server;
    ~Thaw() { server.freeze(false); }
  } thaw{*server};
  server->freeze(true);
  check_rides_out_unanswered(daemon);
  // An operator's `magcal status` meanwhile says why it cannot connect (a 2 s connect_timeout
  // in the URI keeps the test short).
  const std::string status_log = dir.file("status.log");
  CHECK(run({kBin + "/magcal", "status", "--db", db + "&connect_timeout=2"}, status_log, 30) == 2);
  CHECK(slurp(status_log).find("no answer within libpq's connect_timeout") != std::string::npos);
  const double received = metric(daemon.port, "magcal_samples_received_total");
  // SIGTERM: the samples go to the spill file, at once.
  const std::string text = stop_during_outage(daemon.pid, daemon.log_path);
  INFO(text);
  CHECK(text.find("no reply within 1 s to ") != std::string::npos);
  const int64_t received_all = final_status(text, "received");
  CHECK(received_all >= static_cast<int64_t>(received));
  server->freeze(false);
  // The next start (taking none of the log's samples) commits the spill file: every sample the
  // first run received is stored once.
  const std::string again =
      write_config(dir, "again.toml", config_text + "[service]\nwhitelist = [\"SOMEONE-ELSE\"]\n");
  const std::string again_log = dir.file("magcald_again.log");
  REQUIRE(run({kBin + "/magcald", "--config", again, "--http-listen", "", "--lcm-url",
               "file://" + log + "?speed=0"},
              again_log, 120) == 0);
  INFO(slurp(again_log));
  CHECK(stored_samples(db) == received_all);
  CHECK_FALSE(
      std::filesystem::exists(dir.file("magcal-spill-" + magcal::default_station_id() + ".spill")));
}

TEST_CASE("data-clock refits that fall due during a PostgreSQL outage run after it, once each",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_refits");
  // 6000 samples (16.7 h of data) in 24 s: a data hour every 1.4 s of replay.
  const std::string log = paced_log(dir, 6000, 200'000);
  const std::vector<int64_t> expected = scheduled_refits(reference_db(log, dir, kHourlyRefits));
  REQUIRE(expected.size() >= 12);

  const std::string db = server->create_database();
  const std::string config = write_config(
      dir, "pg.toml", "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n", 200,
      kHourlyRefits);
  const PacedDaemon daemon(log, config, dir, 400);
  server->stop();
  // ~5 data hours (1800 samples 10 s apart) received during the outage, whatever the pace.
  const double received_at_stop = metric(daemon.port, "magcal_samples_received_total");
  REQUIRE(wait_until(
      [&] {
        return metric(daemon.port, "magcal_samples_received_total") >= received_at_stop + 1800;
      },
      60));
  server->start();
  const int rc = wait_exit(daemon.pid, 120);
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  REQUIRE(rc == 0);
  // (The owner's filter triggers them from the stored samples: it waits with the database and
  // reaches each due time once the held samples are committed.)
  CHECK(scheduled_refits(db) == expected);
  CHECK(text.find("received=6000 stored=6000 rejected=0") != std::string::npos);
}

TEST_CASE("SIGTERM during a PostgreSQL outage without a spill file: exit 3 within the stop bound",
          "[daemon][postgres][outage][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg_nospill_stop");
  const std::string log = paced_log(dir, 6000, 200'000);
  const std::string db = server->create_database();
  // No spill file: the held samples can go nowhere. Without the stop's bound the drain would
  // retry for pg_max_failure_s (an hour), past systemd's TimeoutStopSec.
  constexpr double kBound_s = 2.0;
  const PacedDaemon daemon(
      log,
      write_config(dir, "pg.toml",
                   "db_path = \"" + db + "\"\nspill_max_bytes = 0\nstop_max_failure_s = " +
                       std::to_string(kBound_s) + "\n"),
      dir, 400);
  server->stop();
  REQUIRE(
      wait_until([&] { return metric(daemon.port, "magcal_storage_pending_samples") >= 100; }, 20));
  const auto t0 = std::chrono::steady_clock::now();
  ::kill(daemon.pid, SIGTERM);
  const int rc = wait_exit(daemon.pid, 60);
  const double stop_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  server->start();
  const std::string text = slurp(daemon.log_path);
  INFO(text);
  CHECK(rc == 3);
  CHECK(stop_s >= kBound_s);
  CHECK(stop_s < kBound_s + 5);
  CHECK(text.find("after the stop ([storage] stop_max_failure_s = 2;") != std::string::npos);
  // The held samples are counted as not committed, in the log and the final counters, and the
  // books balance: every received sample is stored or counted.
  const int64_t received = final_status(text, "received");
  const int64_t stored = final_status(text, "stored");
  const int64_t not_committed = final_status(text, "storage_error");
  INFO("received " << received << ", stored " << stored << ", not committed " << not_committed);
  CHECK(not_committed >= 100);
  CHECK(received == stored + not_committed);
  CHECK(final_status(text, "rejected") == not_committed);
  CHECK(text.find(std::to_string(not_committed) + " received samples were not committed") !=
        std::string::npos);
  CHECK(stored_samples(db) == stored);
}
