// A simulation scenario: orbit, epoch, attitude profile, sensor truth model, sampling, duration,
// spacecraft id and seed (estimation.md section 5, paper.md scenario table). Plain data;
// service/scenario_file.{hpp,cpp} reads it from TOML with the same key names used in the
// validate() messages ("orbit.inclination_deg", "sensor.nbits", ...).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "pipeline/attitude_profile.hpp"
#include "pipeline/orbit.hpp"
#include "pipeline/sensor_model.hpp"

namespace magcal {

struct Scenario {
  std::string name = "custom";
  std::string sat_id = "SIM-1";
  int64_t epoch_utime = 1577836800LL * 1'000'000;  // 2020-01-01T00:00:00Z
  double duration_s = 12.0 * 3600.0;
  double sample_period_s = 10.0;
  uint64_t seed = 1;

  // Orbit (elements at the epoch). elements.epoch_utime is kept equal to epoch_utime.
  KeplerianElements orbit;
  Orbit::Options orbit_options;

  AttitudeProfileOptions attitude;
  SensorModelParameters sensor;

  // Knowledge errors on what the spacecraft reports (off = 0).
  double attitude_noise_deg = 0.0;  // 1-sigma per axis, small rotation on the reported q
  double gnss_noise_m = 0.0;        // 1-sigma per ECEF axis on the reported position
  // false: a sensor without a temperature channel (the samples' temperature is NaN: unknown); the
  // truth's temperature still drives the bias temperature coefficient.
  bool temperature_reported = true;

  // Number of samples: floor(duration / period) + 1 would double-count the end; we use
  // samples at t = k * period for k = 0 .. floor(duration / period) - 1 (12 h @ 10 s = 4320).
  int64_t sample_count() const;

  // "" if valid, else one line naming the bad key (e.g. "orbit.eccentricity: must be in [0, 1)").
  std::string validate() const;
};

// Built-in presets: "paper", "pure", "tumbling". nullopt for an unknown name.
std::optional<Scenario> scenario_preset(std::string_view name);
std::vector<std::string> scenario_preset_names();

}  // namespace magcal
