// `magcal status` through the real binary: per-spacecraft summary (JSON and text), bias change
// between the last two refits, samples in the window, empty and missing databases.
#include <sys/wait.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "pipeline/time_utc.hpp"
#include "storage/calibration_history.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"

namespace fs = std::filesystem;
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/cli_test_support.hpp"

using namespace magcal;
using namespace magcal::storage;
using magcal::test::Run;
using magcal::test::run_magcal;
using magcal::test::TempDir;

namespace {

constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kHour = 3600 * kSecond;
constexpr int64_t kT0 = 1'767'225'600LL * kSecond;  // 2026-01-01T00:00:00Z
constexpr int64_t kWindow = 12 * kHour;             // the daemon's default window_hours

CalibrationRecord make_record(const std::string& sat, const std::string& method, int64_t utime,
                              std::array<double, 3> bias, const std::string& verdict) {
  CalibrationRecord r;
  r.sat_id = sat;
  r.method = method;
  r.utime = utime;
  r.window_start_utime = utime - kWindow + 1;
  r.window_end_utime = utime;
  r.n_samples = 4320;
  r.bias_nT = bias;
  for (int i = 0; i < 9; ++i) r.cov[cov_index(i, i)] = i < 3 ? 2.25 : 1e-8;
  r.residual_rms_nT = 3.0;
  r.verdict = verdict;
  r.status = verdict == "accepted" ? 0 : 4;
  return r;
}

struct Fixture {
  TempDir dir;
  std::string db = dir.file("status.db");
  int64_t newest = 0;
  Fixture() {
    Database d(db);
    SqliteSampleWindowStore samples(d);
    SqliteCalibrationHistory history(d);
    SqliteRefitJobLog jobs(d);
    // SAT1: 20 h of samples every 10 s (so the 12 h window holds 4320 of them).
    std::vector<StoredSample> batch;
    for (int64_t t = kT0; t < kT0 + 20 * kHour; t += 10 * kSecond) {
      StoredSample s;
      s.sat_id = "SAT1";
      s.utime = t;
      s.b_sensor_nT = {1.0, 2.0, 3.0};
      s.h_norm_nT = 4.0;
      batch.push_back(s);
    }
    samples.insert_batch(batch);
    newest = batch.back().utime;
    history.append(make_record("SAT1", "twostep", kT0 + 2 * kHour, {10, 20, 30}, "accepted"));
    history.append(make_record("SAT1", "ukf", kT0 + 3 * kHour, {11, 21, 31}, "accepted"));
    history.append(make_record("SAT1", "twostep", kT0 + 14 * kHour, {12.5, 19, 30}, "accepted"));
    history.append(make_record("SAT1", "ukf", kT0 + 19 * kHour, {13, 22, 33}, "accepted"));
    const int64_t cal =
        history.append(make_record("SAT1", "twostep", kT0 + 18 * kHour, {60, 20, 30}, "rejected"));
    const int64_t job = jobs.start("SAT1", "scheduled", kT0 + 18 * kHour, kT0 + 18 * kHour);
    jobs.finish(job, job_outcome::kRejected, kT0 + 18 * kHour + kSecond, "", cal);
    // SAT2: results only, no samples stored any more.
    history.append(make_record("SAT2", "ukf", kT0, {1, 2, 3}, "accepted"));
  }
};

}  // namespace

TEST_CASE("status --json: per-spacecraft summary with the design.md keys") {
  Fixture f;
  const Run r = run_magcal("status --db " + f.db + " --json", f.dir);
  REQUIRE(r.exit_code == 0);
  const auto j = nlohmann::json::parse(r.out);
  REQUIRE(j["spacecraft"].size() == 2);
  const auto& s1 = j["spacecraft"][0];
  CHECK(s1["sat_id"] == "SAT1");
  CHECK(parse_iso8601_utc(s1["last_sample_time"].get<std::string>()) == f.newest);
  // (newest - 12 h, newest] on a 10 s grid.
  CHECK(s1["samples_in_window"] == kWindow / (10 * kSecond));
  CHECK(s1["last_ukf"]["utime"] == kT0 + 19 * kHour);
  CHECK(s1["last_ukf"]["bias_sigma_nT"][0].get<double>() == 1.5);
  CHECK(s1["last_refit"]["utime"] == kT0 + 18 * kHour);
  CHECK(s1["last_refit"]["verdict"] == "rejected");
  CHECK(s1["last_refit"]["status"] == "rejected");
  CHECK(s1["last_refit_job"]["outcome"] == "rejected");
  // Last refit minus the one before it: (60, 20, 30) - (12.5, 19, 30).
  const auto d = s1["bias_change_since_previous_refit_nT"];
  REQUIRE(d.is_array());
  CHECK(d[0].get<double>() == 60.0 - 12.5);
  CHECK(d[1].get<double>() == 20.0 - 19.0);
  CHECK(d[2].get<double>() == 0.0);

  const auto& s2 = j["spacecraft"][1];
  CHECK(s2["sat_id"] == "SAT2");
  CHECK(s2["last_sample_time"].is_null());
  CHECK(s2["samples_in_window"] == 0);
  CHECK(s2["last_ukf"]["utime"] == kT0);
  CHECK(s2["last_refit"].is_null());
  CHECK(s2["bias_change_since_previous_refit_nT"].is_null());
}

TEST_CASE("status text output names every spacecraft and the bias change") {
  Fixture f;
  const Run r = run_magcal("status --db " + f.db, f.dir);
  REQUIRE(r.exit_code == 0);
  CHECK(r.out.find("SAT1\n") != std::string::npos);
  CHECK(r.out.find("SAT2\n") != std::string::npos);
  CHECK(r.out.find("2160 samples") == std::string::npos);
  CHECK(r.out.find("4320 samples") != std::string::npos);
  CHECK(r.out.find("+47.50") != std::string::npos);
  INFO(r.out);
  // The rejected refit (status and verdict both "rejected") says it once; the UKF both.
  CHECK(r.out.find("rejected, rejected") == std::string::npos);
  CHECK(r.out.find("rms 3.00 nT  rejected\n") != std::string::npos);
  CHECK(r.out.find("rms 3.00 nT  ok, accepted\n") != std::string::npos);
}

TEST_CASE("status labels its times: data time, and the refit job's run as wall clock") {
  Fixture f;
  // A manual refit, run long after the data (its job's times are the wall clock's).
  constexpr int64_t kWall = 1'796'145'912LL * kSecond;  // 2026-12-01T17:25:12Z
  {
    Database d(f.db);
    SqliteRefitJobLog jobs(d);
    jobs.finish(jobs.start("SAT1", "manual", kWall, kWall), job_outcome::kOk, kWall + kSecond);
  }
  Run r = run_magcal("status --db " + f.db, f.dir);
  INFO(r.out);
  REQUIRE(r.exit_code == 0);
  CHECK(r.out.rfind("(times in UTC: data time, the samples' time tags, unless marked wall clock)\n",
                    0) == 0);
  CHECK(r.out.find("last refit job   ok (manual, ran 2026-12-01T17:25:12Z (wall clock))\n") !=
        std::string::npos);
  CHECK(r.out.find("due") == std::string::npos);  // a manual refit is due when it runs

  // A scheduled one: its due time is on the [refit] clock, its run on the wall clock.
  Fixture scheduled;
  r = run_magcal("status --db " + scheduled.db, scheduled.dir);
  INFO(r.out);
  CHECK(r.out.find("last refit job   rejected (scheduled, due " +
                   format_iso8601_utc(kT0 + 18 * kHour) + " ([refit] clock), ran " +
                   format_iso8601_utc(kT0 + 18 * kHour) + " (wall clock))\n") != std::string::npos);
}

TEST_CASE("status on an empty, missing or foreign database") {
  TempDir dir;
  const std::string empty = dir.file("empty.db");
  { Database d(empty); }
  Run r = run_magcal("status --db " + empty + " --json", dir);
  CHECK(r.exit_code == 0);
  CHECK(nlohmann::json::parse(r.out) == nlohmann::json{{"spacecraft", nlohmann::json::array()},
                                                       {"stations", nlohmann::json::array()}});

  const std::string missing = dir.file("missing.db");
  r = run_magcal("status --db " + missing, dir);
  CHECK(r.exit_code == 2);
  CHECK_FALSE(r.err.empty());
  CHECK_FALSE(fs::exists(missing));

  const std::string newer = dir.file("newer.db");
  {
    Database d(newer);
    d.exec("PRAGMA user_version = 999");
  }
  r = run_magcal("status --db " + newer, dir);
  CHECK(r.exit_code == 2);
  CHECK(r.err.find("newer") != std::string::npos);

  // Not a database at all: one line naming the file.
  const std::string text = dir.file("notdb.db");
  {
    std::ofstream out(text);
    for (int i = 0; i < 20; ++i) out << "this is a text file, not an SQLite database\n";
  }
  r = run_magcal("status --db " + text, dir);
  INFO(r.err);
  CHECK(r.exit_code == 2);
  CHECK(r.err ==
        "magcal status: " + text + " is not a database (SQLite: file is not a database)\n");
}

TEST_CASE("status --db on a directory says it is a directory") {
  TempDir dir;
  const std::string folder = dir.file("results");
  fs::create_directories(folder);
  const Run r = run_magcal("status --db " + folder, dir);
  INFO(r.err);
  CHECK(r.exit_code == 2);
  CHECK(r.err == "magcal status: cannot open database " + folder +
                     ": is a directory, not a database file\n");
  CHECK(fs::is_empty(folder));  // nothing created in it
}
