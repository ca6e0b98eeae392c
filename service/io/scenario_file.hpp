// Scenario files (TOML, toml++) <-> pipeline/scenario.hpp, and preset lookup for the CLI.
//
// Layout (every key optional; absent keys keep the base scenario's value; deploy/scenarios/
// has commented examples). Unknown keys, wrong types and out-of-range values are errors that
// name the key, e.g. "scenario.toml: orbit.eccentricity: must be in [0, 1)".
//
//   base = "paper"                  # start from a preset (default: the paper preset)
//   name, sat_id, epoch (ISO 8601 UTC), duration_h, sample_period_s, seed
//   [orbit]       altitude_km | semi_major_axis_km, eccentricity, inclination_deg, raan_deg,
//                 arg_perigee_deg, mean_anomaly_deg, j2 = "none" | "secular"
//   [attitude]    mode = "nadir" | "inertial" | "spin" | "tumbling", q0_body_from_eci [w,x,y,z],
//                 spin_axis_body [3], spin_rate_deg_s, inertia_kg_m2 [3], omega0_deg_s [3],
//                 integration_step_s
//   [sensor]      bias_nT [3], D [[3],[3],[3]], permeability [[3],[3],[3]],
//                 internal_misalignment_mrad [3], installation_deg [roll,pitch,yaw],
//                 noise_sigma_nT, nonlinearity_fraction_fs, hysteresis_fraction_fs,
//                 full_scale_nT, saturation (bool), nbits (0 = off),
//                 temperature_coefficient_nT_per_C [3], reference_temperature_C,
//                 drift_nT_per_day [3]
//   [temperature] mean_C, amplitude_C, period_s (0 = orbital period), phase_deg
//   [knowledge]   attitude_noise_deg, gnss_noise_m
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "pipeline/scenario.hpp"

namespace magcal {

struct ScenarioLoadResult {
  std::optional<Scenario> scenario;  // set iff error is empty; always validated
  std::string error;
  bool ok() const { return error.empty(); }
};

// Parses TOML text; source_name prefixes error messages.
ScenarioLoadResult parse_scenario_toml(std::string_view text, std::string_view source_name);
ScenarioLoadResult load_scenario_file(const std::string& path);
// "paper" / "pure" / "tumbling" (built-in presets) or a path to a .toml file.
ScenarioLoadResult resolve_scenario(const std::string& preset_or_path);

// The scenario as a TOML document using the keys above (round-trips through parse).
std::string scenario_to_toml(const Scenario& scenario);

}  // namespace magcal
