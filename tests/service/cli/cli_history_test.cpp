// `magcal history` through the real binary: formats, filters, --limit newest in either order,
// unknown spacecraft, missing/foreign database, and reading while a writer writes.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>
#include <sstream>

#include "pipeline/rotation.hpp"
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

constexpr int64_t kHour = 3'600'000'000LL;
constexpr int64_t kT0 = 1'767'225'600'000'000LL;  // 2026-01-01T00:00:00Z

CalibrationRecord make_record(const std::string& sat, const std::string& method, int64_t utime,
                              int k) {
  CalibrationRecord r;
  r.sat_id = sat;
  r.method = method;
  r.utime = utime;
  r.window_start_utime = utime - 12 * kHour + 1;
  r.window_end_utime = utime;
  r.n_samples = 4000 + k;
  r.bias_nT = {100.0 + 0.1 * k, -50.0 - k / 3.0, 25.0};
  r.D = {1e-3 * k, -2e-3, 3e-3, 1e-4, -1e-4, 2e-4};
  for (int i = 0; i < 9; ++i) r.cov[cov_index(i, i)] = i < 3 ? 4.0 * (i + 1) + k : 1e-8;
  r.cov[cov_index(0, 1)] = 0.5;
  r.has_alignment = method == "twostep" && k % 2 == 0;
  r.R_sensor_from_body = {0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0};
  r.residual_rms_nT = 3.0 + 0.01 * k;
  if (method == "twostep" && k % 2 == 1) {
    r.status = 4;
    r.verdict = "rejected";
    r.rejection_reasons = {"bias jump 80 nT > 50 nT", "comma, \"quoted\""};
  }
  r.iterations = 6;
  r.created_utime = utime + 60'000'000;
  return r;
}

// SAT1: 10 hourly ukf snapshots and twostep refits at 2 h (accepted, aligned), 5 h (rejected)
// and 8 h (accepted, aligned); SAT2: one ukf snapshot.
void populate(const std::string& path) {
  Database db(path);
  SqliteCalibrationHistory history(db);
  for (int k = 0; k < 10; ++k) history.append(make_record("SAT1", "ukf", kT0 + k * kHour, k));
  for (int k : {2, 5, 8}) history.append(make_record("SAT1", "twostep", kT0 + k * kHour + 1, k));
  history.append(make_record("SAT2", "ukf", kT0, 0));
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::stringstream ss(text);
  for (std::string line; std::getline(ss, line);) out.push_back(line);
  return out;
}

std::vector<std::string> split_csv(const std::string& line) {
  std::vector<std::string> out(1);
  bool quoted = false;
  for (size_t i = 0; i < line.size(); ++i) {
    const char c = line[i];
    if (quoted) {
      if (c == '"' && i + 1 < line.size() && line[i + 1] == '"') {
        out.back() += '"';
        ++i;
      } else if (c == '"') {
        quoted = false;
      } else {
        out.back() += c;
      }
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      out.emplace_back();
    } else {
      out.back() += c;
    }
  }
  return out;
}

// Index of the CSV column `name` in `header` (which must have it).
size_t column_of(const std::vector<std::string>& header, const std::string& name) {
  const auto it = std::find(header.begin(), header.end(), name);
  REQUIRE(it != header.end());
  return static_cast<size_t>(it - header.begin());
}

}  // namespace

TEST_CASE("history --format json matches the stored rows and design.md keys") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  const Run r = run_magcal("history --db " + db + " --sat SAT1 --format json", dir);
  REQUIRE(r.exit_code == 0);
  const auto j = nlohmann::json::parse(r.out);
  REQUIRE(j.is_array());
  REQUIRE(j.size() == 13);

  Database check(db);
  SqliteCalibrationHistory history(check);
  HistoryQuery q;
  q.sat_id = "SAT1";
  const auto rows = history.query(q);
  REQUIRE(rows.size() == j.size());
  for (size_t k = 0; k < rows.size(); ++k) {
    const auto& o = j[k];
    const auto& row = rows[k];
    INFO("row " << k);
    for (const char* key : {"time", "utime", "method", "bias_nT", "D", "bias_sigma_nT", "n_samples",
                            "window_start", "window_end", "window_start_utime", "window_end_utime",
                            "residual_rms_nT", "status", "verdict", "rejection_reasons"}) {
      CHECK(o.contains(key));
    }
    CHECK(o["utime"] == row.utime);
    CHECK(parse_iso8601_utc(o["time"].get<std::string>()) == row.utime);
    CHECK(parse_iso8601_utc(o["window_start"].get<std::string>()) == row.window_start_utime);
    CHECK(parse_iso8601_utc(o["window_end"].get<std::string>()) == row.window_end_utime);
    CHECK(o["method"] == row.method);
    CHECK(o["n_samples"] == row.n_samples);
    for (int i = 0; i < 3; ++i) {
      CHECK(o["bias_nT"][i].get<double>() == row.bias_nT[i]);
      CHECK(o["bias_sigma_nT"][i].get<double>() == std::sqrt(row.cov[cov_index(i, i)]));
    }
    // D is symmetric with D12 = D21 etc. (D11 D22 D33 D12 D13 D23 in the row).
    CHECK(o["D"][0][0].get<double>() == row.D[0]);
    CHECK(o["D"][2][2].get<double>() == row.D[2]);
    CHECK(o["D"][0][1].get<double>() == row.D[3]);
    CHECK(o["D"][1][0].get<double>() == row.D[3]);
    CHECK(o["D"][1][2].get<double>() == row.D[5]);
    CHECK(o["status"] == status_name(row.status));
    CHECK(o["verdict"] == row.verdict);
    CHECK(o["rejection_reasons"].get<std::vector<std::string>>() == row.rejection_reasons);
    CHECK(o.contains("R_sensor_from_body") == row.has_alignment);
    if (row.has_alignment) CHECK(o["R_sensor_from_body"][1][0].get<double>() == -1.0);
  }
  // Oldest first by default.
  CHECK(j.front()["utime"] == kT0);
  CHECK(j.back()["utime"] == kT0 + 9 * kHour);
}

TEST_CASE("history filters: method, inclusive since/until, limit newest in asc and desc") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  const std::string base = "history --db " + db + " --sat SAT1 --format json ";
  auto utimes = [&](const std::string& extra) {
    const Run r = run_magcal(base + extra, dir);
    REQUIRE(r.exit_code == 0);
    std::vector<int64_t> out;
    for (const auto& o : nlohmann::json::parse(r.out)) out.push_back(o["utime"].get<int64_t>());
    return out;
  };
  CHECK(utimes("--method twostep") ==
        std::vector<int64_t>{kT0 + 2 * kHour + 1, kT0 + 5 * kHour + 1, kT0 + 8 * kHour + 1});
  CHECK(utimes("--method ukf --since 2026-01-01T03:00:00Z --until 2026-01-01T05:00:00Z") ==
        std::vector<int64_t>{kT0 + 3 * kHour, kT0 + 4 * kHour, kT0 + 5 * kHour});
  CHECK(utimes("--method ukf --limit 3") ==
        std::vector<int64_t>{kT0 + 7 * kHour, kT0 + 8 * kHour, kT0 + 9 * kHour});
  CHECK(utimes("--method ukf --limit 3 --order desc") ==
        std::vector<int64_t>{kT0 + 9 * kHour, kT0 + 8 * kHour, kT0 + 7 * kHour});
  CHECK(utimes("--limit 2 --since 2026-01-01T08:00:00Z --until 2026-01-01T08:30:00Z") ==
        std::vector<int64_t>{kT0 + 8 * kHour, kT0 + 8 * kHour + 1});
  // A known spacecraft with nothing in range: an empty array, exit 0.
  CHECK(utimes("--since 2027-01-01").empty());
}

TEST_CASE("history --format csv has design.md's flat columns and exact values") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  const Run r = run_magcal("history --db " + db + " --sat SAT1 --method twostep --format csv", dir);
  REQUIRE(r.exit_code == 0);
  const auto lines = lines_of(r.out);
  REQUIRE(lines.size() == 4);
  const auto header = split_csv(lines[0]);
  auto col = [&](const std::string& name) { return column_of(header, name); };
  for (const char* name : {"time",
                           "utime",
                           "method",
                           "bias_x_nT",
                           "bias_y_nT",
                           "bias_z_nT",
                           "bias_sigma_x_nT",
                           "bias_sigma_y_nT",
                           "bias_sigma_z_nT",
                           "D11",
                           "D22",
                           "D33",
                           "D12",
                           "D13",
                           "D23",
                           "R11",
                           "R33",
                           "n_samples",
                           "window_start",
                           "window_end",
                           "residual_rms_nT",
                           "status",
                           "verdict",
                           "rejection_reasons"}) {
    col(name);
  }
  for (size_t k = 1; k < lines.size(); ++k) {
    const auto f = split_csv(lines[k]);
    REQUIRE(f.size() == header.size());
    const int kk = k == 1 ? 2 : (k == 2 ? 5 : 8);
    const CalibrationRecord want = make_record("SAT1", "twostep", kT0 + kk * kHour + 1, kk);
    CHECK(std::stod(f[col("bias_y_nT")]) == want.bias_nT[1]);  // shortest round-trip text
    CHECK(std::stod(f[col("bias_sigma_x_nT")]) == std::sqrt(want.cov[0]));
    CHECK(std::stod(f[col("D12")]) == want.D[3]);
    CHECK(std::stoll(f[col("utime")]) == want.utime);
    CHECK(f[col("status")] == status_name(want.status));
    CHECK(f[col("R11")].empty() == !want.has_alignment);
    if (want.status == 4) {
      CHECK(f[col("rejection_reasons")] == "bias jump 80 nT > 50 nT; comma, \"quoted\"");
    }
  }
}

TEST_CASE("history table output is aligned") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  const Run r = run_magcal("history --db " + db + " --sat SAT1", dir);
  REQUIRE(r.exit_code == 0);
  const auto lines = lines_of(r.out);
  REQUIRE(lines.size() == 14);  // header + 13 rows
  // Every row starts with the time and has the method and status in the header's columns.
  const size_t method_col = lines[0].find("method");
  const size_t status_col = lines[0].find("status");
  REQUIRE(method_col != std::string::npos);
  for (size_t k = 1; k < lines.size(); ++k) {
    INFO(lines[k]);
    CHECK(parse_iso8601_utc(lines[k].substr(0, 20)).has_value());
    CHECK((lines[k].compare(method_col, 3, "ukf") == 0 ||
           lines[k].compare(method_col, 7, "twostep") == 0));
    CHECK((lines[k].compare(status_col, 2, "ok") == 0 ||
           lines[k].compare(status_col, 8, "rejected") == 0));
  }
}

TEST_CASE("history: unknown spacecraft, missing or foreign database, bad arguments") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  Run r = run_magcal("history --db " + db + " --sat NOPE --format json", dir);
  CHECK(r.exit_code == 2);
  CHECK(r.out.empty());
  CHECK(r.err.find("NOPE") != std::string::npos);

  const std::string missing = dir.file("missing.db");
  r = run_magcal("history --db " + missing + " --sat SAT1", dir);
  CHECK(r.exit_code == 2);
  CHECK(r.out.empty());
  CHECK_FALSE(r.err.empty());
  CHECK_FALSE(fs::exists(missing));

  const std::string foreign = dir.file("foreign.txt");
  { std::ofstream(foreign) << std::string(4096, 'x'); }
  r = run_magcal("history --db " + foreign + " --sat SAT1", dir);
  CHECK(r.exit_code == 2);

  r = run_magcal("history --db " + db + " --sat SAT1 --since yesterday", dir);
  CHECK(r.exit_code == 1);
  r = run_magcal("history --db " + db + " --sat SAT1 --method magic", dir);
  CHECK(r.exit_code == 1);
  r = run_magcal("history --db " + db + " --sat SAT1 --order sideways", dir);
  CHECK(r.exit_code == 1);
}

TEST_CASE("history and status read while a writer is writing") {
  TempDir dir;
  const std::string db = dir.file("live.db");
  populate(db);
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  const pid_t child = ::fork();
  REQUIRE(child >= 0);
  if (child == 0) {
    // Writer: batches of samples and a history row per batch, as the daemon does.
    ::close(fds[0]);
    try {
      Database wdb(db);
      SqliteSampleWindowStore samples(wdb);
      SqliteCalibrationHistory history(wdb);
      std::vector<StoredSample> batch(200);
      for (int64_t n = 0;; ++n) {
        {
          Transaction tx(wdb);
          for (int i = 0; i < 200; ++i) {
            StoredSample& s = batch[i];
            s.sat_id = "SAT1";
            s.utime = kT0 + (n * 200 + i) * 1'000'000;
            s.b_sensor_nT = {1.0, 2.0, 3.0};
            s.h_norm_nT = 4.0;
          }
          samples.insert_batch(batch);
          history.append(make_record("SAT1", "ukf", kT0 + 10 * kHour + n, 1));
          tx.commit();
        }
        if (n == 5 && ::write(fds[1], &n, sizeof n) != sizeof n) ::_exit(3);
      }
    } catch (...) {
      ::_exit(2);
    }
  }
  ::close(fds[1]);
  int64_t n = 0;
  REQUIRE(::read(fds[0], &n, sizeof n) == sizeof n);  // the writer is running
  size_t previous = 0;
  for (int k = 0; k < 5; ++k) {
    const Run h = run_magcal("history --db " + db + " --sat SAT1 --method ukf --format json", dir);
    REQUIRE(h.exit_code == 0);
    const auto rows = nlohmann::json::parse(h.out);
    CHECK(rows.size() >= previous);
    CHECK(rows.size() > 10);
    previous = rows.size();
    const Run s = run_magcal("status --db " + db + " --json", dir);
    REQUIRE(s.exit_code == 0);
    const auto st = nlohmann::json::parse(s.out);
    CHECK(st["spacecraft"][0]["samples_in_window"].get<int64_t>() % 200 == 0);  // whole batches
  }
  int status = 0;
  CHECK(::waitpid(child, &status, WNOHANG) == 0);  // the writer never failed meanwhile
  ::kill(child, SIGKILL);
  ::waitpid(child, &status, 0);
  ::close(fds[0]);
  Database after(db);
  CHECK(after.integrity_check() == "ok");
}

TEST_CASE("history flags roll/yaw near gimbal lock in JSON and CSV (canonical split, roll 0)") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  populate(db);
  CalibrationRecord side = make_record("SIDE", "twostep", kT0 + 2 * kHour + 1, 2);
  const Eigen::Matrix3d R =
      magcal::dcm_from_roll_pitch_yaw({0.3, 0.5 * std::numbers::pi, -0.2});  // pitch 90 deg
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) side.R_sensor_from_body[static_cast<size_t>(3 * i + j)] = R(i, j);
  {
    Database d(db);
    SqliteCalibrationHistory(d).append(side);
  }
  const Run js = run_magcal("history --db " + db + " --sat SIDE --format json", dir);
  REQUIRE(js.exit_code == 0);
  const auto row = nlohmann::json::parse(js.out).at(0);
  CHECK(row["alignment_singular"] == true);
  CHECK(row["alignment_deg"]["roll"].get<double>() == 0.0);
  const double combination_deg = (-0.2 - 0.3) * 180.0 / std::numbers::pi;
  CHECK(row["alignment_deg"]["yaw"].get<double>() == Approx(combination_deg));
  CHECK(row["alignment_determined_deg"]["yaw_minus_roll"].get<double>() == Approx(combination_deg));
  // At the pole itself the roll-0 angles are the rotation.
  CHECK(row["alignment_canonical_error_deg"].get<double>() == Approx(0.0).margin(1e-9));
  // Stored without a covariance (as rows before it was kept): no sigma is printed.
  CHECK_FALSE(row.contains("alignment_determined_sigma_deg"));
  CHECK_FALSE(row.contains("alignment_sigma_deg"));
  CHECK_FALSE(row.contains("alignment_covariance_deg2"));

  const Run ok =
      run_magcal("history --db " + db + " --sat SAT1 --method twostep --format json", dir);
  for (const auto& o : nlohmann::json::parse(ok.out)) {
    CHECK(o.contains("alignment_singular") == o.contains("R_sensor_from_body"));
    if (o.contains("alignment_singular")) CHECK(o["alignment_singular"] == false);
  }

  for (const auto& [sat, want] : {std::pair{"SIDE", "1"}, std::pair{"SAT2", ""}}) {
    const Run csv =
        run_magcal(std::string("history --db ") + db + " --sat " + sat + " --format csv", dir);
    REQUIRE(csv.exit_code == 0);
    const auto lines = lines_of(csv.out);
    REQUIRE(lines.size() == 2);
    const auto header = split_csv(lines[0]);
    const auto f = split_csv(lines[1]);
    REQUIRE(f.size() == header.size());
    CHECK(f[column_of(header, "alignment_singular")] == want);
    const std::string name = f[column_of(header, "alignment_determined_name")];
    const std::string value = f[column_of(header, "alignment_determined_deg")];
    if (std::string(want) == "1") {
      CHECK(name == "yaw_minus_roll");
      CHECK(std::stod(value) == row["alignment_determined_deg"]["yaw_minus_roll"].get<double>());
    } else {
      CHECK(name.empty());
      CHECK(value.empty());
    }
  }
}

TEST_CASE("history JSON and CSV: quaternion, rotation-vector covariance and angle sigmas") {
  TempDir dir;
  const std::string db = dir.file("m.db");
  // R = Rz(90 deg) (a frame rotation, section 0): the active rotation by -90 deg about z, so
  // q = (cos 45, 0, 0, -sin 45); roll, pitch 0 and yaw 90 deg, where each angle's sigma is the
  // square root of the matching diagonal entry of the rotation-vector covariance.
  CalibrationRecord aligned = make_record("SAT1", "twostep", kT0, 0);
  REQUIRE(aligned.has_alignment);
  const std::array<double, 6> c_rad2 = {4e-8, 9e-8,  2.5e-7,
                                        1e-8, -2e-8, 3e-9};  // 11 22 33 12 13 23
  aligned.alignment_covariance_rad2 = c_rad2;
  CalibrationRecord old = make_record("SAT1", "twostep", kT0 + kHour, 2);  // unknown covariance
  CalibrationRecord ukf = make_record("SAT1", "ukf", kT0 + 2 * kHour, 1);  // no alignment
  {
    Database d(db);
    SqliteCalibrationHistory history(d);
    history.append(aligned);
    history.append(old);
    history.append(ukf);
  }
  const double deg2 = std::pow(180.0 / std::numbers::pi, 2);
  const Eigen::Matrix3d C_deg2 = (Eigen::Matrix3d() << c_rad2[0], c_rad2[3], c_rad2[4], c_rad2[3],
                                  c_rad2[1], c_rad2[5], c_rad2[4], c_rad2[5], c_rad2[2])
                                     .finished() *
                                 deg2;
  const double h = std::sqrt(0.5);
  const std::array<double, 4> q_want = {h, 0.0, 0.0, -h};
  const std::array<const char*, 3> angles = {"roll", "pitch", "yaw"};

  const Run js = run_magcal("history --db " + db + " --sat SAT1 --format json", dir);
  REQUIRE(js.exit_code == 0);
  const auto j = nlohmann::json::parse(js.out);
  REQUIRE(j.size() == 3);
  const auto& a = j[0];
  for (int i = 0; i < 4; ++i)
    CHECK(a["q_sensor_from_body"][i].get<double>() == Approx(q_want[i]).margin(1e-15));
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      CHECK(a["alignment_covariance_deg2"][r][c].get<double>() == Approx(C_deg2(r, c)));
  for (int i = 0; i < 3; ++i)
    CHECK(a["alignment_sigma_deg"][angles[i]].get<double>() == Approx(std::sqrt(C_deg2(i, i))));
  CHECK(a["alignment_singular"] == false);
  // A row without a stored covariance: the rotation, never sigmas made up from defaults.
  const auto& o = j[1];
  CHECK(o.contains("q_sensor_from_body"));
  CHECK(o.contains("alignment_deg"));
  CHECK_FALSE(o.contains("alignment_covariance_deg2"));
  CHECK_FALSE(o.contains("alignment_sigma_deg"));
  // No alignment: none of the keys.
  for (const char* key : {"q_sensor_from_body", "alignment_covariance_deg2", "alignment_sigma_deg",
                          "alignment_singular", "alignment_deg"})
    CHECK_FALSE(j[2].contains(key));

  const Run csv = run_magcal("history --db " + db + " --sat SAT1 --format csv", dir);
  REQUIRE(csv.exit_code == 0);
  const auto lines = lines_of(csv.out);
  REQUIRE(lines.size() == 4);
  const auto header = split_csv(lines[0]);
  auto col = [&](const std::string& name) { return column_of(header, name); };
  std::vector<std::vector<std::string>> rows;
  for (size_t k = 1; k < lines.size(); ++k) {
    rows.push_back(split_csv(lines[k]));
    REQUIRE(rows.back().size() == header.size());
  }
  const char* wxyz = "wxyz";
  for (int i = 0; i < 4; ++i) {
    const size_t c = col(std::string("q_sensor_from_body_") + wxyz[i]);
    CHECK(std::stod(rows[0][c]) == Approx(q_want[i]).margin(1e-15));
    CHECK(std::stod(rows[0][c]) == a["q_sensor_from_body"][i].get<double>());
    CHECK_FALSE(rows[1][c].empty());
    CHECK(rows[2][c].empty());
  }
  const std::array<const char*, 6> pairs = {"11", "22", "33", "12", "13", "23"};
  for (int i = 0; i < 6; ++i) {
    const size_t c = col(std::string("alignment_covariance_") + pairs[i] + "_deg2");
    CHECK(std::stod(rows[0][c]) == Approx(c_rad2[i] * deg2));
    // The same number as the JSON's, to the last bit.
    const int r = i < 3 ? i : (i == 5 ? 1 : 0), cc = i < 3 ? i : (i == 3 ? 1 : 2);
    CHECK(std::stod(rows[0][c]) == a["alignment_covariance_deg2"][r][cc].get<double>());
    CHECK(rows[1][c].empty());
    CHECK(rows[2][c].empty());
  }
  for (int i = 0; i < 3; ++i) {
    const size_t c = col(std::string("alignment_sigma_") + angles[i] + "_deg");
    CHECK(std::stod(rows[0][c]) == Approx(std::sqrt(C_deg2(i, i))));
    CHECK(std::stod(rows[0][c]) == a["alignment_sigma_deg"][angles[i]].get<double>());
    CHECK(rows[1][c].empty());
    CHECK(rows[2][c].empty());
    CHECK(std::stod(rows[0][col(std::string("alignment_") + angles[i] + "_deg")]) ==
          Approx(i == 2 ? 90.0 : 0.0).margin(1e-12));
  }
  CHECK(rows[0][col("alignment_determined_sigma_deg")].empty());  // not singular
}
