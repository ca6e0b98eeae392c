// magcal sim --scenario paper|FILE.toml --hours H --seed S --out FILE.lcm|FILE.csv
//            [--truth FILE.json] [--sat-id ID] [--batch N]
// Writes to temporary files in the output folders and renames them at the end, so an error
// never leaves a half-written output behind.
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>

#include "pipeline/simulator.hpp"
#include "pipeline/time_utc.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/sample_files.hpp"
#include "service/io/scenario_file.hpp"

namespace magcal::cli {

namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() &&
         s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

std::string temp_path_for(const std::string& path) {
  return path + ".tmp." + std::to_string(::getpid());
}

nlohmann::json json_vec(const Eigen::Vector3d& v) {
  return {v(0), v(1), v(2)};
}
nlohmann::json json_mat(const Eigen::Matrix3d& m) {
  nlohmann::json a = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) a.push_back({m(r, 0), m(r, 1), m(r, 2)});
  return a;
}

nlohmann::json truth_json(const Simulator& sim) {
  const TruthParameters t = sim.truth();
  const Scenario& s = sim.scenario();
  nlohmann::json j;
  j["scenario"] = s.name;
  j["sat_id"] = s.sat_id;
  j["seed"] = s.seed;
  j["epoch"] = format_iso8601_utc(s.epoch_utime);
  j["epoch_utime"] = s.epoch_utime;
  j["duration_h"] = s.duration_s / 3600.0;
  j["sample_period_s"] = s.sample_period_s;
  j["n_samples"] = sim.sample_count();
  j["bias_nT"] = json_vec(t.bias_nT);
  j["D"] = json_mat(t.D);
  j["R_sensor_from_body"] = json_mat(t.R_sensor_from_body);
  j["alignment_deg"] = {
      {"roll", t.alignment_deg(0)}, {"pitch", t.alignment_deg(1)}, {"yaw", t.alignment_deg(2)}};
  j["installation_R"] = json_mat(t.installation_R);
  j["installation_deg"] = {{"roll", t.installation_deg(0)},
                           {"pitch", t.installation_deg(1)},
                           {"yaw", t.installation_deg(2)}};
  j["internal_misalignment_mrad"] = json_vec(t.internal_misalignment_mrad);
  j["internal_C"] = json_mat(t.internal_C);
  j["permeability"] = json_mat(t.permeability);
  j["noise_sigma_nT"] = t.noise_sigma_nT;
  j["nonlinearity_fraction_fs"] = t.nonlinearity_fraction_fs;
  j["hysteresis_fraction_fs"] = t.hysteresis_fraction_fs;
  j["full_scale_nT"] = t.full_scale_nT;
  j["saturation"] = t.saturation;
  j["nbits"] = t.nbits;
  j["lsb_nT"] = t.lsb_nT;
  j["temperature_coefficient_nT_per_C"] = json_vec(t.temperature_coefficient_nT_per_C);
  j["reference_temperature_C"] = t.reference_temperature_C;
  j["drift_nT_per_day"] = json_vec(t.drift_nT_per_day);
  j["temperature"] = {{"mean_C", t.temperature_mean_C},
                      {"amplitude_C", t.temperature_amplitude_C},
                      {"period_s", t.temperature_period_s},
                      {"phase_deg", t.temperature_phase_deg},
                      {"reported", t.temperature_reported}};
  j["attitude_noise_deg"] = t.attitude_noise_deg;
  j["gnss_noise_m"] = t.gnss_noise_m;
  return j;
}

mag_sample_t to_message(const SimulatedSample& s, const std::string& sat_id) {
  mag_sample_t m;
  m.utime = s.utime;
  m.sat_id = sat_id;
  m.seq = s.index;
  for (int i = 0; i < 3; ++i) {
    m.b_sensor_nT[i] = s.b_sensor_nT(i);
    m.r_ecef_m[i] = s.r_ecef_reported_m(i);
    m.h_body_nT[i] = s.h_body_reported_nT(i);
  }
  for (int i = 0; i < 4; ++i) m.q_body_from_eci[i] = s.q_body_from_eci_reported(i);
  m.has_position = true;
  m.has_attitude = true;
  m.has_reference = true;
  m.temperature_C = static_cast<float>(s.temperature_reported_C);  // NaN: no channel
  return m;
}

int fail(const std::string& message, int code, const std::vector<std::string>& temps) {
  std::error_code ec;
  for (const auto& t : temps) std::filesystem::remove(t, ec);
  std::cerr << "magcal sim: " << message << "\n";
  return code;
}

}  // namespace

int run_sim(const SimArgs& args) {
  const bool to_lcm = ends_with(args.out, ".lcm");
  const bool to_csv = ends_with(args.out, ".csv");
  if (!to_lcm && !to_csv)
    return fail("--out must end in .lcm or .csv: " + args.out, kExitUsage, {});
  if (args.batch_size < 0 || args.batch_size > 400)
    return fail("--batch must be in [0, 400] (LCM fragments above ~400 samples)", kExitUsage, {});
  if (args.batch_size > 0 && !to_lcm)
    return fail("--batch applies to .lcm output only", kExitUsage, {});
  if (!args.truth.empty() && !ends_with(args.truth, ".json"))
    return fail("--truth must end in .json: " + args.truth, kExitUsage, {});

  ScenarioLoadResult loaded = resolve_scenario(args.scenario);
  if (!loaded.ok()) {
    const bool is_preset_name = args.scenario.find('.') == std::string::npos &&
                                args.scenario.find('/') == std::string::npos;
    return fail(loaded.error, is_preset_name ? kExitUsage : kExitData, {});
  }
  Scenario scenario = *loaded.scenario;
  if (args.hours) {
    if (!std::isfinite(*args.hours) || *args.hours <= 0.0)
      return fail("--hours must be > 0", kExitUsage, {});
    scenario.duration_s = *args.hours * 3600.0;
  }
  if (args.seed) scenario.seed = *args.seed;
  if (args.sat_id) scenario.sat_id = *args.sat_id;
  if (std::string e = scenario.validate(); !e.empty()) {
    // "sat_id: must be 1..64 characters" about the flag's value names the flag.
    if (args.sat_id && e.rfind("sat_id:", 0) == 0) {
      e = "--sat-id" + e.substr(7) + " (got \"" + *args.sat_id + "\")";
    }
    return fail(e, kExitUsage, {});
  }

  Simulator sim(scenario);
  const std::string out_tmp = temp_path_for(args.out);
  const std::string truth_tmp = args.truth.empty() ? "" : temp_path_for(args.truth);
  std::vector<std::string> temps = {out_tmp};
  if (!truth_tmp.empty()) temps.push_back(truth_tmp);

  SampleCsvWriter csv;
  SampleLcmLogWriter lcm_log;
  const std::string open_error =
      to_csv ? csv.open(out_tmp) : lcm_log.open(out_tmp, args.batch_size);
  if (!open_error.empty()) return fail(args.out + ": cannot open for writing", kExitData, temps);

  const auto start = std::chrono::steady_clock::now();
  const int64_t n = sim.sample_count();
  const bool show_progress = n >= 100'000;
  int64_t next_report = n / 10;
  double h_min = INFINITY, h_max = 0.0;
  SimulatedSample s;
  while (sim.next(&s)) {
    h_min = std::min(h_min, s.h_norm_nT);
    h_max = std::max(h_max, s.h_norm_nT);
    if (to_csv) {
      CsvSampleExtras extras;
      extras.q_body_from_eci = s.q_body_from_eci_reported;
      extras.r_ecef_m = s.r_ecef_reported_m;
      if (std::isfinite(s.temperature_reported_C)) extras.temperature_C = s.temperature_reported_C;
      csv.write(s.calibration_sample(), extras);
    } else if (std::string e = lcm_log.write(to_message(s, scenario.sat_id)); !e.empty()) {
      return fail(e, kExitData, temps);
    }
    if (show_progress && s.index + 1 >= next_report) {
      std::cerr << "magcal sim: " << (100 * (s.index + 1) / n) << " % (" << (s.index + 1) << "/"
                << n << ")\n";
      next_report += n / 10;
    }
  }
  const std::string close_error = to_csv ? csv.close() : lcm_log.close();
  if (!close_error.empty()) return fail(close_error, kExitData, temps);

  if (!truth_tmp.empty()) {
    std::ofstream out(truth_tmp);
    out << truth_json(sim).dump(2) << "\n";
    out.close();
    if (!out) return fail(args.truth + ": write error", kExitData, temps);
  }
  std::error_code ec;
  std::filesystem::rename(out_tmp, args.out, ec);
  if (ec) return fail(args.out + ": " + ec.message(), kExitData, temps);
  if (!truth_tmp.empty()) {
    std::filesystem::rename(truth_tmp, args.truth, ec);
    if (ec) return fail(args.truth + ": " + ec.message(), kExitData, {truth_tmp});
  }
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::fprintf(
      stderr, "magcal sim: %s: %lld samples of %s (%s, seed %llu), |h| %.0f..%.0f nT, %.3f s\n",
      args.out.c_str(), static_cast<long long>(n), scenario.sat_id.c_str(), scenario.name.c_str(),
      static_cast<unsigned long long>(scenario.seed), h_min, h_max, elapsed_s);
  return kExitOk;
}

}  // namespace magcal::cli
