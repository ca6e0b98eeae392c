// `magcal export` and `magcal compare`, run as the real binary on simulated days: the uplink
// table applied by an independent script (tests/service/cli/apply_uplink_table.py, the table
// alone) reproduces the fit's calibrated field within the stated rounding; compare's field
// errors agree with the simulator's truth and its advice follows them.
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "pipeline/calibration_table.hpp"
#include "pipeline/field_error.hpp"
#include "service/io/calibration_export.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/sample_files.hpp"
#include "storage/connection.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/test_skip.hpp"

using namespace magcal;
using magcal::test::Run;
using magcal::test::TempDir;

namespace {

nlohmann::json parse(const Run& r) {
  INFO("stdout: " << r.out << "\nstderr: " << r.err);
  REQUIRE(r.exit_code == 0);
  return nlohmann::json::parse(r.out);
}

nlohmann::json read_json(const std::string& path) {
  std::ifstream in(path);
  return nlohmann::json::parse(in);
}

// The first `rows` data rows of a sample CSV, or every other one from `first` (stride 2).
void write_subset(const std::string& from, const std::string& to, int rows, int stride, int first) {
  std::ifstream in(from);
  std::ofstream out(to);
  std::string line;
  std::getline(in, line);
  out << line << "\n";
  for (int k = 0; std::getline(in, line) && k < rows; ++k) {
    if (k % stride == first) out << line << "\n";
  }
}

SampleSet read_samples(const std::string& path) {
  CsvReadResult csv = read_sample_csv(path);
  REQUIRE(csv.ok());
  SampleSet out;
  for (const CsvSampleRow& row : csv.rows) out.push_back(row.sample);
  return out;
}

// The simulator's true calibration (its truth JSON): b, D, R.
CalibrationResult truth_calibration(const nlohmann::json& t) {
  CalibrationResult r;
  for (int i = 0; i < 3; ++i) {
    r.parameters.bias_nT(i) = t["bias_nT"][i].get<double>();
    for (int j = 0; j < 3; ++j) {
      r.parameters.D(i, j) = t["D"][i][j].get<double>();
      r.alignment.R_sensor_from_body(i, j) = t["R_sensor_from_body"][i][j].get<double>();
    }
  }
  r.has_alignment = true;
  return r;
}

}  // namespace

TEST_CASE("export: the float32 table, applied by an independent script, reproduces the fit") {
  if (std::system("python3 -c 'import json, csv' >/dev/null 2>&1") != 0) {
    magcal::test::skip_or_fail("python3 is not available");
    return;
  }
  TempDir dir("magcal_export");
  // Tumbling with a temperature swing and a drift: the table has every term.
  REQUIRE(test::run_magcal("sim --scenario " + std::string(MAGCAL_SOURCE_DIR) +
                               "/deploy/scenarios/tumbling.toml --hours 12 --seed 4 --out " +
                               dir.file("s.csv"),
                           dir)
              .exit_code == 0);
  const Run fit = test::run_magcal("fit --input " + dir.file("s.csv") + " --json", dir);
  const nlohmann::json fit_json = parse(fit);
  REQUIRE(fit_json["verdict"] == "accepted");
  REQUIRE(fit_json.contains("R_sensor_from_body"));
  REQUIRE(fit_json.contains("temperature_coefficient_nT_per_C"));
  REQUIRE(fit_json.contains("bias_rate_nT_per_h"));
  { std::ofstream(dir.file("fit.json")) << fit.out; }

  const Run table = test::run_magcal(
      "export " + dir.file("fit.json") + " --format csv --out " + dir.file("table.csv"), dir);
  INFO(table.err);
  REQUIRE(table.exit_code == 0);
  const std::string script =
      std::string(MAGCAL_SOURCE_DIR) + "/tests/service/cli/apply_uplink_table.py";
  const std::string command = "python3 " + script + " " + dir.file("table.csv") + " " +
                              dir.file("s.csv") + " " + dir.file("fit.json") + " > " +
                              dir.file("applied.json");
  const int status = std::system(command.c_str());
  const nlohmann::json check = read_json(dir.file("applied.json"));
  INFO(check.dump());
  CHECK(status == 0);
  CHECK(check["ok"] == true);
  CHECK(check["n"].get<int>() > 4000);
  CHECK(check["worst_vs_fit_nT"].get<double>() <= check["stated_rounding_nT"].get<double>());
  CHECK(check["stated_rounding_nT"].get<double>() < 0.05);
  // Against the simulator's reference: the noise (3 nT per axis), the attitude knowledge error
  // (0.01 deg: up to 9 nT across the field) and what the table has no term for (the sensor's
  // hysteresis, 1e-4 of its 1e5 nT full scale); a wrong sign, transpose or term would leave
  // hundreds of nT.
  for (int i = 0; i < 3; ++i) CHECK(check["rms_vs_reference_nT"][i].get<double>() < 15.0);

  // The JSON form: versioned, float32 values exactly float32, the epoch and the terms' reference.
  const nlohmann::json j = parse(test::run_magcal("export " + dir.file("fit.json"), dir));
  CHECK(j["format"] == "magcal-calibration-table");
  CHECK(j["format_version"] == 1);
  CHECK(j["epoch_utime"] == fit_json["utime"]);
  for (const auto& row : j["table_float32"]["M"]) {
    for (const auto& v : row)
      CHECK(static_cast<double>(static_cast<float>(v.get<double>())) == v.get<double>());
  }
  CHECK(j["table_float32"]["T0_C"].is_number());
  CHECK(j["table_float32"]["t_ref_utime"] == fit_json["window_end_utime"]);
  CHECK(j["field_direction_error_deg"]["rms"].is_number());
}

TEST_CASE("export: by id and latest from a database, refusals name the fix") {
  TempDir dir("magcal_export_db");
  REQUIRE(
      test::run_magcal("sim --scenario paper --hours 3 --seed 2 --out " + dir.file("s.csv"), dir)
          .exit_code == 0);
  const nlohmann::json fit_json =
      parse(test::run_magcal("fit --input " + dir.file("s.csv") + " --json", dir));
  { std::ofstream(dir.file("fit.json")) << fit_json.dump(); }
  // The fit's result stored as the daemon stores a refit.
  CalibrationOrigin origin;
  std::string error;
  const auto result = calibration_from_json(fit_json, &origin, &error);
  REQUIRE(result);
  {
    auto db = storage::open_database(dir.file("m.db"));
    db->make_calibration_history()->append(record_from_result("PAPER-1", *result));
    // The window's samples, stored as magcald stores them.
    std::vector<storage::StoredSample> stored;
    for (const CalibrationSample& s : read_samples(dir.file("s.csv"))) {
      storage::StoredSample row;
      row.sat_id = "PAPER-1";
      row.utime = s.utime;
      row.seq = static_cast<int64_t>(stored.size());
      Eigen::Map<Eigen::Vector3d>(row.b_sensor_nT.data()) = s.b_sensor_nT;
      Eigen::Map<Eigen::Vector3d>(row.h_body_nT.data()) = s.h_body_nT;
      row.has_direction = true;
      row.h_norm_nT = s.h_body_nT.norm();
      row.temperature_C = s.temperature_C;
      stored.push_back(row);
    }
    db->make_sample_window_store()->insert_batch(stored);
  }
  const nlohmann::json by_id = parse(test::run_magcal("export 1 --db " + dir.file("m.db"), dir));
  const nlohmann::json latest =
      parse(test::run_magcal("export latest --db " + dir.file("m.db") + " --sat PAPER-1", dir));
  CHECK(by_id["calibration_id"] == 1);
  CHECK(by_id["sat_id"] == "PAPER-1");
  CHECK(by_id["table_float32"] == latest["table_float32"]);
  const nlohmann::json from_file = parse(test::run_magcal("export " + dir.file("fit.json"), dir));
  CHECK(by_id["table_float32"] == from_file["table_float32"]);
  // The history keeps the field error of the fit.
  CHECK(by_id["field_direction_error_deg"] == from_file["field_direction_error_deg"]);

  // compare on the stored window (by default B's): the same calibration, from the file and the
  // database, is within the noise, and its field error is the one the fit stored.
  const nlohmann::json c =
      parse(test::run_magcal("compare " + dir.file("fit.json") + " latest --db " +
                                 dir.file("m.db") + " --sat PAPER-1 --json",
                             dir));
  CHECK(c["window"]["n_samples"] == fit_json["n_samples"]);
  CHECK(c["advice"] == "within the noise: keep A");
  CHECK(c["field_error"]["b"]["direction_deg"]["rms"].get<double>() ==
        Approx(fit_json["field_direction_error_deg"]["rms"].get<double>()).epsilon(1e-9));

  Run r = test::run_magcal("export latest --db " + dir.file("m.db"), dir);
  CHECK(r.exit_code == 1);
  CHECK(r.err.find("--sat") != std::string::npos);
  r = test::run_magcal("export 7 --db " + dir.file("m.db"), dir);
  CHECK(r.exit_code == 2);
  CHECK(r.err.find("no calibration with id 7") != std::string::npos);
  r = test::run_magcal("export 3", dir);
  CHECK(r.exit_code == 1);
  CHECK(r.err.find("--db") != std::string::npos);
  r = test::run_magcal("export " + dir.file("s.csv"), dir);
  CHECK(r.exit_code == 2);
}

TEST_CASE("compare: two refits of a day, field errors against the simulator's truth") {
  TempDir dir("magcal_compare");
  REQUIRE(test::run_magcal("sim --scenario paper --hours 12 --seed 5 --out " + dir.file("s.csv") +
                               " --truth " + dir.file("t.json"),
                           dir)
              .exit_code == 0);
  // A: the first orbit only, centered; B: the day, twostep; B1, B2: the day's even and odd
  // samples (two refits with the same geometry and independent noise).
  write_subset(dir.file("s.csv"), dir.file("orbit.csv"), 600, 1, 0);
  write_subset(dir.file("s.csv"), dir.file("even.csv"), 1 << 30, 2, 0);
  write_subset(dir.file("s.csv"), dir.file("odd.csv"), 1 << 30, 2, 1);
  const auto fit = [&](const std::string& input, const std::string& method,
                       const std::string& out) {
    const Run r =
        test::run_magcal("fit --input " + dir.file(input) + " --method " + method + " --json", dir);
    INFO(r.err);
    REQUIRE(r.exit_code == 0);
    std::ofstream(dir.file(out)) << r.out;
  };
  fit("orbit.csv", "centered", "a.json");
  fit("s.csv", "twostep", "b.json");
  fit("even.csv", "twostep", "b1.json");
  fit("odd.csv", "twostep", "b2.json");

  // compare --json of two fits on the day's samples.
  const auto compare_json = [&](const std::string& a, const std::string& b) {
    return parse(test::run_magcal("compare " + dir.file(a) + " " + dir.file(b) + " --samples " +
                                      dir.file("s.csv") + " --json",
                                  dir));
  };
  const nlohmann::json c = compare_json("a.json", "b.json");
  INFO(c.dump(1));
  // The truth: the true calibration's error on the window (noise and what no table removes),
  // and each calibration's distance from it (noise-free); the reported error combines the two.
  const SampleSet samples = read_samples(dir.file("s.csv"));
  const auto truth_field = calibrated_field(
      calibration_table(truth_calibration(read_json(dir.file("t.json")))), samples);
  const FieldError floor = field_error(truth_field, samples);
  for (const char* side : {"a", "b"}) {
    CalibrationOrigin origin;
    std::string error;
    const auto r =
        calibration_from_json(read_json(dir.file(std::string(side) + ".json")), &origin, &error);
    REQUIRE(r);
    const FieldError off =
        field_difference(truth_field, calibrated_field(calibration_table(*r), samples));
    const double expected_deg = std::hypot(floor.direction_deg.rms, off.direction_deg.rms);
    const double reported_deg = c["field_error"][side]["direction_deg"]["rms"].get<double>();
    INFO(side << ": truth floor " << floor.direction_deg.rms << " deg, off truth "
              << off.direction_deg.rms << " deg, reported " << reported_deg);
    CHECK(reported_deg == Approx(expected_deg).epsilon(0.15));
    const double expected_nT = std::hypot(floor.magnitude_nT.rms, off.magnitude_nT.rms);
    CHECK(c["field_error"][side]["magnitude_nT"]["rms"].get<double>() ==
          Approx(expected_nT).epsilon(0.15));
  }
  CHECK(c["difference"]["significant"] == true);
  CHECK(c["upload_b"] == true);
  CHECK(c["advice"].get<std::string>().find("B improves the direction error from") == 0);
  CHECK(c["field_error"]["raw"]["direction_deg"]["rms"].get<double>() >
        10 * c["field_error"]["b"]["direction_deg"]["rms"].get<double>());

  // Reversed, the better one is A: keep it.
  const nlohmann::json reversed = compare_json("b.json", "a.json");
  CHECK(reversed["upload_b"] == false);
  CHECK(reversed["advice"].get<std::string>().find("keep A") != std::string::npos);

  // Two refits of the same day from independent noise: within the noise.
  const Run same = test::run_magcal("compare " + dir.file("b1.json") + " " + dir.file("b2.json") +
                                        " --samples " + dir.file("s.csv"),
                                    dir);
  INFO(same.out << same.err);
  REQUIRE(same.exit_code == 0);
  CHECK(same.out.find("within the noise: keep A") != std::string::npos);
  CHECK(same.out.find("direction A (deg)") != std::string::npos);

  // A calibration without an alignment (a recording with |H| only) against one with: never
  // "within the noise", whatever the chi2 of the 9 parameters both have; B's alignment removes
  // the direction error A leaves.
  {
    std::ifstream in(dir.file("s.csv"));
    std::ofstream out(dir.file("no_attitude.csv"));
    for (std::string line; std::getline(in, line);) {
      std::vector<std::string> cells;
      std::stringstream cells_in(line);
      for (std::string cell; std::getline(cells_in, cell, ',');) cells.push_back(cell);
      REQUIRE(cells.size() == 15);  // t_s, b, h, q, r_ecef, temperature_C
      out << cells[0] << ',' << cells[1] << ',' << cells[2] << ',' << cells[3] << ',' << cells[11]
          << ',' << cells[12] << ',' << cells[13] << ',' << cells[14] << '\n';
    }
  }
  fit("no_attitude.csv", "twostep", "a0.json");
  const nlohmann::json unaligned = compare_json("a0.json", "b.json");
  INFO(unaligned.dump(1));
  CHECK(unaligned["difference"]["same_model"] == false);
  CHECK(unaligned["upload_b"] == true);
  CHECK(unaligned["advice"].get<std::string>().find("B improves the direction error from") == 0);
  CHECK(unaligned["field_error"]["a"]["direction_deg"]["rms"].get<double>() >
        10 * unaligned["field_error"]["b"]["direction_deg"]["rms"].get<double>());

  // Without a window: the fix is named.
  const Run no_window =
      test::run_magcal("compare " + dir.file("a.json") + " " + dir.file("b.json"), dir);
  CHECK(no_window.exit_code == 1);
  CHECK(no_window.err.find("--samples") != std::string::npos);
}
