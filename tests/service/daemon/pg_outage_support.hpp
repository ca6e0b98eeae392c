// What the PostgreSQL outage tests of magcald share (daemon_pg_outage_test.cpp,
// daemon_pg_down_at_start_test.cpp): paced replay logs, their configs, a paced daemon with its
// operations server, and what the database, the metrics and the daemon's log say afterwards.
#pragma once

#include <signal.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "service/config/daemon_config.hpp"
#include "service/daemon/intake/sample_spill.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/service/prometheus_text.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace magcal::test::pg_outage {

using magcal::test::http_get;
using magcal::test::run;
using magcal::test::slurp;
using magcal::test::spawn;
using magcal::test::TempDir;
using magcal::test::wait_exit;
using magcal::test::wait_http_port;
using magcal::test::wait_until;
namespace storage = magcal::storage;

inline const std::string kBin = MAGCAL_BIN_DIR;
inline const std::string kSat = "OUTAGE-1";
// [refit] keys: data-clock refits every data hour.
inline const std::string kHourlyRefits = "clock = \"data\"\nevery_hours = 1\n";

// Samples 10 s apart from 300 h ago (within [ingest] max_future_s of the wall clock, and the
// whole log within the window below).
inline int64_t log_start_utime() {
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
inline std::string write_config(const TempDir& dir, const std::string& name,
                                const std::string& extra, int commit_every_samples = 200,
                                const std::string& refit_extra = "") {
  const std::string path = dir.file(name);
  const bool computes = refit_extra.find("min_samples") != std::string::npos;
  std::ofstream(path) << "[storage]\nwindow_hours = 200\ncommit_every_samples = "
                      << commit_every_samples << "\n"
                      << extra << "[refit]\n"
                      << (computes ? "" : "min_samples = 1000000000\n") << refit_extra;
  return path;
}

inline int64_t stored_samples(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  return storage::open_database(db, read_only)->make_sample_window_store()->count(kSat);
}

// The same log replayed as fast as it goes into a fresh SQLite file: its path.
inline std::string reference_db(const std::string& log, const TempDir& dir,
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
inline int64_t reference_count(const std::string& log, const TempDir& dir) {
  return stored_samples(reference_db(log, dir));
}

// The due times of kSat's scheduled refits in `db` that ran to their end, ascending; fails the
// test when one ran twice.
inline std::vector<int64_t> scheduled_refits(const std::string& db) {
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
inline std::vector<int64_t> ukf_snapshot_times(const std::string& db) {
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
inline std::vector<storage::CalibrationRecord> refit_rows(const std::string& db) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  storage::HistoryQuery q;
  q.sat_id = kSat;
  auto rows = storage::open_database(db, read_only)->make_calibration_history()->query(q);
  std::erase_if(rows, [](const auto& r) { return !storage::is_refit_method(r.method); });
  return rows;
}

// A log of n samples of kSat, kLogBatch per frame, frames `frame_spacing_us` apart.
inline std::string paced_log(const TempDir& dir, int n, int64_t frame_spacing_us) {
  const std::string log = dir.file("paced.lcm");
  magcal::test::write_batch_log(log, kSat, log_start_utime(), n, frame_spacing_us);
  return log;
}

inline magcal::test::PromText scrape(int port) {
  const auto res = http_get(port, "/metrics");
  REQUIRE(res.status == 200);
  auto p = magcal::test::parse_prometheus_text(res.body);
  REQUIRE(p.error.empty());
  return p;
}

inline double metric(int port, const std::string& name) {
  return scrape(port).sum(name);
}

// magcald replaying `log` at its recorded pace (?speed=1) into the database of `config`, its
// operations server on a free port; constructed once it has stored `first_samples` (0: once it
// listens; it may have ended since, as one that gives up on a database down from its start).
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
    if (first_samples <= 0) return;
    REQUIRE(wait_until([&] { return metric(port, "magcal_samples_stored_total") >= first_samples; },
                       30));
  }
};

inline size_t count_of(const std::string& text, const std::string& what) {
  size_t n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// The value of `key`=N in the last "final status:" line of a daemon's log (-1 when absent).
inline int64_t final_status(const std::string& text, const std::string& key) {
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

// After a daemon that spilled ended during an outage (`stored` samples in `db`), with the server
// back: the samples its spill file holds, all committed by the next start (with a config that
// takes none of the log's samples, so that the file alone adds them), and the file gone.
// Returns what the spill file held.
inline int64_t check_next_start_commits_spill(const TempDir& dir, const std::string& config_text,
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
inline std::string stop_during_outage(pid_t pid, const std::string& log_path) {
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

// The [storage] keys of a server that does not answer: a reply deadline of 1 s (above a lock
// wait of 0.5 s), commits spilled past 1000 pending samples.
inline std::string unanswered_config_text(const std::string& db, const TempDir& dir) {
  return "db_path = \"" + db +
         "\"\nbusy_timeout_ms = 500\npg_reply_timeout_s = 1\nmax_pending_samples = 1000\n"
         "spill_dir = \"" +
         dir.file("") + "\"\n";
}

// While the server does not answer: alive, not ready, both saying why; samples spilled.
inline void check_rides_out_unanswered(const PacedDaemon& daemon) {
  const int port = daemon.port;
  REQUIRE(wait_until([&] { return http_get(port, "/-/ready").status == 503; }, 20));
  const auto healthy = http_get(port, "/-/healthy");
  CHECK(healthy.status == 200);
  CHECK(healthy.body.find("storage failing for") != std::string::npos);
  REQUIRE(wait_until([&] { return metric(port, "magcal_samples_spilled_total") >= 1000; }, 40));
  CHECK(metric(port, "magcal_queue_overflow_total") == 0);
}

}  // namespace magcal::test::pg_outage
