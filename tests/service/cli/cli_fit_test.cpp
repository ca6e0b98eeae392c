// `magcal fit`, run as the real binary (popen): design.md JSON keys, recovery of known
// parameters from CSV and LCM (reference in the sample, or IGRF from position), --sat handling,
// ekf/ukf with --trace, and one-line errors with the documented exit codes.
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <lcm/lcm-cpp.hpp>
#include <nlohmann/json.hpp>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "pipeline/frames.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/sample_files.hpp"

using namespace magcal;

namespace {

constexpr double kBiasTolNt = 2.0;  // 600 tumbling samples at 3 nT: bias sigma ~0.3 nT

struct Run {
  int exit_code = -1;
  std::string out, err;
};

std::filesystem::path temp_path(const std::string& name) {
  return std::filesystem::temp_directory_path() /
         ("magcal_cli_fit_test_" + std::to_string(::getpid()) + "_" + name);
}

Run run_magcal(const std::string& args) {
  const std::string err_path = temp_path("stderr").string();
  const std::string cmd = std::string(MAGCAL_BIN_DIR) + "/magcal " + args + " 2>" + err_path;
  Run r;
  FILE* p = ::popen(cmd.c_str(), "r");
  REQUIRE(p != nullptr);
  std::array<char, 4096> buf;
  size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int status = ::pclose(p);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream e(err_path);
  r.err.assign(std::istreambuf_iterator<char>(e), std::istreambuf_iterator<char>());
  std::filesystem::remove(err_path);
  return r;
}

void require_one_line_error(const Run& r, int exit_code, const std::string& contains) {
  INFO("stdout: " << r.out << "\nstderr: " << r.err);
  CHECK(r.exit_code == exit_code);
  CHECK(r.out.empty());
  CHECK(std::count(r.err.begin(), r.err.end(), '\n') == 1);
  CHECK(r.err.find(contains) != std::string::npos);
}

const Eigen::Vector3d kBias(1000, 800, 900);
Eigen::Matrix3d truth_D() {
  Eigen::Matrix3d D;
  D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  return D;
}
const Eigen::Matrix3d& truth_R() {
  static const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({0.017, 0.035, 0.017});
  return R;
}

// Estimation-model samples, random field directions.
SampleSet model_data(int n, double sigma, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> mag(20000.0, 50000.0);
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + truth_D()).inverse();
  SampleSet s(n);
  for (int k = 0; k < n; ++k) {
    s[k].utime = 1'700'000'000'000'000LL + k * 10'000'000LL;
    s[k].h_body_nT = Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized() * mag(rng);
    s[k].b_sensor_nT = inv * (truth_R() * s[k].h_body_nT + kBias +
                              sigma * Eigen::Vector3d(g(rng), g(rng), g(rng)));
  }
  return s;
}

mag_sample_t to_msg(const CalibrationSample& s, const std::string& sat, int64_t seq) {
  mag_sample_t m{};
  m.utime = s.utime;
  m.sat_id = sat;
  m.seq = seq;
  for (int i = 0; i < 3; ++i) {
    m.b_sensor_nT[i] = s.b_sensor_nT(i);
    m.h_body_nT[i] = s.h_body_nT(i);
  }
  m.has_reference = true;
  m.q_body_from_eci[0] = 1.0;
  return m;
}

std::vector<std::string> read_lines(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

void write_lines(const std::filesystem::path& path, const std::vector<std::string>& lines) {
  std::ofstream out(path);
  for (const std::string& line : lines) out << line << "\n";
}

// `line` with its comma-separated field `column` (0-based) replaced by `value`.
std::string with_field(const std::string& line, int column, const std::string& value) {
  size_t start = 0;
  for (int c = 0; c < column; ++c) start = line.find(',', start) + 1;
  const size_t end = line.find(',', start);
  return line.substr(0, start) + value + (end == std::string::npos ? "" : line.substr(end));
}

void check_bias(const nlohmann::json& j) {
  for (int i = 0; i < 3; ++i)
    CHECK(std::abs(j["bias_nT"][i].get<double>() - kBias(i)) < kBiasTolNt);
}

}  // namespace

TEST_CASE("fit --json on a CSV prints design.md's keys and recovers the parameters", "[cli][fit]") {
  const auto csv = temp_path("model.csv");
  REQUIRE(write_sample_csv(csv.string(), model_data(600, 3.0, 1)).empty());
  for (const char* method : {"twostep", "centered"}) {
    const Run r =
        run_magcal(std::string("fit --input ") + csv.string() + " --method " + method + " --json");
    INFO(r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    for (const char* key :
         {"method", "n_samples", "bias_nT", "D", "bias_sigma_nT", "R_sensor_from_body",
          "alignment_deg", "residual_rms_nT", "iterations", "converged", "compute_ms", "status",
          "verdict", "rejection_reasons", "q_sensor_from_body", "alignment_covariance_deg2",
          "alignment_sigma_deg", "alignment_singular"}) {
      CHECK(j.contains(key));
    }
    // The quaternion is R's (estimation.md section 0: v_sensor = q v_body q*, w >= 0), and the
    // angle sigmas at these small angles are ~sqrt(diag) of the rotation covariance.
    QuaternionWxyz q;
    Eigen::Matrix3d R, C;
    for (int i = 0; i < 4; ++i) q(i) = j["q_sensor_from_body"][i].get<double>();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        R(r, c) = j["R_sensor_from_body"][r][c].get<double>();
        C(r, c) = j["alignment_covariance_deg2"][r][c].get<double>();
      }
    }
    CHECK(q(0) >= 0.0);
    CHECK((dcm_from_quaternion(q) - R).norm() < 1e-12);
    CHECK((C - C.transpose()).norm() == 0.0);
    CHECK(C.diagonal().minCoeff() > 0.0);
    for (int i = 0; i < 3; ++i) {
      const char* angle = i == 0 ? "roll" : (i == 1 ? "pitch" : "yaw");
      CHECK(j["alignment_sigma_deg"][angle].get<double>() ==
            Approx(std::sqrt(C(i, i))).epsilon(0.05));
    }
    CHECK(j["method"] == method);
    CHECK(j["n_samples"] == 600);
    CHECK(j["status"] == "ok");
    check_bias(j);
    CHECK(std::abs(j["D"][1][1].get<double>() - 0.02) < 1e-3);
    CHECK(std::abs(j["alignment_deg"]["pitch"].get<double>() - 0.035 * 180 / M_PI) < 0.01);
    CHECK(j["residual_rms_nT"].get<double>() < 4.0);
  }
  // Human-readable output.
  const Run t = run_magcal("fit --input " + csv.string() + " --method twostep");
  CHECK(t.exit_code == 0);
  CHECK(t.out.find("bias_nT") != std::string::npos);
  CHECK(t.out.find("alignment_deg") != std::string::npos);
  CHECK(t.out.find("q_sensor_from_body") != std::string::npos);
  CHECK(t.out.find("alignment_sigma") != std::string::npos);
  CHECK(t.out.find("alignment_cov_deg2") != std::string::npos);
  std::filesystem::remove(csv);
}

TEST_CASE("fit on thermal data (CSV temperature_C, LCM temperature_C): the temperature keys",
          "[cli][fit]") {
  // magcal sim of the paper scenario with +-15 degC orbit-synchronous and 1 nT/degC-sized
  // coefficients; truth from its --truth file.
  const auto toml = temp_path("thermal.toml");
  const auto truth = temp_path("thermal_truth.json");
  {
    std::ofstream f(toml);
    f << "base = \"paper\"\nduration_h = 12\nseed = 7\n[sensor]\n"
         "temperature_coefficient_nT_per_C = [1.0, -0.8, 1.2]\nreference_temperature_C = 20\n"
         "[temperature]\nmean_C = 20\namplitude_C = 15\nperiod_s = 0\n";
  }
  for (const char* ext : {"csv", "lcm"}) {
    const auto data = temp_path(std::string("thermal.") + ext);
    REQUIRE(run_magcal("sim --scenario " + toml.string() + " --out " + data.string() + " --truth " +
                       truth.string())
                .exit_code == 0);
    std::ifstream tf(truth);
    const nlohmann::json t = nlohmann::json::parse(tf);
    const Run r = run_magcal("fit --input " + data.string() + " --method twostep --json");
    INFO(ext << ": " << r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    REQUIRE(j.contains("temperature_coefficient_nT_per_C"));
    REQUIRE(j.contains("temperature_coefficient_sigma_nT_per_C"));
    REQUIRE(j.contains("reference_temperature_C"));
    CHECK(j["verdict"] == "accepted");
    const double T0 = j["reference_temperature_C"].get<double>();
    for (int i = 0; i < 3; ++i) {
      const double k = t["temperature_coefficient_nT_per_C"][i].get<double>();
      const double b_T0 =
          t["bias_nT"][i].get<double>() + k * (T0 - t["reference_temperature_C"].get<double>());
      CHECK(std::abs(j["bias_nT"][i].get<double>() - b_T0) <=
            3.0 * j["bias_sigma_nT"][i].get<double>());
      CHECK(std::abs(j["temperature_coefficient_nT_per_C"][i].get<double>() - k) <=
            3.0 * j["temperature_coefficient_sigma_nT_per_C"][i].get<double>());
    }
    std::filesystem::remove(data);
  }
  // Without temperatures (model_data writes none): no temperature keys.
  const auto csv = temp_path("no_temperature.csv");
  REQUIRE(write_sample_csv(csv.string(), model_data(600, 3.0, 1)).empty());
  const Run r = run_magcal("fit --input " + csv.string() + " --method twostep --json");
  REQUIRE(r.exit_code == 0);
  CHECK_FALSE(nlohmann::json::parse(r.out).contains("temperature_coefficient_nT_per_C"));
  std::filesystem::remove(csv);
  std::filesystem::remove(toml);
  std::filesystem::remove(truth);
}

// `magcal sim` of 12 h of `base` with an orbit-synchronous temperature of +-amplitude_C about
// 20 degC and the bias temperature coefficients k_nT_per_C ("kx, ky, kz"), as a CSV.
std::filesystem::path simulate_thermal_csv(const std::string& name, const char* base, int seed,
                                           const char* k_nT_per_C, double amplitude_C) {
  const auto toml = temp_path(name + ".toml");
  {
    std::ofstream f(toml);
    f << "base = \"" << base << "\"\nduration_h = 12\nseed = " << seed << "\n[sensor]\n"
      << "temperature_coefficient_nT_per_C = [" << k_nT_per_C << "]\nreference_temperature_C = 20\n"
      << "[temperature]\nmean_C = 20\namplitude_C = " << amplitude_C << "\nperiod_s = 0\n";
  }
  const auto csv = temp_path(name + "_full.csv");
  REQUIRE(run_magcal("sim --scenario " + toml.string() + " --out " + csv.string()).exit_code == 0);
  std::filesystem::remove(toml);
  return csv;
}

// Copies a sample CSV with the temperature_C field of the rows where blank(row) is true emptied
// (unknown).
template <class Blank>
void blank_temperatures(const std::filesystem::path& from, const std::filesystem::path& to,
                        Blank blank) {
  std::ifstream in(from);
  std::ofstream out(to);
  std::string line;
  REQUIRE(std::getline(in, line));
  const size_t column = static_cast<size_t>(std::count(
      line.begin(), line.begin() + static_cast<std::ptrdiff_t>(line.find("temperature_C")), ','));
  out << line << "\n";
  for (int row = 0; std::getline(in, line); ++row) {
    if (blank(row)) {
      size_t start = 0;
      for (size_t c = 0; c < column; ++c) start = line.find(',', start) + 1;
      const size_t end = line.find(',', start);
      line.erase(start, end == std::string::npos ? std::string::npos : end - start);
    }
    out << line << "\n";
  }
}

TEST_CASE("fit: temperatures too sparse for the model are named on stderr", "[cli][fit]") {
  // The thermal data above with the temperature of 3 rows in 5 blanked: the model is not tried
  // (at least half the samples must carry one), and a thermal bias stays in the fit, so say so.
  const auto full = simulate_thermal_csv("sparse", "paper", 7, "1.0, -0.8, 1.2", 15.0);
  const auto sparse = temp_path("sparse.csv");
  blank_temperatures(full, sparse, [](int row) { return row % 5 < 3; });
  const Run r = run_magcal("fit --input " + sparse.string() + " --method twostep --json");
  INFO(r.err);
  REQUIRE(r.exit_code == 0);
  CHECK_FALSE(nlohmann::json::parse(r.out).contains("temperature_coefficient_nT_per_C"));
  CHECK(r.err.find("1728 of 4320 samples carry a temperature") != std::string::npos);
  CHECK(r.err.find("stays unmodelled") != std::string::npos);
  // The complete file takes the model and says nothing of the kind.
  const Run whole = run_magcal("fit --input " + full.string() + " --method twostep --json");
  REQUIRE(whole.exit_code == 0);
  CHECK(whole.err.find("unmodelled") == std::string::npos);
  for (const auto& f : {full, sparse}) std::filesystem::remove(f);
}

TEST_CASE("fit without any temperature: the orbit swing it estimated is reported", "[cli][fit]") {
  // A tumbling spacecraft whose bias swings +-10 nT with the orbit (1 nT/degC, +-10 degC), its
  // temperature blanked in every row: the refit estimates the swing and says so.
  const auto full = simulate_thermal_csv("swing", "tumbling", 2, "1.0, 1.0, 1.0", 10.0);
  const auto blind = temp_path("swing_blind.csv");
  blank_temperatures(full, blind, [](int) { return true; });
  const Run r = run_magcal("fit --input " + blind.string() + " --method twostep --json");
  INFO(r.err);
  REQUIRE(r.exit_code == 0);
  const nlohmann::json j = nlohmann::json::parse(r.out);
  REQUIRE(j.contains("orbit_swing"));
  const nlohmann::json& w = j["orbit_swing"];
  INFO(w.dump());
  CHECK(w["period_probability"].get<double>() > 0.5);
  CHECK(w["detected"].get<bool>());
  CHECK(w["period_min"].get<double>() > 85.0);
  CHECK(w["period_min"].get<double>() < 130.0);
  for (int i = 0; i < 3; ++i) {
    CHECK(std::abs(w["amplitude_nT"][i].get<double>() - 10.0) <=
          3.0 * w["amplitude_sigma_nT"][i].get<double>());
    // In the published sigma: at least the swing's rms about the mean, 10 / sqrt(2) nT.
    CHECK(j["bias_sigma_nT"][i].get<double>() > 6.0);
    CHECK(j["bias_variability_nT2"][i].get<double>() >= w["variance_nT2"][i].get<double>() - 1e-9);
  }
  const Run text = run_magcal("fit --input " + blind.string() + " --method twostep");
  REQUIRE(text.exit_code == 0);
  CHECK(text.out.find("orbit_swing_nT") != std::string::npos);
  // With the temperatures the temperature model takes it instead: no swing term.
  const Run known = run_magcal("fit --input " + full.string() + " --method twostep --json");
  REQUIRE(known.exit_code == 0);
  const nlohmann::json k = nlohmann::json::parse(known.out);
  CHECK_FALSE(k.contains("orbit_swing"));
  CHECK(k.contains("temperature_coefficient_nT_per_C"));
  for (const auto& f : {full, blind}) std::filesystem::remove(f);
}

TEST_CASE("fit --robust reports down-weighted samples", "[cli][fit]") {
  SampleSet s = model_data(600, 3.0, 2);
  for (int k = 0; k < 600; k += 100) s[k].b_sensor_nT(0) += 5000.0;
  const auto csv = temp_path("spikes.csv");
  REQUIRE(write_sample_csv(csv.string(), s).empty());
  for (const char* method : {"twostep", "centered"}) {
    // centered too: an option that is silently ignored misleads.
    INFO(method);
    const Run r =
        run_magcal("fit --input " + csv.string() + " --method " + method + " --robust --json");
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    CHECK(j["n_downweighted"].get<int>() >= 6);
    CHECK(j["verdict"] == "accepted");
    check_bias(j);
  }
  std::filesystem::remove(csv);
}

TEST_CASE("fit on an LCM log: --sat required with several spacecraft", "[cli][fit]") {
  const auto log = temp_path("two.lcm");
  {
    SampleLcmLogWriter w;
    REQUIRE(w.open(log.string(), 0).empty());
    const SampleSet a = model_data(400, 3.0, 3), b = model_data(400, 3.0, 4);
    for (int k = 0; k < 400; ++k) {
      REQUIRE(w.write(to_msg(a[k], "SAT-A", k)).empty());
      REQUIRE(w.write(to_msg(b[k], "SAT-B", k)).empty());
    }
    REQUIRE(w.close().empty());
  }
  const Run none = run_magcal("fit --input " + log.string() + " --method twostep --json");
  require_one_line_error(none, 1, "SAT-A, SAT-B");
  const Run one =
      run_magcal("fit --input " + log.string() + " --method twostep --sat SAT-B --json");
  REQUIRE(one.exit_code == 0);
  const nlohmann::json j = nlohmann::json::parse(one.out);
  CHECK(j["n_samples"] == 400);
  check_bias(j);
  const Run missing = run_magcal("fit --input " + log.string() + " --method twostep --sat SAT-Z");
  require_one_line_error(missing, 2, "SAT-Z");
  std::filesystem::remove(log);
}

TEST_CASE("fit on an LCM log with a corrupt frame: its samples left out, and said", "[cli][fit]") {
  // A lost batch must be said (magcald counts it as decode_error).
  const auto log = temp_path("corrupt_frame.lcm");
  {
    SampleLcmLogWriter w;
    REQUIRE(w.open(log.string(), 0).empty());
    const SampleSet a = model_data(400, 3.0, 3);
    for (int k = 0; k < 400; ++k) REQUIRE(w.write(to_msg(a[k], "SAT-A", k)).empty());
    REQUIRE(w.close().empty());
  }
  {
    std::ifstream in(log, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const std::size_t at = bytes.find("SAT-A");
    REQUIRE(at != std::string::npos);
    REQUIRE(at >= 4);
    for (std::size_t i = at - 4; i < at; ++i) bytes[i] = 0;  // the first sat_id's length = 0
    std::ofstream out(log, std::ios::binary | std::ios::trunc);
    out << bytes;
  }
  const Run r = run_magcal("fit --input " + log.string() + " --method twostep --json");
  INFO(r.err);
  REQUIRE(r.exit_code == 0);
  CHECK(nlohmann::json::parse(r.out)["n_samples"] == 399);
  CHECK(r.err.find("1 of 400 frames") != std::string::npos);
  CHECK(r.err.find("could not be decoded") != std::string::npos);
  std::filesystem::remove(log);
}

TEST_CASE("fit --method ukf|ekf with --trace writes state and 1-sigma per sample", "[cli][fit]") {
  const auto csv = temp_path("filter.csv");
  const auto trace = temp_path("trace.csv");
  REQUIRE(write_sample_csv(csv.string(), model_data(800, 3.0, 5)).empty());
  for (const char* method : {"ukf", "ekf"}) {
    const Run r = run_magcal("fit --input " + csv.string() + " --method " + method + " --trace " +
                             trace.string() + " --json");
    INFO(r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    CHECK(j["method"] == method);
    CHECK(j.contains("convergence_time_s"));
    std::ifstream in(trace);
    std::string header, line;
    std::getline(in, header);
    CHECK(header.rfind("t_s,b1_nT", 0) == 0);
    int rows = 0;
    while (std::getline(in, line)) ++rows;
    CHECK(rows == 800);
  }
  std::filesystem::remove(csv);
  std::filesystem::remove(trace);
}

TEST_CASE("fit --method ukf|ekf on a thermal sensor: ok only within 3 sigma of the bias at T0",
          "[cli][fit]") {
  // Tumbling, +-10 degC with every orbit, k_T (2, -1.5, 1) nT/degC: the bias swings +-20 nT per
  // orbit, faster than a filter follows: on the raw samples it is `ok` up to 16.6 sigma off the
  // current bias on 24 h of deploy/scenarios/tumbling.toml. It sees them moved to the refit's T0
  // (as the daemon's UKF) and reports the bias there.
  const auto csv = simulate_thermal_csv("filter_thermal", "tumbling", 4, "2.0, -1.5, 1.0", 10.0);
  const auto trace = temp_path("filter_thermal_trace.csv");
  const Eigen::Vector3d k(2.0, -1.5, 1.0);
  for (const char* method : {"ukf", "ekf"}) {
    const Run r = run_magcal("fit --input " + csv.string() + " --method " + method + " --trace " +
                             trace.string() + " --json");
    INFO(method << ": " << r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    CHECK(j["verdict"] == "accepted");
    REQUIRE(j.contains("reference_temperature_C"));
    const Eigen::Vector3d b_T0 = kBias + k * (j["reference_temperature_C"].get<double>() - 20.0);
    std::ifstream in(trace);
    std::string line;
    std::getline(in, line);
    int ok_rows = 0, beyond_3_sigma = 0;
    double worst = 0.0;
    while (std::getline(in, line)) {
      std::vector<std::string> f;
      for (size_t start = 0;;) {
        const size_t end = line.find(',', start);
        f.push_back(line.substr(start, end == std::string::npos ? end : end - start));
        if (end == std::string::npos) break;
        start = end + 1;
      }
      REQUIRE(f.size() > 19);
      if (f[19] != "ok") continue;
      ++ok_rows;
      double z = 0.0;
      for (int i = 0; i < 3; ++i) {
        z = std::max(z, std::abs(std::stod(f[1 + i]) - b_T0(i)) / std::stod(f[10 + i]));
      }
      beyond_3_sigma += z > 3.0 ? 1 : 0;
      worst = std::max(worst, z);
    }
    WARN(method << ": " << ok_rows << " ok rows, " << beyond_3_sigma << " beyond 3 sigma, worst "
                << worst);
    CHECK(ok_rows > 1000);
    CHECK(beyond_3_sigma <= ok_rows / 100);
    CHECK(worst < 4.0);
  }
  // 100 rows without a temperature (10 s apart): those beyond the 60 s hold of the last one
  // seen are left out of the filter, and said.
  const auto gap = temp_path("filter_thermal_gap.csv");
  blank_temperatures(csv, gap, [](int row) { return row >= 1000 && row < 1100; });
  const Run g = run_magcal("fit --input " + gap.string() + " --method ukf --json");
  INFO(g.err);
  REQUIRE(g.exit_code == 0);
  const int held = 60 / 10;
  CHECK(g.err.find(std::to_string(100 - held) + " of 4320 samples without a temperature within 60 "
                                                "s left out of the filter") != std::string::npos);
  CHECK(nlohmann::json::parse(g.out)["n_samples"] == 4320 - (100 - held));
  std::filesystem::remove(gap);
  std::filesystem::remove(csv);
  std::filesystem::remove(trace);
}

TEST_CASE("fit --method ukf|ekf: a failed refit says why the filter is not ok", "[cli][fit]") {
  // Samples in uT: the snapshot's reason alone said "waiting for the first refit".
  const auto csv = temp_path("filter_uT.csv");
  SampleSet s = model_data(600, 3.0, 21);
  for (CalibrationSample& x : s) x.b_sensor_nT *= 1e-3;
  REQUIRE(write_sample_csv(csv.string(), s).empty());
  const Run r = run_magcal("fit --input " + csv.string() + " --method ukf --json");
  INFO(r.err);
  REQUIRE(r.exit_code == 0);
  CHECK(nlohmann::json::parse(r.out)["verdict"] == "rejected");
  CHECK(r.err.find("the twostep refit that measures the model error gave failed: median |B|") !=
        std::string::npos);
  CHECK(r.err.find("another unit (uT") != std::string::npos);
  std::filesystem::remove(csv);
}

TEST_CASE("fit --method ukf|ekf: a result that is not ok is never accepted", "[cli][fit]") {
  // 3 h of the paper scenario: the filters start but their bias 1-sigma is still above the
  // 10 nT convergence threshold: a `not_converged` result can be 5.8 sigma off, and accepting it
  // would pass that on.
  const auto csv = temp_path("short.csv");
  REQUIRE(run_magcal("sim --scenario paper --hours 3 --seed 1 --out " + csv.string()).exit_code ==
          0);
  for (const char* method : {"ukf", "ekf"}) {
    const Run r = run_magcal("fit --input " + csv.string() + " --method " + method + " --json");
    INFO(method << ": " << r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    REQUIRE(j["status"] != "ok");  // the case this test is about
    CHECK(j["verdict"] == "rejected");
    REQUIRE(!j["rejection_reasons"].empty());
    CHECK(j["rejection_reasons"][0].get<std::string>().rfind(j["status"].get<std::string>(), 0) ==
          0);
  }
  std::filesystem::remove(csv);
}

TEST_CASE("fit errors: one line on stderr, exit 1 usage / 2 data", "[cli][fit]") {
  const auto csv = temp_path("err.csv");
  REQUIRE(write_sample_csv(csv.string(), model_data(600, 3.0, 6)).empty());
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method magic"), 1,
                         "--method");
  require_one_line_error(run_magcal("fit --input /nonexistent/x.csv --method twostep"), 2,
                         "does not exist");

  REQUIRE(write_sample_csv(csv.string(), model_data(12, 3.0, 7)).empty());
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2,
                         "too few samples");

  SampleSet line = model_data(300, 3.0, 8);
  for (auto& s : line) {
    s.h_body_nT = Eigen::Vector3d(0, 0, 1) * s.h_body_nT.norm();
    s.b_sensor_nT =
        (Eigen::Matrix3d::Identity() + truth_D()).inverse() * (truth_R() * s.h_body_nT + kBias);
  }
  REQUIRE(write_sample_csv(csv.string(), line).empty());
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2,
                         "geometry");
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method ukf"), 2,
                         "geometry");

  {
    std::ofstream f(csv);
    f << "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n1,2,3,nan,4,5,6\n";
  }
  const Run nan_run = run_magcal("fit --input " + csv.string() + " --method twostep");
  CHECK(nan_run.exit_code == 2);
  CHECK(nan_run.out.empty());
  std::filesystem::remove(csv);
}

TEST_CASE("fit: a field beyond any magnetometer's range is a data error naming line and column",
          "[cli][fit]") {
  // 1e300 in a field column is a corrupt number: said as such, not as a singular normal matrix.
  const auto csv = temp_path("range.csv");
  const auto trace = temp_path("range_trace.csv");
  REQUIRE(write_sample_csv(csv.string(), model_data(600, 3.0, 9)).empty());
  std::vector<std::string> lines = read_lines(csv);
  lines[50] = with_field(lines[50], 2, "1e300");  // line 51, column by_nT
  write_lines(csv, lines);
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2,
                         "line 51: column by_nT: 1e+300 nT is beyond any magnetometer's range");
  // Nothing written half: no trace file from a filter run on it.
  require_one_line_error(
      run_magcal("fit --input " + csv.string() + " --method ukf --trace " + trace.string()), 2,
      "line 51: column by_nT");
  CHECK_FALSE(std::filesystem::exists(trace));

  // The same limit on an LCM log's samples.
  const auto log = temp_path("range.lcm");
  {
    SampleLcmLogWriter w;
    REQUIRE(w.open(log.string(), 0).empty());
    const SampleSet a = model_data(100, 3.0, 10);
    for (int k = 0; k < 100; ++k) {
      mag_sample_t m = to_msg(a[k], "SAT-A", k);
      if (k == 42) m.h_body_nT[2] = -2e7;
      REQUIRE(w.write(m).empty());
    }
    REQUIRE(w.close().empty());
  }
  require_one_line_error(run_magcal("fit --input " + log.string() + " --method twostep"), 2,
                         "sample 42 (seq 42): h_body_nT[2] = -2e+07 nT is beyond");
  std::filesystem::remove(csv);
  std::filesystem::remove(log);
}

TEST_CASE(
    "fit: zero vectors are sensor dropouts (left out by --robust), a wrapped |B| names itself",
    "[cli][fit]") {
  // 18 % of the rows (0, 0, 0): before, "NaN/Inf in input", and --robust refused too.
  SampleSet dropouts = model_data(600, 3.0, 11);
  int n_zero = 0;
  for (int k = 0; k < 600; ++k) {
    if (k % 50 < 9) {
      dropouts[k].b_sensor_nT.setZero();
      ++n_zero;
    }
  }
  const auto csv = temp_path("dropouts.csv");
  REQUIRE(write_sample_csv(csv.string(), dropouts).empty());
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2,
                         "zero field vector (sensor dropout); 108 of 600 samples");
  const Run robust =
      run_magcal("fit --input " + csv.string() + " --method twostep --robust --json");
  INFO(robust.err);
  REQUIRE(robust.exit_code == 0);
  const nlohmann::json j = nlohmann::json::parse(robust.out);
  CHECK(j["n_samples"] == 600);
  CHECK(j["n_downweighted"].get<int>() >= n_zero);
  CHECK(j["verdict"] == "accepted");
  check_bias(j);

  // Negative 16-bit counts read as unsigned: c + 65536 counts, ~+6e6 nT at 92 nT per count.
  // Before, refused only through the bounds and conditioning gates, naming no magnitude.
  SampleSet wrapped = model_data(600, 3.0, 12);
  for (int k = 0; k < 600; k += 10) {
    for (int i = 0; i < 3; ++i) {
      double& v = wrapped[k].b_sensor_nT(i);
      if (v < 0.0) v += 65536.0 * 92.0;
    }
  }
  REQUIRE(write_sample_csv(csv.string(), wrapped).empty());
  for (const char* extra : {"", " --robust"}) {
    require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep" + extra),
                           2, "e+06 nT: beyond the sensor range (wrapped or wrong unit?");
  }

  // One spike beyond the range: named with its time tag (an index alone cannot be found in the
  // file); --robust leaves it out.
  SampleSet spike = model_data(600, 3.0, 13);
  spike[321].b_sensor_nT = spike[321].b_sensor_nT.normalized() * 5e6;
  REQUIRE(write_sample_csv(csv.string(), spike).empty());
  char label[80];
  std::snprintf(label, sizeof label, "sample 321 (t_s %.3f): |B| 5e+06 nT",
                static_cast<double>(spike[321].utime) * 1e-6);
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2, label);
  const Run robust_spike =
      run_magcal("fit --input " + csv.string() + " --method twostep --robust --json");
  INFO(robust_spike.err);
  REQUIRE(robust_spike.exit_code == 0);
  const nlohmann::json js = nlohmann::json::parse(robust_spike.out);
  CHECK(js["verdict"] == "accepted");
  CHECK(js["n_downweighted"].get<int>() >= 1);
  check_bias(js);
  std::filesystem::remove(csv);
}

TEST_CASE("fit: a sample CSV without its reference columns names what is missing", "[cli][fit]") {
  // The missing columns are named, not a consequence of them ("no position columns").
  const auto csv = temp_path("noref.csv");
  std::vector<std::string> rows;
  rows.push_back("t_s,bx_nT,by_nT,bz_nT");
  for (const CalibrationSample& s : model_data(300, 3.0, 14)) {
    rows.push_back(std::to_string(static_cast<double>(s.utime) * 1e-6) + "," +
                   std::to_string(s.b_sensor_nT(0)) + "," + std::to_string(s.b_sensor_nT(1)) + "," +
                   std::to_string(s.b_sensor_nT(2)));
  }
  write_lines(csv, rows);
  require_one_line_error(run_magcal("fit --input " + csv.string() + " --method twostep"), 2,
                         "hx_nT, hy_nT, hz_nT: the reference field in the body frame) nor "
                         "position columns");
  std::filesystem::remove(csv);
}

TEST_CASE("fit: a file that is no LCM log, or a log without our samples, says so", "[cli][fit]") {
  const auto log = temp_path("garbage.lcm");
  {
    std::ofstream f(log, std::ios::binary);
    std::mt19937 rng(3);
    for (int i = 0; i < 5000; ++i) f.put(static_cast<char>(rng() & 0xFF));
  }
  require_one_line_error(run_magcal("fit --input " + log.string() + " --method twostep"), 2,
                         "not an LCM log, or corrupt");
  // A valid log whose events are all on another channel.
  std::filesystem::remove(log);
  {
    lcm::LogFile out(log.string(), "w");
    REQUIRE(out.good());
    const mag_sample_t m = to_msg(model_data(1, 3.0, 11)[0], "SAT-A", 0);
    std::vector<uint8_t> buf(static_cast<size_t>(m.getEncodedSize()));
    m.encode(buf.data(), 0, static_cast<int>(buf.size()));
    lcm::LogEvent ev{};
    ev.channel = "SOMETHING_ELSE";
    ev.timestamp = m.utime;
    ev.datalen = static_cast<int32_t>(buf.size());
    ev.data = buf.data();
    REQUIRE(out.writeEvent(&ev) == 0);
  }
  require_one_line_error(run_magcal("fit --input " + log.string() + " --method twostep"), 2,
                         "without events on MAGCAL_SAMPLES or MAGCAL_BATCH (channels in it: "
                         "SOMETHING_ELSE)");
  std::filesystem::remove(log);
}

TEST_CASE("fit: repeated rows count once (same sigma), a conflicting repeat is a data error",
          "[cli][fit]") {
  // Every row twice would shrink the reported sigma by sqrt(2): the repeats are dropped.
  const auto once = temp_path("once.csv");
  const auto twice = temp_path("twice.csv");
  REQUIRE(write_sample_csv(once.string(), model_data(600, 3.0, 12)).empty());
  std::vector<std::string> lines = read_lines(once);
  std::vector<std::string> doubled = lines;
  doubled.insert(doubled.end(), lines.begin() + 1, lines.end());
  write_lines(twice, doubled);
  for (const char* method : {"twostep", "ukf"}) {
    INFO(method);
    const std::string tail = std::string(" --method ") + method + " --json";
    const Run a = run_magcal("fit --input " + once.string() + tail);
    const Run b = run_magcal("fit --input " + twice.string() + tail);
    REQUIRE(a.exit_code == 0);
    REQUIRE(b.exit_code == 0);
    CHECK(a.err.empty());
    CHECK(b.err.find("dropped 600 exact duplicate rows") != std::string::npos);
    const nlohmann::json ja = nlohmann::json::parse(a.out), jb = nlohmann::json::parse(b.out);
    CHECK(jb["n_samples"] == ja["n_samples"]);
    CHECK(jb["bias_nT"] == ja["bias_nT"]);
    CHECK(jb["bias_sigma_nT"] == ja["bias_sigma_nT"]);
  }
  // The same rule for an LCM log whose every frame was recorded twice.
  const auto log_once = temp_path("once.lcm");
  const auto log_twice = temp_path("twice.lcm");
  {
    const SampleSet set = model_data(600, 3.0, 12);
    SampleLcmLogWriter a, b;
    REQUIRE(a.open(log_once.string(), 0).empty());
    REQUIRE(b.open(log_twice.string(), 0).empty());
    for (int k = 0; k < 600; ++k) {
      REQUIRE(a.write(to_msg(set[k], "SAT-A", k)).empty());
      REQUIRE(b.write(to_msg(set[k], "SAT-A", k)).empty());
      REQUIRE(b.write(to_msg(set[k], "SAT-A", k)).empty());
    }
    REQUIRE(a.close().empty());
    REQUIRE(b.close().empty());
  }
  const Run la = run_magcal("fit --input " + log_once.string() + " --method twostep --json");
  const Run lb = run_magcal("fit --input " + log_twice.string() + " --method twostep --json");
  REQUIRE(la.exit_code == 0);
  REQUIRE(lb.exit_code == 0);
  CHECK(lb.err.find("dropped 600 exact duplicate samples") != std::string::npos);
  CHECK(nlohmann::json::parse(lb.out)["bias_sigma_nT"] ==
        nlohmann::json::parse(la.out)["bias_sigma_nT"]);
  std::filesystem::remove(log_once);
  std::filesystem::remove(log_twice);

  // The same time tag with another value: which one is the measurement is unknowable.
  lines.push_back(with_field(lines[100], 1, "12345.5"));  // line 602 repeats line 101's t_s
  write_lines(twice, lines);
  require_one_line_error(run_magcal("fit --input " + twice.string() + " --method twostep"), 2,
                         "line 602: same t_s as line 101 but other values");
  std::filesystem::remove(once);
  std::filesystem::remove(twice);
}

// ---------------------------------------------------------------- a user's own recording

namespace {

// A magcal sample CSV rewritten as a flight-dynamics export: ISO time with the zone in the
// header, the field in µT with the unit in quoted names, latitude/longitude/altitude (m) from
// the position, the attitude as q0..q3, a temperature, a mode column; `;`-separated with a
// decimal comma, and no reference columns (the reader computes them from IGRF as magcald does).
// `attitude` false: without the quaternion columns (a recording with |H| only).
void write_as_export(const std::filesystem::path& from, const std::filesystem::path& to,
                     bool attitude = true) {
  const CsvReadResult csv = read_sample_csv(from.string());
  REQUIRE(csv.ok());
  std::ofstream out(to);
  out << "\xEF\xBB\xBF\"Time (UTC)\";\"Bx (uT)\";\"By (uT)\";\"Bz (uT)\";Latitude;Longitude;"
         "\"Altitude (m)\";"
      << (attitude ? "q0;q1;q2;q3;" : "") << "temp_C;mode\n";
  const auto number = [](double v) {
    std::string text = fmt::format("{:.17g}", v);
    std::replace(text.begin(), text.end(), '.', ',');
    return text;
  };
  for (const CsvSampleRow& row : csv.rows) {
    REQUIRE(row.extras.r_ecef_m);
    REQUIRE(row.extras.q_body_from_eci);
    const GeodeticPosition g = geodetic_from_ecef(*row.extras.r_ecef_m);
    const Eigen::Vector4d& q = *row.extras.q_body_from_eci;
    std::string time = format_iso8601_utc(row.sample.utime, 6);
    time.erase(time.find_last_not_of("Z") + 1);  // the header says UTC
    out << time;
    for (int i = 0; i < 3; ++i) out << ';' << number(row.sample.b_sensor_nT(i) * 1e-3);
    out << ';' << number(g.latitude_rad * kRadToDeg) << ';' << number(g.longitude_rad * kRadToDeg)
        << ';' << number(g.altitude_m);
    if (attitude) {
      for (int i = 0; i < 4; ++i) out << ';' << number(q(i));
    }
    out << ';' << (row.extras.temperature_C ? number(*row.extras.temperature_C) : "")
        << ";nominal\n";
  }
}

Vector9d parameters_of(const nlohmann::json& j) {
  Vector9d x;
  for (int i = 0; i < 3; ++i) x(i) = j["bias_nT"][i].get<double>();
  const auto D = [&](int r, int c) { return j["D"][r][c].get<double>(); };
  x.tail<6>() << D(0, 0), D(1, 1), D(2, 2), D(0, 1), D(0, 2), D(1, 2);
  return x;
}

Vector9d sigmas_of(const nlohmann::json& j) {
  Vector9d s;
  for (int i = 0; i < 3; ++i) s(i) = j["bias_sigma_nT"][i].get<double>();
  for (int i = 0; i < 6; ++i) s(3 + i) = j["D_sigma"][i].get<double>();
  return s;
}

// The 9 parameters of a recording's fit within 0.1 sigma of the sample format's.
void check_same_estimates(const nlohmann::json& sample_format, const nlohmann::json& recording) {
  const Vector9d difference = parameters_of(recording) - parameters_of(sample_format);
  const Vector9d sigma = sigmas_of(sample_format);
  for (int i = 0; i < 9; ++i) {
    INFO("parameter " << i << ": " << difference(i) << " against sigma " << sigma(i));
    CHECK(std::abs(difference(i)) < 0.1 * sigma(i));
  }
}

// `magcal sim --scenario paper` for `hours` into a sample CSV.
std::filesystem::path simulate_paper_csv(const std::string& name, int hours, int seed) {
  const auto csv = temp_path(name);
  REQUIRE(run_magcal(fmt::format("sim --scenario paper --hours {} --seed {} --out {}", hours, seed,
                                 csv.string()))
              .exit_code == 0);
  return csv;
}

// fit --method twostep --json on `input`, which must give a result.
Run fit_twostep_json(const std::filesystem::path& input) {
  Run r = run_magcal("fit --input " + input.string() + " --method twostep --json");
  INFO(r.err);
  REQUIRE(r.exit_code == 0);
  return r;
}

}  // namespace

TEST_CASE(
    "fit: a recording with position, attitude and temperature gives the sample format's "
    "estimates (paper and tumbling thermal, 10 seeds)",
    "[cli][fit][recording]") {
  for (const char* scenario : {"paper", "tumbling_thermal"}) {
    for (int seed = 1; seed <= 10; ++seed) {
      INFO(scenario << " seed " << seed);
      const bool thermal = std::string(scenario) == "tumbling_thermal";
      const std::filesystem::path samples =
          thermal ? simulate_thermal_csv("same", "tumbling", seed, "1.0, -0.8, 1.2", 15.0)
                  : simulate_paper_csv("same_samples.csv", 6, seed);
      const auto recording = temp_path("same_export.csv");
      write_as_export(samples, recording);
      const Run a = fit_twostep_json(samples);
      const Run b = fit_twostep_json(recording);
      CHECK(b.err.find("columns used: Time (UTC), Bx (uT), By (uT), Bz (uT), Latitude, "
                       "Longitude, Altitude (m), q0, q1, q2, q3, temp_C; ignored: mode") !=
            std::string::npos);
      CHECK(b.err.find("without a zone") == std::string::npos);  // the header says UTC
      const nlohmann::json ja = nlohmann::json::parse(a.out), jb = nlohmann::json::parse(b.out);
      CHECK(jb["n_samples"] == ja["n_samples"]);
      CHECK(jb["verdict"] == ja["verdict"]);
      check_same_estimates(ja, jb);
      REQUIRE(jb.contains("R_sensor_from_body"));
      for (const char* angle : {"roll", "pitch", "yaw"}) {
        CHECK(std::abs(jb["alignment_deg"][angle].get<double>() -
                       ja["alignment_deg"][angle].get<double>()) <
              0.1 * ja["alignment_sigma_deg"][angle].get<double>());
      }
      CHECK(jb.contains("temperature_coefficient_nT_per_C") == thermal);
      if (thermal) {
        REQUIRE(ja.contains("temperature_coefficient_nT_per_C"));
        for (int i = 0; i < 3; ++i) {
          CHECK(std::abs(jb["temperature_coefficient_nT_per_C"][i].get<double>() -
                         ja["temperature_coefficient_nT_per_C"][i].get<double>()) <
                0.1 * ja["temperature_coefficient_sigma_nT_per_C"][i].get<double>());
        }
      }
      if (seed == 1) {  // the filters take recordings too
        for (const char* method : {"ekf", "ukf"}) {
          const Run f =
              run_magcal("fit --input " + recording.string() + " --method " + method + " --json");
          INFO(method << ": " << f.err);
          CHECK(f.exit_code == 0);
        }
      }
      std::filesystem::remove(samples);
      std::filesystem::remove(recording);
    }
  }
}

TEST_CASE(
    "fit: a recording with a temperature but no attitude says the temperature is not modelled",
    "[cli][fit][recording]") {
  const auto samples = simulate_thermal_csv("noatt", "tumbling", 1, "1.0, -0.8, 1.2", 15.0);
  const auto recording = temp_path("noatt_export.csv");
  write_as_export(samples, recording, false);
  const Run r = fit_twostep_json(recording);
  CHECK(r.err.find("temp_C; ignored: mode") != std::string::npos);
  CHECK(r.err.find("the temperature is not modelled in a fit against |H| alone") !=
        std::string::npos);
  CHECK_FALSE(nlohmann::json::parse(r.out).contains("temperature_coefficient_nT_per_C"));
  std::filesystem::remove(samples);
  std::filesystem::remove(recording);
}

TEST_CASE("fit: a sample CSV with attitude and position but no reference columns is fitted",
          "[cli][fit][recording]") {
  const auto samples = simulate_paper_csv("noh_samples.csv", 3, 4);
  std::vector<std::string> lines = read_lines(samples);
  for (std::string& line : lines) {  // the columns hx_nT, hy_nT, hz_nT (4..6) removed
    std::vector<std::string> fields;
    size_t start = 0;
    for (size_t comma; (comma = line.find(',', start)) != std::string::npos; start = comma + 1)
      fields.push_back(line.substr(start, comma - start));
    fields.push_back(line.substr(start));
    fields.erase(fields.begin() + 4, fields.begin() + 7);
    line = fmt::format("{}", fmt::join(fields, ","));
  }
  const auto without_h = temp_path("noh.csv");
  write_lines(without_h, lines);
  const nlohmann::json ja = nlohmann::json::parse(fit_twostep_json(samples).out);
  const nlohmann::json jb = nlohmann::json::parse(fit_twostep_json(without_h).out);
  check_same_estimates(ja, jb);
  CHECK(jb.contains("R_sensor_from_body"));
  for (const auto& f : {samples, without_h}) std::filesystem::remove(f);
}

TEST_CASE("fit: several files give one result each (JSON lines), - reads standard input",
          "[cli][fit][recording]") {
  const auto a = temp_path("multi_a.csv");
  const auto b = temp_path("multi_b.csv");
  REQUIRE(write_sample_csv(a.string(), model_data(600, 3.0, 21)).empty());
  REQUIRE(write_sample_csv(b.string(), model_data(600, 3.0, 22)).empty());
  const Run one = run_magcal("fit --input " + a.string() + " --method twostep --json");
  REQUIRE(one.exit_code == 0);
  // Repeated --input, and a glob: one JSON object per line, in order.
  const std::string glob = temp_path("multi_*.csv").string();
  for (const std::string& inputs :
       {"--input " + a.string() + " --input " + b.string(), "--input '" + glob + "'"}) {
    const Run r = run_magcal("fit " + inputs + " --method twostep --json");
    INFO(r.err);
    REQUIRE(r.exit_code == 0);
    const std::vector<std::string> lines = [&] {
      std::vector<std::string> v;
      std::istringstream in(r.out);
      for (std::string l; std::getline(in, l);) v.push_back(l);
      return v;
    }();
    REQUIRE(lines.size() == 2);
    const nlohmann::json j0 = nlohmann::json::parse(lines[0]);
    CHECK(j0["input"] == a.string());
    CHECK(nlohmann::json::parse(lines[1])["input"] == b.string());
    CHECK(j0["bias_nT"] == nlohmann::json::parse(one.out)["bias_nT"]);
  }
  // A file that fails says so and the others still give their result; the exit code says it.
  const Run partial = run_magcal("fit --input " + a.string() + " --input /nonexistent/x.csv " +
                                 "--method twostep --json");
  CHECK(partial.exit_code == 2);
  CHECK(std::count(partial.out.begin(), partial.out.end(), '\n') == 1);
  CHECK(partial.err.find("does not exist") != std::string::npos);
  require_one_line_error(
      run_magcal("fit --input '" + temp_path("none_*.csv").string() + "' --method twostep"), 1,
      "no file matches");
  // Standard input: the same result as the file.
  const Run piped = run_magcal("fit --input - --method twostep --json < " + a.string());
  INFO(piped.err);
  REQUIRE(piped.exit_code == 0);
  CHECK(nlohmann::json::parse(piped.out)["bias_nT"] == nlohmann::json::parse(one.out)["bias_nT"]);
  for (const auto& f : {a, b}) std::filesystem::remove(f);
}

TEST_CASE("fit: a recording's quaternions in another convention: the refused alignment names it",
          "[cli][fit][recording]") {
  const auto samples = simulate_paper_csv("convention_samples.csv", 6, 3);
  const auto recording = temp_path("convention_export.csv");
  write_as_export(samples, recording);
  const std::vector<std::string> lines = read_lines(recording);
  // q0..q3 are the fields 7..10 of the `;`-separated export.
  const auto rewritten = [&](const char* name, auto change) {
    std::vector<std::string> out = {lines.front()};
    for (size_t k = 1; k < lines.size(); ++k) {
      std::vector<std::string> f;
      std::istringstream in(lines[k]);
      for (std::string cell; std::getline(in, cell, ';');) f.push_back(cell);
      change(f);
      out.push_back(fmt::format("{}", fmt::join(f, ";")));
    }
    const auto path = temp_path(name);
    write_lines(path, out);
    return path;
  };
  const auto scalar_last = rewritten("convention_last.csv", [](std::vector<std::string>& f) {
    std::rotate(f.begin() + 7, f.begin() + 8, f.begin() + 11);
  });
  const auto conjugate = rewritten("convention_conj.csv", [](std::vector<std::string>& f) {
    for (int i = 8; i <= 10; ++i) f[i] = f[i][0] == '-' ? f[i].substr(1) : "-" + f[i];
  });
  const std::pair<std::filesystem::path, const char*> cases[] = {
      {scalar_last, "read as x, y, z, w (scalar last) the quaternions give an accepted alignment"},
      {conjugate, "read as the conjugate (ECI from body) the quaternions give an accepted"}};
  for (const auto& [path, reason] : cases) {
    const Run r = run_magcal("fit --input " + path.string() + " --method twostep --json");
    INFO(r.err);
    REQUIRE(r.exit_code == 0);
    const nlohmann::json j = nlohmann::json::parse(r.out);
    CHECK(j["verdict"] == "rejected");
    CHECK(j["rejection_reasons"].dump().find(reason) != std::string::npos);
  }
  const Run as_stated =
      run_magcal("fit --input " + recording.string() + " --method twostep --json");
  CHECK(nlohmann::json::parse(as_stated.out)["rejection_reasons"].dump().find(
            "attitude_convention") == std::string::npos);
  for (const auto& f : {samples, recording, scalar_last, conjugate}) std::filesystem::remove(f);
}
