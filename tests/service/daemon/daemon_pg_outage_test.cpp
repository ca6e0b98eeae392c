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
// - down when magcald starts: it receives and spills, not ready, both probes saying since when;
//   once the server is up every sample is stored once, and the refits and UKF snapshots are
//   those of SQLite. Before the server came up: SIGTERM exits 0 at once, SIGKILL loses at most a
//   commit interval, pg_max_failure_s exits 3, and the next start commits the spill; an earlier
//   run's spill file is committed ahead of this run's (said once, and counted by the spill
//   gauge). A database it cannot use (missing database or role) is still a start error at once
//   (exit 2), and so when the server first answers after being down at start;
// - stopped (SIGTERM) during an outage without a spill file ([storage] spill_max_bytes = 0):
//   exit 3 once [storage] stop_max_failure_s has passed, the held samples counted as not
//   committed (storage_error), never a hang until systemd's SIGKILL;
// - a spill_dir that cannot take the file (configured or $STATE_DIRECTORY), or a file another
//   magcald holds, or one written for another database: a start error (exit 2) naming the path
//   (and errno, or both databases), the file kept;
// - a server that accepts connections but does not answer ([storage] pg_reply_timeout_s): one
//   holding every commit for a synchronous standby that is down, and one frozen (SIGSTOP), are
//   ridden out as outages (spilled, not ready, alive); the commit in doubt when the standby
//   returns is found committed, so every sample is stored and counted once and no UKF snapshot
//   is written twice; a SIGTERM while frozen stops at once, the next start commits the spill.
// Skipped without the PostgreSQL server programs (with CI=true it fails).
#include <signal.h>

#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "service/daemon/daemon_config.hpp"
#include "service/daemon/sample_spill.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/service/prometheus_text.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace {

using magcal::test::http_get;
using magcal::test::run;
using magcal::test::slurp;
using magcal::test::spawn;
using magcal::test::TempDir;
using magcal::test::wait_exit;
using magcal::test::wait_http_port;
using magcal::test::wait_until;
namespace storage = magcal::storage;

const std::string kBin = MAGCAL_BIN_DIR;
const std::string kSat = "OUTAGE-1";
// [refit] keys: data-clock refits every data hour.
const std::string kHourlyRefits = "clock = \"data\"\nevery_hours = 1\n";

// Samples 10 s apart from 300 h ago (within [ingest] max_future_s of the wall clock, and the
// whole log within the window below).
int64_t log_start_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
             .count() -
         300LL * 3600 * 1'000'000;
}

// The config of every run: no refit computes (too few samples for min_samples: a refit started
// just before an outage would hold a replay until the database returns, and these tests are
// about the samples; a due one still leaves its job row, "skipped"), a window that keeps every
// sample, small commits; `extra` adds keys to [storage], `refit_extra` to [refit] (a
// min_samples there replaces the one above).
std::string write_config(const TempDir& dir, const std::string& name, const std::string& extra,
                         int commit_every_samples = 200, const std::string& refit_extra = "") {
  const std::string path = dir.file(name);
  const bool computes = refit_extra.find("min_samples") != std::string::npos;
  std::ofstream(path) << "[storage]\nwindow_hours = 200\ncommit_every_samples = "
                      << commit_every_samples << "\n"
                      << extra << "[refit]\n"
                      << (computes ? "" : "min_samples = 1000000000\n") << refit_extra;
  return path;
}

int64_t stored_samples(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  return storage::open_database(db, read_only)->make_sample_window_store()->count(kSat);
}

// The same log replayed as fast as it goes into a fresh SQLite file: its path.
std::string reference_db(const std::string& log, const TempDir& dir,
                         const std::string& refit_extra = "") {
  const std::string db = dir.file("reference.db");
  const std::string config = write_config(dir, "reference.toml", "", 200, refit_extra);
  const int rc = run({kBin + "/magcald", "--config", config, "--db", db, "--http-listen", "",
                      "--lcm-url", "file://" + log + "?speed=0"},
                     dir.file("reference.log"), 120);
  INFO(slurp(dir.file("reference.log")));
  REQUIRE(rc == 0);
  return db;
}

// Samples the same log leaves in a fresh SQLite file.
int64_t reference_count(const std::string& log, const TempDir& dir) {
  return stored_samples(reference_db(log, dir));
}

// The due times of kSat's scheduled refits in `db` that ran to their end, ascending; fails the
// test when one ran twice.
std::vector<int64_t> scheduled_refits(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  std::vector<int64_t> out;
  for (const auto& job :
       storage::open_database(db, read_only)->make_refit_job_log()->recent(kSat, 10'000)) {
    if (job.trigger != "scheduled" || job.outcome == storage::job_outcome::kInterrupted) continue;
    CHECK(job.outcome != storage::job_outcome::kRunning);
    out.push_back(job.scheduled_utime);
  }
  std::sort(out.begin(), out.end());
  CHECK(std::adjacent_find(out.begin(), out.end()) == out.end());
  return out;
}

// The data times of kSat's UKF snapshots in `db`, ascending.
std::vector<int64_t> ukf_snapshot_times(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  storage::HistoryQuery q;
  q.sat_id = kSat;
  q.method = "ukf";
  std::vector<int64_t> out;
  for (const auto& row :
       storage::open_database(db, read_only)->make_calibration_history()->query(q)) {
    out.push_back(row.utime);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// kSat's refit results in `db` (the history's rows of the offline methods), by time.
std::vector<storage::CalibrationRecord> refit_rows(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  storage::HistoryQuery q;
  q.sat_id = kSat;
  auto rows = storage::open_database(db, read_only)->make_calibration_history()->query(q);
  std::erase_if(rows, [](const auto& r) { return !storage::is_refit_method(r.method); });
  return rows;
}

// A log of n samples of kSat, kLogBatch per frame, frames `frame_spacing_us` apart.
std::string paced_log(const TempDir& dir, int n, int64_t frame_spacing_us) {
  const std::string log = dir.file("paced.lcm");
  magcal::test::write_batch_log(log, kSat, log_start_utime(), n, frame_spacing_us);
  return log;
}

double metric(int port, const std::string& name);

// magcald replaying `log` at its recorded pace (?speed=1) into the database of `config`, its
// operations server on a free port; constructed once it has stored `first_samples`.
struct PacedDaemon {
  std::string log_path;
  pid_t pid = -1;
  int port = -1;

  PacedDaemon(const std::string& log, const std::string& config, const TempDir& dir,
              double first_samples)
      : log_path(dir.file("magcald.log")) {
    pid = spawn({kBin + "/magcald", "--config", config, "--http-listen", "127.0.0.1:0", "--lcm-url",
                 "file://" + log + "?speed=1"},
                log_path);
    REQUIRE(pid > 0);
    port = wait_http_port(log_path, 30);
    REQUIRE(port > 0);
    REQUIRE(wait_until([&] { return metric(port, "magcal_samples_stored_total") >= first_samples; },
                       30));
  }
};

magcal::test::PromText scrape(int port) {
  const auto res = http_get(port, "/metrics");
  REQUIRE(res.status == 200);
  auto p = magcal::test::parse_prometheus_text(res.body);
  REQUIRE(p.error.empty());
  return p;
}

double metric(int port, const std::string& name) {
  return scrape(port).sum(name);
}

size_t count_of(const std::string& text, const std::string& what) {
  size_t n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// The value of `key`=N in the last "final status:" line of a daemon's log (-1 when absent).
int64_t final_status(const std::string& text, const std::string& key) {
  const size_t line = text.rfind("final status:");
  if (line == std::string::npos) return -1;
  // (" key=N", or "(key=N" for a reason's count.)
  size_t at = text.find(key + "=", line);
  while (at != std::string::npos && text[at - 1] != ' ' && text[at - 1] != '(') {
    at = text.find(key + "=", at + 1);
  }
  if (at == std::string::npos || at > text.find('\n', line)) return -1;
  return std::stoll(text.substr(at + key.size() + 1));
}

}  // namespace

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

// After a daemon that spilled ended during an outage (`stored` samples in `db`), with the server
// back: the samples its spill file holds, all committed by the next start (with a config that
// takes none of the log's samples, so that the file alone adds them), and the file gone.
// Returns what the spill file held.
int64_t check_next_start_commits_spill(const TempDir& dir, const std::string& config_text,
                                       const std::string& log, const std::string& db,
                                       int64_t stored) {
  const std::string spill_file =
      dir.file("magcal-spill-" + magcal::default_station_id() + ".spill");
  int64_t held = 0;
  {
    magcal::SampleSpill left(spill_file, "", int64_t{1} << 30);  // (the lock died with magcald)
    held = left.held_samples();
  }
  CHECK(held > 0);
  CHECK(stored_samples(db) == stored);
  const std::string again =
      write_config(dir, "again.toml", config_text + "[service]\nwhitelist = [\"SOMEONE-ELSE\"]\n");
  const std::string again_log = dir.file("magcald_again.log");
  const int rc = run({kBin + "/magcald", "--config", again, "--http-listen", "", "--lcm-url",
                      "file://" + log + "?speed=0"},
                     again_log, 120);
  const std::string text = slurp(again_log);
  INFO(text);
  REQUIRE(rc == 0);
  CHECK(stored_samples(db) == stored + held);
  CHECK(text.find("holds " + std::to_string(held) + " samples an earlier run received") !=
        std::string::npos);
  CHECK(text.find(std::to_string(held) + " samples committed (0 already stored); file removed") !=
        std::string::npos);
  CHECK_FALSE(std::filesystem::exists(spill_file));
  return held;
}

// SIGTERM to magcald `pid` during an outage: exit 0 at once (without the spill it would retry
// for pg_max_failure_s, an hour). Its log.
std::string stop_during_outage(pid_t pid, const std::string& log_path) {
  const auto t0 = std::chrono::steady_clock::now();
  ::kill(pid, SIGTERM);
  const int rc = wait_exit(pid, 30);
  const double stop_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::string text = slurp(log_path);
  INFO(text);
  CHECK(rc == 0);
  CHECK(stop_s < 10);
  return text;
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

// The [storage] keys of a server that does not answer: a reply deadline of 1 s (above a lock
// wait of 0.5 s), commits spilled past 1000 pending samples.
std::string unanswered_config_text(const std::string& db, const TempDir& dir) {
  return "db_path = \"" + db +
         "\"\nbusy_timeout_ms = 500\npg_reply_timeout_s = 1\nmax_pending_samples = 1000\n"
         "spill_dir = \"" +
         dir.file("") + "\"\n";
}

// While the server does not answer: alive, not ready, both saying why; samples spilled.
void check_rides_out_unanswered(const PacedDaemon& daemon) {
  const int port = daemon.port;
  REQUIRE(wait_until([&] { return http_get(port, "/-/ready").status == 503; }, 20));
  const auto healthy = http_get(port, "/-/healthy");
  CHECK(healthy.status == 200);
  CHECK(healthy.body.find("storage failing for") != std::string::npos);
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 1000; }, 40));
  CHECK(metric(port, "magcal_queue_overflow_total") == 0);
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
  std::this_thread::sleep_for(std::chrono::seconds(5));
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
  CHECK(up_s < 8);
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
  std::this_thread::sleep_for(std::chrono::seconds(8));  // ~5 data hours
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
  CHECK(http_get(port, "/api/v1/spacecraft").status == 200);
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
  std::string log, db, config_text;
  std::unique_ptr<PacedDaemon> daemon;

  StartedWhileDown(magcal::test::PgTestServer& s, const TempDir& d, const std::string& extra,
                   int n = 6000)
      : server(s), dir(d), log(paced_log(d, n, 200'000)), db(s.create_database()) {
    storage::open_database(db);
    server.stop();
    config_text = "db_path = \"" + db + "\"\nspill_dir = \"" + dir.file("") + "\"\n" + extra;
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
  // Started again, still down: its samples go behind the earlier run's in the file (the gauge
  // counts all the file holds; the probes tell the earlier run's apart).
  const PacedDaemon again(first.log, write_config(dir, "again.toml", first.config_text), dir, 0);
  REQUIRE(
      wait_until([&] { return metric(again.port, "magcal_samples_spilled_total") >= 200; }, 20));
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
  CHECK(count_of(text, "database commit failed (") >= 3);
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
