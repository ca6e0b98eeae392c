// Three ground stations, one PostgreSQL database (issue 19, design.md "Fleet"), as real
// processes: a day of the paper scenario split into three stations' passes (30 min each in
// turn, neighbours overlapping by 400 s, so each station receives about 41 % of the samples
// and every sample reaches at least one), each station's log replayed by its own magcald at the
// same speed from the same start. The owner of the spacecraft is killed with SIGKILL mid-day;
// once another daemon has taken it over, the killed station restarts, re-sending its last half
// hour (its uncommitted samples) before going on with its passes.
//
// Afterwards, against one daemon replaying the whole log alone:
//   - the window holds every sample of the union exactly once (contiguous up to the last one);
//   - another station took the spacecraft over within the lease time, and its UKF went on from
//     the stored state;
//   - the UKF snapshots form one series (one row per time, on one 60 s grid);
//   - every scheduled refit ran once and used the union window; its bias and the last UKF
//     snapshot's are within 1 sigma of the lone daemon's.
// Without the PostgreSQL server programs the test is skipped (with CI=true it fails).
#include <signal.h>
#include <catch2/catch.hpp>
#include <lcm/lcm-cpp.hpp>
#include <nlohmann/json.hpp>

#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "schemas/magcal_messages.hpp"
#include "service/io/exit_codes.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/service/prometheus_text.hpp"
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
constexpr int kStations = 3;
constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kPass_utime = 1800 * kSecond;    // each station's pass, in turn
constexpr int64_t kOverlap_utime = 200 * kSecond;  // each side: neighbours share 400 s
constexpr int kFrameSamples = 30;                  // samples per downlink packet
constexpr double kSpeed = 2000.0;                  // replay speed (24 h in 43 s)
constexpr double kLease_s = 3.0;
// Data time a replay may run ahead of another (process start, scheduling): 0.9 s of wall time.
constexpr double kReorderDelay_s = 1800.0;
constexpr int64_t kResend_utime = 1800 * kSecond;  // the restarted station re-sends this much

std::vector<magcal::mag_sample_t> read_samples(const std::string& log_path) {
  lcm::LogFile log(log_path, "r");
  REQUIRE(log.good());
  std::vector<magcal::mag_sample_t> out;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel != "MAGCAL_BATCH") continue;
    magcal::mag_batch_t b;
    REQUIRE(b.decode(e->data, 0, e->datalen) == e->datalen);
    for (const auto& s : b.samples) out.push_back(s);
  }
  return out;
}

// Stations that receive a sample at `utime` (pass schedule from t0).
std::vector<int> stations_of(int64_t utime, int64_t t0) {
  const int64_t since = utime - t0;
  const int k = static_cast<int>((since / kPass_utime) % kStations);
  const int64_t into = since % kPass_utime;
  std::vector<int> out{k};
  if (into < kOverlap_utime && since >= kPass_utime) out.push_back((k + kStations - 1) % kStations);
  if (into >= kPass_utime - kOverlap_utime) out.push_back((k + 1) % kStations);
  return out;
}

// Writes `samples` as mag_batch_t frames (a new frame at every gap in the pass), after a SYNC
// event at sync_utime: every station's replay starts at the same data time. Frames are stamped
// with their last sample's time, or sync_utime for older samples (a re-send, played at once).
void write_station_log(const std::string& path, const std::vector<magcal::mag_sample_t>& samples,
                       int64_t sync_utime) {
  lcm::LogFile out(path, "w");
  REQUIRE(out.good());
  int64_t event = 0;
  magcal::test::write_log_event(out, event++, sync_utime, "SYNC", magcal::daemon_status_t{});
  magcal::mag_batch_t batch;
  batch.sat_id = kSat;
  auto flush = [&] {
    if (batch.samples.empty()) return;
    batch.n = static_cast<int32_t>(batch.samples.size());
    magcal::test::write_log_event(out, event++, std::max(sync_utime, batch.samples.back().utime),
                                  "MAGCAL_BATCH", batch);
    batch.samples.clear();
  };
  for (const auto& s : samples) {
    if (!batch.samples.empty() && (s.utime - batch.samples.back().utime > 10 * kSecond ||
                                   static_cast<int>(batch.samples.size()) == kFrameSamples)) {
      flush();
    }
    batch.samples.push_back(s);
  }
  flush();
}

std::map<int64_t, storage::CalibrationRecord> history_by_time(storage::Connection& db,
                                                              const std::string& method) {
  storage::HistoryQuery q;
  q.sat_id = kSat;
  q.method = method;
  q.limit = 1'000'000;
  std::map<int64_t, storage::CalibrationRecord> out;
  for (const auto& r : db.make_calibration_history()->query(q)) {
    INFO(method << " row at " << r.utime);
    CHECK(out.count(r.utime) == 0);  // one row per time
    out[r.utime] = r;
  }
  return out;
}

// Finished scheduled refits by due time; each due time once.
std::map<int64_t, storage::RefitJob> scheduled_refits(storage::Connection& db) {
  std::map<int64_t, storage::RefitJob> out;
  for (const auto& job : db.make_refit_job_log()->recent(kSat, 10'000)) {
    if (job.trigger != "scheduled" || job.outcome == storage::job_outcome::kInterrupted) continue;
    INFO("scheduled refit at " << job.scheduled_utime << " by " << job.claimed_by << ": "
                               << job.outcome);
    CHECK(job.outcome != storage::job_outcome::kRunning);
    CHECK(out.count(job.scheduled_utime) == 0);
    out[job.scheduled_utime] = job;
  }
  return out;
}

// Wall clock, as the leases count it.
int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

double wall_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

}  // namespace

TEST_CASE("three stations, one database: one window, one series, each refit once, failover",
          "[daemon][fleet][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_stations");
  const std::string day = dir.file("day.lcm");
  REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "24", "--seed", "3",
               "--out", day, "--batch", "200"},
              dir.file("sim.log")) == 0);
  const auto all = read_samples(day);
  REQUIRE(all.size() == 8640);
  const int64_t t0 = all.front().utime;
  std::vector<std::vector<magcal::mag_sample_t>> by_station(kStations);
  for (const auto& s : all) {
    for (const int k : stations_of(s.utime, t0)) by_station[static_cast<size_t>(k)].push_back(s);
  }
  for (const auto& samples : by_station) {
    // Each sees well under half of the day (the issue's 38-43 %).
    CHECK(samples.size() > all.size() * 35 / 100);
    CHECK(samples.size() < all.size() * 45 / 100);
  }
  const std::string names[kStations] = {"gs-a", "gs-b", "gs-c"};
  std::string logs[kStations];
  for (int k = 0; k < kStations; ++k) {
    logs[k] = dir.file(names[k] + ".lcm");
    write_station_log(logs[k], by_station[static_cast<size_t>(k)], t0);
  }
  const std::string config = dir.file("d.toml");
  {
    std::ofstream out(config);
    // Each test's own spill directory: ctest runs test cases in parallel from one directory,
    // and a station's spill file is locked by its daemon.
    out << "[refit]\nclock = \"data\"\nevery_hours = 6\n"
        << "[fleet]\nlease_s = " << kLease_s << "\nreorder_delay_s = " << kReorderDelay_s << "\n"
        << "[storage]\nspill_dir = \"" << dir.file("") << "\"\n";
  }

  // One daemon, the whole log: what the fleet must match.
  const std::string alone_db = dir.file("alone.db");
  {
    const std::string log = dir.file("alone.log");
    const int rc = run({kBin + "/magcald", "--config", config, "--db", alone_db, "--station",
                        "solo", "--http-listen", "", "--lcm-url", "file://" + day + "?speed=0"},
                       log, 120);
    INFO(slurp(log));
    REQUIRE(rc == 0);
  }

  const std::string db = server->create_database();
  const std::string url_suffix = "?speed=" + std::to_string(static_cast<int>(kSpeed));
  std::string daemon_logs[kStations];
  pid_t pids[kStations];
  const double start = wall_s();
  for (int k = 0; k < kStations; ++k) {
    daemon_logs[k] = dir.file(names[k] + ".daemon.log");
    pids[k] = spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", names[k],
                     "--http-listen", "", "--lcm-url", "file://" + logs[k] + url_suffix},
                    daemon_logs[k]);
    REQUIRE(pids[k] > 0);
  }
  const auto connection = storage::open_database(db);
  const auto leases = connection->make_lease_store();

  // Mid-day (10 h of data stored): kill the owner. The replay's clock, not the wall's: a loaded
  // machine replays slower than kSpeed.
  const auto samples = connection->make_sample_window_store();
  REQUIRE(wait_until(
      [&] {
        const auto newest = samples->newest_utime(kSat);
        return newest && *newest >= t0 + 10 * 3600 * kSecond;
      },
      10 * 3600 / kSpeed * 4 + 30));
  const auto owner = leases->owner_of(kSat, wall_utime());
  REQUIRE(owner.has_value());
  int killed = -1;
  for (int k = 0; k < kStations; ++k) killed = names[k] == *owner ? k : killed;
  REQUIRE(killed >= 0);
  REQUIRE(::kill(pids[killed], SIGKILL) == 0);
  const double killed_at = wall_s();
  wait_exit(pids[killed], 10);
  INFO("killed " << *owner << " at " << killed_at - start << " s");

  // Another station takes the spacecraft over within the lease time (plus its renewal period).
  std::string new_owner;
  REQUIRE(wait_until(
      [&] {
        const auto o = leases->owner_of(kSat, wall_utime());
        if (o && *o != *owner) new_owner = *o;
        return !new_owner.empty();
      },
      kLease_s * 4 / 3 + 5));
  const double takeover_s = wall_s() - killed_at;
  INFO("taken over by " << new_owner << " after " << takeover_s << " s");
  CHECK(takeover_s <= kLease_s * 4 / 3 + 1.0);
  {
    // magcal status names the owner.
    const std::string status = dir.file("status.json");
    REQUIRE(run({kBin + "/magcal", "status", "--db", db, "--json"}, status) == 0);
    const auto j = nlohmann::json::parse(slurp(status));
    REQUIRE(j["spacecraft"].size() == 1);
    CHECK(j["spacecraft"][0]["owner"]["station"] == new_owner);
    CHECK(j["spacecraft"][0]["owner"]["lease_epoch"] == 2);
    // ... and lists the stations: the killed one gone (its heartbeat expired with the lease it
    // held: both were renewed at one time), the new owner live with the spacecraft.
    REQUIRE(j["stations"].size() == kStations);
    for (const auto& st : j["stations"]) {
      INFO(st.dump());
      CHECK(st["live"] == (st["station"] != *owner));
      CHECK(st["spacecraft_owned"] == (st["station"] == new_owner ? 1 : 0));
    }
  }

  // The killed station comes back: it re-sends its last half hour, then goes on with its passes
  // at the data time the others have reached. What only it received in between comes late for
  // the owner's filter (the refits still use it, once stored).
  int64_t down_only = 0;
  {
    const int64_t now_data = t0 + static_cast<int64_t>((wall_s() - start) * kSpeed * 1e6);
    const int64_t killed_data = t0 + static_cast<int64_t>((killed_at - start) * kSpeed * 1e6);
    for (const auto& s : all) {
      const auto st = stations_of(s.utime, t0);
      if (s.utime >= killed_data - kResend_utime && s.utime <= now_data && st.size() == 1 &&
          st[0] == killed) {
        ++down_only;
      }
    }
    std::vector<magcal::mag_sample_t> rest;
    for (const auto& s : by_station[static_cast<size_t>(killed)]) {
      if (s.utime >= killed_data - kResend_utime) rest.push_back(s);
    }
    const std::string restart_log = dir.file(names[killed] + ".restart.lcm");
    write_station_log(restart_log, rest, now_data);
    daemon_logs[killed] = dir.file(names[killed] + ".restart.daemon.log");
    pids[killed] =
        spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", names[killed],
               "--http-listen", "", "--lcm-url", "file://" + restart_log + url_suffix},
              daemon_logs[killed]);
    REQUIRE(pids[killed] > 0);
  }
  std::string texts;
  for (int k = 0; k < kStations; ++k) {
    const int rc = wait_exit(pids[k], 120);
    texts += names[k] + ":\n" + slurp(daemon_logs[k]) + "\n";
    INFO(names[k] << " exit " << rc);
    CHECK(rc == 0);
  }
  {
    // The replays end within about a lease round of each other, so the last owner may hand the
    // spacecraft over (clean stop) after the others stopped taking leases, with the end of the
    // day not yet filtered. In operations a live station takes it within lease_s / 3; here a
    // station started afterwards does (it re-sends the day's last sample, a duplicate): it
    // takes the free lease and its UKF goes on from the stored state to the end.
    const std::string closing_log = dir.file("closing.lcm");
    write_station_log(closing_log, {all.back()}, all.back().utime);
    const std::string closing_daemon_log = dir.file("closing.daemon.log");
    const pid_t closing =
        spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", names[0],
               "--http-listen", "", "--lcm-url", "file://" + closing_log + "?speed=0"},
              closing_daemon_log);
    REQUIRE(closing > 0);
    const int rc = wait_exit(closing, 120);
    texts += names[0] + " (closing):\n" + slurp(closing_daemon_log) + "\n";
    INFO("closing station exit " << rc);
    CHECK(rc == 0);
  }
  INFO(texts);
  // Seq gaps are missing only where no station delivered the sample in time for the owner's
  // filter: about what only the killed station had while it was down (before: each station
  // counted the others' passes, about 59 % of the day).
  int64_t missing = 0;
  for (size_t at = texts.find("final status:"); at != std::string::npos;
       at = texts.find("final status:", at + 1)) {
    const size_t m = texts.find("missing_by_seq=", at);
    REQUIRE(m != std::string::npos);
    missing += std::stoll(texts.substr(m + 15));
  }
  INFO("missing_by_seq over the stations " << missing << ", only at the killed station while "
                                           << "down " << down_only);
  // (Plus at most one reorder delay of samples a replay that fell that far behind delivered too
  // late for the filter: a slow machine, or the sanitizers.)
  CHECK(missing <= down_only + static_cast<int64_t>(kReorderDelay_s / 10));
  // The new owner's UKF went on from the stored state (not from the first sample).
  CHECK(texts.find("PAPER-1: owned here (lease epoch 2); its UKF goes on from 2") !=
        std::string::npos);

  // The window: every sample of the union once, contiguous up to the last one of the day.
  std::vector<storage::StoredSample> rows;
  connection->make_sample_window_store()->read_window(kSat, 0, INT64_MAX, rows);
  REQUIRE(!rows.empty());
  CHECK(rows.back().utime == all.back().utime);
  size_t first = 0;
  while (first < all.size() && all[first].utime < rows.front().utime) ++first;
  REQUIRE(rows.size() == all.size() - first);
  for (size_t i = 0; i < rows.size(); ++i) {
    INFO("row " << i);
    REQUIRE(rows[i].utime == all[first + i].utime);
    CHECK(rows[i].seq == all[first + i].seq);
  }
  CHECK(rows.size() >= 12 * 360);  // the window (12 h at 10 s), retention kept it
  // Each station stored the samples it delivered first.
  const auto by = connection->make_sample_window_store()->count_by_station(kSat, 0, INT64_MAX);
  CHECK(by.size() == kStations);

  // One UKF series, on one grid, ending where the lone daemon's ends, within 1 sigma of it.
  const auto alone = storage::open_database(alone_db);
  const auto ukf = history_by_time(*connection, "ukf");
  const auto ukf_alone = history_by_time(*alone, "ukf");
  REQUIRE(!ukf.empty());
  REQUIRE(!ukf_alone.empty());
  // (A snapshot is taken at the first sample at or after each minute: after a gap in what the
  // filter read, past the minute, but never two in one minute.)
  std::set<int64_t> minutes;
  for (const auto& [utime, r] : ukf) {
    INFO("UKF row at " << (utime - t0) / kSecond << " s");
    CHECK(minutes.insert((utime - t0) / (60 * kSecond)).second);
  }
  size_t off_minute = 0;
  for (const auto& [utime, r] : ukf) off_minute += (utime - t0) % (60 * kSecond) != 0 ? 1 : 0;
  CHECK(off_minute <= ukf.size() / 20);
  CHECK(ukf.rbegin()->first == ukf_alone.rbegin()->first);
  const auto& last = ukf.rbegin()->second;
  const auto& last_alone = ukf_alone.rbegin()->second;
  for (size_t i = 0; i < 3; ++i) {
    INFO("UKF bias axis " << i << ": fleet " << last.bias_nT[i] << ", alone "
                          << last_alone.bias_nT[i] << " +- " << last_alone.bias_sigma_nT[i]);
    CHECK(std::abs(last.bias_nT[i] - last_alone.bias_nT[i]) <= last_alone.bias_sigma_nT[i]);
  }

  // Every scheduled refit once, on the union window, as the lone daemon's.
  const auto refits = scheduled_refits(*connection);
  const auto refits_alone = scheduled_refits(*alone);
  const auto twostep = history_by_time(*connection, "twostep");
  const auto twostep_alone = history_by_time(*alone, "twostep");
  REQUIRE(refits.size() == refits_alone.size());
  REQUIRE(refits.size() >= 3);
  for (const auto& [due, want_job] : refits_alone) {
    INFO("scheduled refit at " << due);
    const auto it = refits.find(due);
    REQUIRE(it != refits.end());
    CHECK(it->second.outcome == want_job.outcome);
    if (!want_job.calibration_id) continue;
    REQUIRE(it->second.calibration_id.has_value());
    const auto got = twostep.find(due);
    const auto want = twostep_alone.find(due);
    REQUIRE(got != twostep.end());
    REQUIRE(want != twostep_alone.end());
    // The union window: all of it, but for what only the killed station had while it was down
    // when the refit ran before the re-send came.
    CHECK(got->second.n_samples <= want->second.n_samples);
    CHECK(got->second.n_samples >= want->second.n_samples - down_only);
    for (size_t i = 0; i < 3; ++i) {
      CHECK(std::abs(got->second.bias_nT[i] - want->second.bias_nT[i]) <=
            want->second.bias_sigma_nT[i]);
    }
  }
}

TEST_CASE("the live daemons share the spacecraft evenly, and take over those of one that stops",
          "[daemon][fleet][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_share");
  // 30 spacecraft, each with a frame every 0.5 s of log time for 20 s (speed 1).
  constexpr int kSats = 30;
  constexpr int kFrames = 40;
  const std::string log = dir.file("fleet.lcm");
  {
    lcm::LogFile out(log, "w");
    REQUIRE(out.good());
    const int64_t t0 = 1'767'225'600LL * kSecond;
    int64_t event = 0;
    for (int f = 0; f < kFrames; ++f) {
      for (int k = 0; k < kSats; ++k) {
        magcal::mag_batch_t batch;
        batch.sat_id = "SAT-" + std::to_string(k);
        for (int i = 0; i < 5; ++i) {
          batch.samples.push_back(magcal::test::turning_field_sample(batch.sat_id, t0, f * 5 + i));
        }
        batch.n = static_cast<int32_t>(batch.samples.size());
        magcal::test::write_log_event(out, event++, t0 + f * 500'000, "MAGCAL_BATCH", batch);
      }
    }
  }
  const std::string config = dir.file("d.toml");
  {
    std::ofstream out(config);
    out << "[fleet]\nlease_s = " << kLease_s << "\n"
        << "[storage]\nspill_dir = \"" << dir.file("") << "\"\n";
  }
  const std::string db = server->create_database();
  const std::string names[kStations] = {"gs-a", "gs-b", "gs-c"};
  pid_t pids[kStations];
  for (int k = 0; k < kStations; ++k) {
    pids[k] = spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", names[k],
                     "--http-listen", "", "--lcm-url", "file://" + log + "?speed=1"},
                    dir.file(names[k] + ".log"));
    REQUIRE(pids[k] > 0);
  }
  const auto connection = storage::open_database(db);
  const auto leases = connection->make_lease_store();
  auto owned_by = [&] {
    const int64_t now = wall_utime();
    std::map<std::string, int> out;
    for (const auto& l : leases->list()) {
      if (l.held_at(now)) ++out[l.owner];
    }
    return out;
  };
  auto logs = [&] {
    std::string text;
    for (int k = 0; k < kStations; ++k) {
      text += names[k] + ":\n" + slurp(dir.file(names[k] + ".log")) + "\n";
    }
    return text;
  };
  // Three live daemons: 10 each (the first to start takes all, then hands over the excess).
  const bool shared = wait_until(
      [&] {
        const auto by = owned_by();
        return by.size() == 3 && by.count("gs-a") && by.at("gs-a") == 10 && by.at("gs-b") == 10;
      },
      10);
  INFO(logs());
  REQUIRE(shared);
  // gs-a stops (SIGTERM: it hands its spacecraft back at once): the other two share all 30.
  REQUIRE(::kill(pids[0], SIGTERM) == 0);
  CHECK(wait_exit(pids[0], 10) == 0);
  const bool taken = wait_until(
      [&] {
        const auto by = owned_by();
        return by.size() == 2 && by.count("gs-b") && by.at("gs-b") == 15 && by.count("gs-c") &&
               by.at("gs-c") == 15;
      },
      kLease_s + 2);
  INFO(logs());
  CHECK(taken);
  for (int k = 1; k < kStations; ++k) CHECK(wait_exit(pids[k], 60) == 0);
  // Every spacecraft's snapshots form one series, whoever owned it when.
  for (int k = 0; k < kSats; ++k) {
    storage::HistoryQuery q;
    q.sat_id = "SAT-" + std::to_string(k);
    q.method = "ukf";
    q.limit = 100'000;
    std::set<int64_t> times;
    for (const auto& r : connection->make_calibration_history()->query(q)) {
      INFO(q.sat_id << " ukf row at " << r.utime);
      CHECK(times.insert(r.utime).second);
    }
  }
}

TEST_CASE("two magcald with one station id: both stop with the reason, none keeps running",
          "[daemon][fleet][integration]") {
  TempDir dir("magcald_same_station");
  // 20 s of telemetry at speed 1 (a frame every 0.2 s).
  const std::string log = dir.file("sat.lcm");
  magcal::test::write_batch_log(log, kSat, 1'767'225'600LL * kSecond, 100 * magcal::test::kLogBatch,
                                200'000);
  const std::string config = dir.file("d.toml");
  {
    std::ofstream out(config);
    out << "[fleet]\nlease_s = " << kLease_s << "\n";
  }
  const std::string db = dir.file("shared.db");
  const std::string log_a = dir.file("a.log"), log_b = dir.file("b.log");
  const pid_t a = spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", "dup",
                         "--http-listen", "", "--lcm-url", "file://" + log + "?speed=1"},
                        log_a);
  REQUIRE(a > 0);
  // The first one holds the spacecraft before the newcomer starts.
  REQUIRE(wait_until(
      [&] { return slurp(log_a).find("owned here (lease epoch 1)") != std::string::npos; }, 15));
  const pid_t b = spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", "dup",
                         "--http-listen", "", "--lcm-url", "file://" + log + "?speed=1"},
                        log_b);
  REQUIRE(b > 0);
  const int rc_a = wait_exit(a, 15);
  const int rc_b = wait_exit(b, 15);
  const std::string text = slurp(log_a) + "\n" + slurp(log_b);
  INFO(text);
  CHECK(rc_a == magcal::kExitUsage);
  CHECK(rc_b == magcal::kExitUsage);
  CHECK(text.find("another magcald runs as station 'dup'") != std::string::npos);
  // The newcomer was told at once what its first beat found.
  CHECK(slurp(log_b).find("the heartbeat of a previous process is live") != std::string::npos);
  // Until then never two processes wrote the spacecraft's snapshots: the newcomer took the
  // lease under the next epoch, so the first one's fenced writes fail (lease_store_test: the
  // old epoch's holds() is false once reclaimed).
  CHECK(slurp(log_b).find("owned here (lease epoch 2)") != std::string::npos);
}

TEST_CASE(
    "stations whose result-affecting settings differ: warned, counted and marked, not refused",
    "[daemon][fleet][integration]") {
  TempDir dir("magcald_settings");
  // 20 s of telemetry at speed 1: both daemons are still replaying when the checks are done.
  const std::string log = dir.file("sat.lcm");
  magcal::test::write_batch_log(log, kSat, 1'767'225'600LL * kSecond, 100 * magcal::test::kLogBatch,
                                200'000);
  for (const bool differ : {true, false}) {
    INFO((differ ? "[refit] every_hours 0 at gs-a, 6 at gs-b" : "equal settings"));
    const std::string config_a = dir.file("a.toml"), config_b = dir.file("b.toml");
    std::ofstream(config_a) << "[fleet]\nlease_s = " << kLease_s << "\n";
    std::ofstream(config_b) << "[fleet]\nlease_s = " << kLease_s << "\n"
                            << (differ ? "[refit]\nevery_hours = 6\n" : "")
                            << "[log]\nlevel = \"debug\"\n";  // not a result: not compared
    const std::string db = dir.file(differ ? "differ.db" : "equal.db");
    const std::string log_a = dir.file(differ ? "differ_a.log" : "equal_a.log");
    const std::string log_b = dir.file(differ ? "differ_b.log" : "equal_b.log");
    const auto start = [&](const std::string& config, const std::string& station,
                           const std::string& out) {
      return spawn({kBin + "/magcald", "--config", config, "--db", db, "--station", station,
                    "--http-listen", "127.0.0.1:0", "--lcm-url", "file://" + log + "?speed=1"},
                   out);
    };
    const pid_t a = start(config_a, "gs-a", log_a);
    REQUIRE(a > 0);
    const int port_a = magcal::test::wait_http_port(log_a, 10);
    // gs-b starts later: gs-a sees a new live station at a later lease round, gs-b at its start.
    const pid_t b = start(config_b, "gs-b", log_b);
    REQUIRE(b > 0);
    const int port_b = magcal::test::wait_http_port(log_b, 10);
    REQUIRE(port_a > 0);
    REQUIRE(port_b > 0);
    const auto mismatch = [](int port) {
      const auto p =
          magcal::test::parse_prometheus_text(magcal::test::http_get(port, "/metrics").body);
      return p.value("magcal_fleet_settings_mismatch").value_or(-1.0);
    };
    // Both have seen the other live (their gauges are set at each lease round, kLease_s / 3).
    const auto connection = storage::open_database(db);
    const auto leases = connection->make_lease_store();
    REQUIRE(wait_until([&] { return leases->live_stations(wall_utime()).size() == 2; }, 10));
    // Each compares the settings of the live stations in the lease round of its heartbeat, after
    // the beat: a beat after both were live means a comparison that saw both.
    const int64_t both_live_utime = wall_utime();
    REQUIRE(wait_until(
        [&] {
          const auto rows = leases->stations();
          return rows.size() == 2 && rows[0].heartbeat_utime > both_live_utime &&
                 rows[1].heartbeat_utime > both_live_utime;
        },
        10));
    const std::string warning_a =
        "settings differ from station gs-b: refit.every_hours 0 here, 6 there; results of a "
        "spacecraft depend on which station owns it";
    const std::string warning_b =
        "settings differ from station gs-a: refit.every_hours 6 here, 0 there";
    const auto status = magcal::test::run_magcal("status --db " + db, dir);
    const auto status_json = magcal::test::run_magcal("status --json --db " + db, dir);
    const double gauge_a = mismatch(port_a), gauge_b = mismatch(port_b);
    REQUIRE(::kill(a, SIGTERM) == 0);
    REQUIRE(::kill(b, SIGTERM) == 0);
    CHECK(wait_exit(a, 15) == 0);  // a mixed fleet runs: a rolling config change passes here
    CHECK(wait_exit(b, 15) == 0);
    const std::string text_a = slurp(log_a), text_b = slurp(log_b);
    INFO("gs-a:\n" << text_a << "\ngs-b:\n" << text_b << "\nstatus:\n" << status.out << status.err);
    REQUIRE(status.exit_code == 0);
    REQUIRE(status_json.exit_code == 0);
    const auto stations = nlohmann::json::parse(status_json.out)["stations"];
    REQUIRE(stations.size() == 2);
    if (differ) {
      CHECK(text_a.find(warning_a) != std::string::npos);
      CHECK(text_b.find(warning_b) != std::string::npos);
      // Once per station, not at every lease round.
      CHECK(text_a.find("settings differ") == text_a.rfind("settings differ"));
      CHECK(gauge_a == 1.0);
      CHECK(gauge_b == 1.0);
      // One against one: no majority, so both are marked, each against the other.
      CHECK(status.out.find("SETTINGS DIFFER from gs-b: refit.every_hours 0 here, 6 there\n") !=
            std::string::npos);
      CHECK(status.out.find("SETTINGS DIFFER from gs-a: refit.every_hours 6 here, 0 there\n") !=
            std::string::npos);
      CHECK(stations[1]["settings_differ"]["keys"] ==
            nlohmann::json::parse(R"([{"key": "refit.every_hours", "here": "6", "there": "0"}])"));
      CHECK(stations[0]["settings_hash"] != stations[1]["settings_hash"]);
    } else {
      CHECK(text_a.find("settings differ") == std::string::npos);
      CHECK(text_b.find("settings differ") == std::string::npos);
      CHECK(gauge_a == 0.0);
      CHECK(gauge_b == 0.0);
      CHECK(status.out.find("SETTINGS DIFFER") == std::string::npos);
      CHECK(stations[0]["settings_differ"].is_null());
      CHECK(stations[0]["settings_hash"] == stations[1]["settings_hash"]);
    }
  }
}
