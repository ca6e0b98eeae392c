// Several magcald sharing one database (design.md "Fleet"), as real processes: two daemons with
// different --station replay the same paper-scenario log at once into one PostgreSQL database
// (a throwaway server: tests/storage/postgres/pg_test_server.hpp) and into one SQLite file.
// One of them owns the spacecraft (its lease): its UKF reads the samples both stored, in time
// order, and it schedules the refits (first, early, data-clock scheduled), each claimed in the
// job log, so each runs once for the fleet: one finished job and one twostep row per due time,
// the same due times and results as one daemon replaying the log alone, and one series of UKF
// snapshots equal to the lone daemon's. Without the PostgreSQL server programs the PostgreSQL
// case is skipped (with CI=true it fails).
#include <catch2/catch.hpp>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "pipeline/time_utc.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace {

using magcal::test::run;
using magcal::test::slurp;
using magcal::test::spawn;
using magcal::test::TempDir;
using magcal::test::wait_exit;
using magcal::test::wait_until;
namespace storage = magcal::storage;

const std::string kBin = MAGCAL_BIN_DIR;
const std::string kSat = "PAPER-1";
constexpr double kDaemonTimeout_s = 120;

// A refit as the fleet must run it once: (trigger, scheduled time).
using RefitKey = std::pair<std::string, int64_t>;

// The UKF snapshots of kSat in `db`, by time (fails the test when a time has two rows).
std::map<int64_t, storage::CalibrationRecord> ukf_series(const std::string& db) {
  const auto connection = storage::open_database(db);
  storage::HistoryQuery q;
  q.sat_id = kSat;
  q.method = "ukf";
  q.limit = 1'000'000;
  std::map<int64_t, storage::CalibrationRecord> out;
  for (const auto& r : connection->make_calibration_history()->query(q)) {
    INFO("ukf row at " << r.utime);
    CHECK(out.count(r.utime) == 0);
    out[r.utime] = r;
  }
  return out;
}

struct RefitRun {
  storage::RefitJob job;
  std::optional<storage::CalibrationRecord> result;  // its twostep row (none when skipped)
};

// Every refit of kSat in `db` that ran to its end (not running, not interrupted), by key; fails
// the test when a key ran twice, or a job that was not skipped names no twostep row, or a
// twostep row has no job.
std::map<RefitKey, RefitRun> finished_refits(const std::string& db) {
  const auto connection = storage::open_database(db);
  const auto jobs = connection->make_refit_job_log()->recent(kSat, 10'000);
  storage::HistoryQuery q;
  q.sat_id = kSat;
  q.method = "twostep";
  const auto rows = connection->make_calibration_history()->query(q);
  std::map<int64_t, storage::CalibrationRecord> by_id;
  for (const auto& r : rows) by_id[r.id] = r;
  std::map<RefitKey, RefitRun> out;
  size_t with_rows = 0;
  for (const auto& job : jobs) {
    INFO("job " << job.id << " " << job.trigger << " " << job.scheduled_utime << " " << job.outcome
                << " by " << job.claimed_by);
    if (job.outcome == storage::job_outcome::kInterrupted) {
      CHECK_FALSE(job.calibration_id.has_value());  // a retried attempt: no row of its own
      continue;
    }
    CHECK(job.outcome != storage::job_outcome::kRunning);
    const RefitKey key{job.trigger, job.scheduled_utime};
    CHECK(out.count(key) == 0);  // once
    RefitRun& ran = out[key];
    ran.job = job;
    if (job.outcome == storage::job_outcome::kSkipped) {
      CHECK_FALSE(job.calibration_id.has_value());
      continue;
    }
    REQUIRE(job.calibration_id.has_value());
    REQUIRE(by_id.count(*job.calibration_id) == 1);
    ran.result = by_id[*job.calibration_id];
    ++with_rows;
  }
  CHECK(rows.size() == with_rows);  // no twostep row without its job
  return out;
}

// magcald replaying `log` into `db` as `station`, started now (returns its pid).
pid_t start_daemon(const std::string& log, const std::string& db, const std::string& station,
                   const std::string& config, const std::string& daemon_log) {
  return spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", station,
                "--http-listen", "", "--lcm-url", "file://" + log + "?speed=0"},
               daemon_log);
}

size_t count_lines_with(const std::string& text, const std::string& what) {
  size_t n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// The time stamp of the first line of a daemon's log holding `what` ("YYYY-MM-DD HH:MM:SS.mmm",
// spdlog's: it sorts as the time), empty when there is none.
std::string time_of_first_line_with(const std::string& text, const std::string& what) {
  const size_t at = text.find(what);
  if (at == std::string::npos) return "";
  const size_t newline = text.rfind('\n', at);
  const size_t start = newline == std::string::npos ? 0 : newline + 1;
  const size_t end = text.find(']', start);
  if (text[start] != '[' || end == std::string::npos || end > at) return "";
  return text.substr(start + 1, end - start - 1);
}

// Both stations live at once in `db` (false while the database or its tables do not exist yet).
bool both_stations_live(const std::string& db) {
  if (!storage::is_postgres_uri(db) && !std::filesystem::exists(db)) return false;
  try {
    storage::OpenOptions read_only;
    read_only.read_only = true;
    return storage::open_database(db, read_only)
               ->make_lease_store()
               ->live_stations(magcal::now_utime())
               .size() == 2;
  } catch (const storage::StorageError&) {
    return false;
  }
}

// Two daemons (stations A and B) replaying `log` at once into `db`: each refit of `alone` (one
// daemon, the same log) ran once, by one of them, with the same result. The replays overlap
// (both stations live at once). Whichever ends first hands its spacecraft back as it stops, so
// the other may take kSat over for the rest of its own replay: legitimately, and only then.
void check_fleet_runs_each_refit_once(
    const std::string& log, const std::string& db, const std::map<RefitKey, RefitRun>& alone,
    const std::map<int64_t, storage::CalibrationRecord>& alone_ukf, const std::string& config,
    const TempDir& dir, const std::string& name) {
  const std::string log_a = dir.file(name + "_a.log"), log_b = dir.file(name + "_b.log");
  const pid_t a = start_daemon(log, db, "station-A", config, log_a);
  const pid_t b = start_daemon(log, db, "station-B", config, log_b);
  REQUIRE(a > 0);
  REQUIRE(b > 0);
  // A replay takes seconds, a daemon's start a fraction of one: both beat while both replay.
  const bool overlapped = wait_until([&] { return both_stations_live(db); }, 30);
  const int rc_a = wait_exit(a, kDaemonTimeout_s);
  const int rc_b = wait_exit(b, kDaemonTimeout_s);
  const std::string text_a = slurp(log_a), text_b = slurp(log_b);
  INFO("station A:\n" << text_a << "\nstation B:\n" << text_b);
  REQUIRE(rc_a == 0);
  REQUIRE(rc_b == 0);
  REQUIRE(overlapped);

  const auto fleet = finished_refits(db);
  std::vector<RefitKey> keys_fleet, keys_alone;
  for (const auto& [key, ran] : fleet) keys_fleet.push_back(key);
  for (const auto& [key, ran] : alone) keys_alone.push_back(key);
  CHECK(keys_fleet == keys_alone);
  for (const auto& [key, ran] : fleet) {
    INFO(key.first << " refit at " << key.second << " ran by " << ran.job.claimed_by);
    CHECK((ran.job.claimed_by == "station-A" || ran.job.claimed_by == "station-B"));
    const auto it = alone.find(key);
    if (it == alone.end()) continue;
    // The same window (both daemons received every sample): the same outcome and estimate.
    CHECK(ran.job.outcome == it->second.job.outcome);
    REQUIRE(ran.result.has_value() == it->second.result.has_value());
    if (!ran.result) continue;
    const storage::CalibrationRecord& want = *it->second.result;
    CHECK(ran.result->n_samples == want.n_samples);
    CHECK(ran.result->verdict == want.verdict);
    for (size_t i = 0; i < 3; ++i) {
      CHECK(std::abs(ran.result->bias_nT[i] - want.bias_nT[i]) <=
            1e-9 * std::max(1.0, std::abs(want.bias_nT[i])));
    }
  }
  // One owner scheduled them all; the other daemon only stored samples.
  std::set<std::string> by;
  for (const auto& [key, ran] : fleet) by.insert(ran.job.claimed_by);
  REQUIRE(by.size() == 1);
  const bool a_owned = *by.begin() == "station-A";
  const std::string& owner_text = a_owned ? text_a : text_b;
  const std::string& other_text = a_owned ? text_b : text_a;
  CHECK(count_lines_with(owner_text, "PAPER-1: owned here") == 1);
  // The other station owned kSat at most once: after the owner's replay had ended.
  const size_t taken_over = count_lines_with(other_text, "PAPER-1: owned here");
  CHECK(taken_over <= 1);
  if (taken_over == 1) {
    const std::string owner_ended = time_of_first_line_with(owner_text, "end of log");
    REQUIRE_FALSE(owner_ended.empty());
    CHECK(time_of_first_line_with(other_text, "PAPER-1: owned here") >= owner_ended);
  }
  CHECK(count_lines_with(text_a + text_b, ": not run here (the ") == 0);
  // One series of UKF snapshots, the lone daemon's: the owner's filter read every sample in time
  // order, whichever station stored it.
  const auto ukf = ukf_series(db);
  REQUIRE(ukf.size() == alone_ukf.size());
  for (const auto& [utime, want] : alone_ukf) {
    const auto it = ukf.find(utime);
    REQUIRE(it != ukf.end());
    INFO("ukf row at " << utime);
    CHECK(it->second.verdict == want.verdict);
    for (size_t i = 0; i < 3; ++i) {
      CHECK(std::abs(it->second.bias_nT[i] - want.bias_nT[i]) <=
            1e-9 * std::max(1.0, std::abs(want.bias_nT[i])));
    }
  }
}

// The log, the config and what one daemon alone makes of the log: built once per process
// (each section runs the test case's body again).
struct Baseline {
  TempDir dir{"magcald_fleet"};
  std::string log = dir.file("six_hours.lcm");
  std::string config = dir.file("d.toml");
  std::map<RefitKey, RefitRun> alone;
  std::map<int64_t, storage::CalibrationRecord> alone_ukf;
};

const Baseline& baseline() {
  static const auto built = [] {
    auto b = std::make_unique<Baseline>();
    // 6 h at 10 s: the first and early refits (from [refit] min_samples on) and data-clock
    // refits every 2 h, a few seconds of replay.
    REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "6", "--seed", "1",
                 "--out", b->log, "--batch", "200"},
                b->dir.file("sim.log")) == 0);
    {
      std::ofstream out(b->config);
      // The process's own spill directory: ctest runs test cases in parallel from one
      // directory, and a station's spill file is locked by its daemon.
      out << "[refit]\nclock = \"data\"\nevery_hours = 2\nmin_samples = 1000\n"
          << "[storage]\nspill_dir = \"" << b->dir.file("") << "\"\n";
    }
    const std::string db = b->dir.file("alone.db"), daemon_log = b->dir.file("alone.log");
    const int rc = run({kBin + "/magcald", "--config", b->config, "--db", db, "--station", "solo",
                        "--http-listen", "", "--lcm-url", "file://" + b->log + "?speed=0"},
                       daemon_log, kDaemonTimeout_s);
    INFO(slurp(daemon_log));
    REQUIRE(rc == 0);
    b->alone = finished_refits(db);
    b->alone_ukf = ukf_series(db);
    return b;
  }();
  return *built;
}

}  // namespace

TEST_CASE("two magcald sharing one database run each refit once", "[daemon][fleet][integration]") {
  const Baseline& b = baseline();
  size_t scheduled = 0;
  for (const auto& [key, ran] : b.alone) scheduled += key.first == "scheduled" ? 1 : 0;
  REQUIRE(scheduled >= 2);
  REQUIRE(b.alone.size() > scheduled);  // and a first refit at least
  TempDir dir("magcald_fleet_run");

  SECTION("PostgreSQL") {
    magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
    if (server == nullptr) return;
    check_fleet_runs_each_refit_once(b.log, server->create_database(), b.alone, b.alone_ukf,
                                     b.config, dir, "pg");
  }
  SECTION("one SQLite file") {
    check_fleet_runs_each_refit_once(b.log, dir.file("shared.db"), b.alone, b.alone_ukf, b.config,
                                     dir, "sqlite");
  }
}
