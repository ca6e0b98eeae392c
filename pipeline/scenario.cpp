#include "pipeline/scenario.hpp"

#include <cmath>

#include "pipeline/igrf.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {

// paper.md table + estimation.md section 5.
Scenario paper_preset() {
  Scenario s;
  s.name = "paper";
  s.sat_id = "PAPER-1";
  s.epoch_utime = 1577836800LL * kMicrosPerSecond;  // 2020-01-01T00:00:00Z
  s.duration_s = 12.0 * 3600.0;
  s.sample_period_s = 10.0;
  s.seed = 1;
  s.orbit.semi_major_axis_m = kEarthEquatorialRadius_m + 550e3;
  s.orbit.eccentricity = 0.0;
  s.orbit.inclination_rad = 97.6 * kDegToRad;
  s.orbit.raan_rad = 0.0;
  s.orbit.arg_perigee_rad = 0.0;
  s.orbit.mean_anomaly_rad = 0.0;  // argument of latitude 0 at the epoch
  s.orbit.epoch_utime = s.epoch_utime;
  s.orbit_options.j2 = J2Model::none;  // "ideal (Keplerian) circular LEO"
  s.attitude.mode = AttitudeMode::nadir;
  SensorModelParameters& p = s.sensor;
  p.bias_nT = Eigen::Vector3d(1000.0, 800.0, 900.0);
  p.D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  p.noise_sigma_nT = 3.0;
  p.nonlinearity_fraction_fs = 1e-4;  // 0.01 % FS
  p.hysteresis_fraction_fs = 1e-4;
  p.full_scale_nT = 100000.0;
  p.saturation = true;
  p.nbits = 16;
  p.internal_misalignment_mrad = Eigen::Vector3d(5.0, 5.0, 5.0);
  p.installation_deg = Eigen::Vector3d(1.0, 2.0, 1.0);
  return s;
}

// A tumbling rigid body with distinct inertias and a rate of a few deg/s: every body axis
// sees the field from all directions within an orbit.
AttitudeProfileOptions tumbling_attitude() {
  AttitudeProfileOptions a;
  a.mode = AttitudeMode::tumbling;
  a.inertia_kg_m2 = Eigen::Vector3d(10.0, 14.0, 8.0);
  a.omega0_body_rad_s = Eigen::Vector3d(2.0, -1.0, 3.0) * kDegToRad;
  a.integration_step_s = 0.1;
  return a;
}
}  // namespace

int64_t Scenario::sample_count() const {
  if (!(sample_period_s > 0.0) || !(duration_s > 0.0)) return 0;
  return static_cast<int64_t>(std::floor(duration_s / sample_period_s + 1e-9));
}

std::string Scenario::validate() const {
  if (sat_id.empty() || sat_id.size() > 64) return "sat_id: must be 1..64 characters";
  const IgrfModel igrf_probe(builtin_igrf14());
  const double year0 = decimal_year_from_utime(epoch_utime);
  if (!igrf_probe.is_valid_date(year0)) return "epoch: outside the IGRF model's validity";
  if (!std::isfinite(duration_s) || duration_s <= 0.0 || duration_s > 366.0 * 86400.0)
    return "duration_h: must be in (0, 8784] hours";
  const int64_t end_utime = epoch_utime + static_cast<int64_t>(duration_s * 1e6);
  if (!igrf_probe.is_valid_date(decimal_year_from_utime(end_utime)))
    return "duration_h: the run ends outside the IGRF model's validity";
  if (!std::isfinite(sample_period_s) || sample_period_s < 1e-3 || sample_period_s > 86400.0)
    return "sample_period_s: must be in [0.001, 86400] s";
  if (sample_count() > 50'000'000) return "duration_h: more than 5e7 samples";
  if (orbit.epoch_utime != epoch_utime)
    return "orbit: element epoch differs from the scenario epoch";
  if (std::string e = orbit_options.validate(orbit); !e.empty()) return "orbit." + e;
  if (std::string e = attitude.validate(); !e.empty()) return e;
  if (std::string e = sensor.validate(); !e.empty()) return e;
  if (!std::isfinite(attitude_noise_deg) || attitude_noise_deg < 0.0 || attitude_noise_deg > 10.0)
    return "knowledge.attitude_noise_deg: must be in [0, 10]";
  if (!std::isfinite(gnss_noise_m) || gnss_noise_m < 0.0 || gnss_noise_m > 1e5)
    return "knowledge.gnss_noise_m: must be in [0, 1e5]";
  return "";
}

std::optional<Scenario> scenario_preset(std::string_view name) {
  if (name == "paper") return paper_preset();
  if (name == "tumbling") {
    Scenario s = paper_preset();
    s.name = "tumbling";
    s.sat_id = "TUMBLE-1";
    s.attitude = tumbling_attitude();
    return s;
  }
  if (name == "pure") {
    // Exactly the estimation model of estimation.md section 1: bias, D, installation R,
    // white noise; nothing else; tumbling so every axis is well observed.
    Scenario s = paper_preset();
    s.name = "pure";
    s.sat_id = "PURE-1";
    s.attitude = tumbling_attitude();
    SensorModelParameters& p = s.sensor;
    p.nonlinearity_fraction_fs = 0.0;
    p.hysteresis_fraction_fs = 0.0;
    p.saturation = false;
    p.nbits = 0;
    p.internal_misalignment_mrad.setZero();
    return s;
  }
  return std::nullopt;
}

std::vector<std::string> scenario_preset_names() {
  return {"paper", "pure", "tumbling"};
}

}  // namespace magcal
