#include "pipeline/simulator.hpp"

#include <cassert>
#include <cmath>
#include <limits>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {

SensorModelParameters with_thermal_period(SensorModelParameters p, double orbital_period_s) {
  if (p.temperature_period_s <= 0.0) p.temperature_period_s = orbital_period_s;
  return p;
}

// Distinct, fixed derivation of the second stream's seed (splitmix64 step).
uint64_t derived_seed(uint64_t seed) {
  uint64_t z = seed + 0x9E3779B97F4A7C15ULL;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}
}  // namespace

CalibrationSample SimulatedSample::calibration_sample() const {
  CalibrationSample s;
  s.utime = utime;
  s.b_sensor_nT = b_sensor_nT;
  s.h_body_nT = h_body_reported_nT;
  s.has_reference_direction = true;
  s.temperature_C = temperature_reported_C;
  return s;
}

Simulator::Simulator(const Scenario& scenario)
    : scenario_(scenario),
      orbit_(scenario.orbit, scenario.orbit_options),
      attitude_(scenario.attitude, scenario.epoch_utime),
      sensor_(with_thermal_period(scenario.sensor, orbit_.period_s())),
      igrf_(builtin_igrf14()),
      earth_(60.0),  // NPB moves ~0.003 arcsec per minute: far below the IGRF's own error
      sensor_noise_(scenario.seed),
      knowledge_noise_(derived_seed(scenario.seed)),
      count_(scenario.sample_count()) {
  assert(scenario.validate().empty());
}

Eigen::Vector3d Simulator::igrf_eci_nT(int64_t utime, const Eigen::Vector3d& r_ecef_m,
                                       const Eigen::Matrix3d& gcrs_from_itrf) {
  const double year = decimal_year_from_utime(utime);
  // Coefficients move by < 0.01 nT per hour of secular variation: refresh every ~1 h.
  if (std::abs(year - igrf_.date()) > 1.0 / 8784.0) {
    const bool ok = igrf_.set_date(year);
    assert(ok);
    (void)ok;
  }
  return gcrs_from_itrf * igrf_.field_ecef_nT(r_ecef_m);
}

bool Simulator::next(SimulatedSample* out) {
  if (k_ >= count_) return false;
  SimulatedSample& s = *out;
  s.index = k_;
  const double t_s = static_cast<double>(k_) * scenario_.sample_period_s;
  s.utime = scenario_.epoch_utime + utime_from_seconds(t_s);
  ++k_;

  const OrbitState eci = orbit_.state_eci(s.utime);
  s.r_eci_m = eci.r_m;
  s.v_eci_m_s = eci.v_m_s;
  const Eigen::Matrix3d gcrs_from_itrf = earth_.gcrs_from_itrf(s.utime);
  s.r_ecef_m = gcrs_from_itrf.transpose() * eci.r_m;
  s.h_eci_nT = igrf_eci_nT(s.utime, s.r_ecef_m, gcrs_from_itrf);
  s.h_norm_nT = s.h_eci_nT.norm();
  s.q_body_from_eci = attitude_.q_body_from_eci(s.utime, eci);
  const Eigen::Matrix3d A = dcm_from_quaternion(s.q_body_from_eci);
  s.h_body_nT = A * s.h_eci_nT;
  s.temperature_C = sensor_.temperature_C(t_s);
  s.temperature_reported_C =
      scenario_.temperature_reported ? s.temperature_C : std::numeric_limits<double>::quiet_NaN();
  s.b_sensor_nT = sensor_.measure(s.h_body_nT, t_s, sensor_noise_);

  // Reported knowledge.
  s.q_body_from_eci_reported = s.q_body_from_eci;
  s.r_ecef_reported_m = s.r_ecef_m;
  s.h_body_reported_nT = s.h_body_nT;
  if (scenario_.attitude_noise_deg > 0.0) {
    const Eigen::Vector3d theta =
        scenario_.attitude_noise_deg * kDegToRad * knowledge_noise_.next3();
    const double angle = theta.norm();
    QuaternionWxyz dq(1.0, 0.0, 0.0, 0.0);
    if (angle > 0.0) {
      const Eigen::Vector3d v = std::sin(0.5 * angle) / angle * theta;
      dq = QuaternionWxyz(std::cos(0.5 * angle), v.x(), v.y(), v.z());
    }
    s.q_body_from_eci_reported = quaternion_multiply(dq, s.q_body_from_eci).normalized();
    if (s.q_body_from_eci_reported(0) < 0.0)
      s.q_body_from_eci_reported = -s.q_body_from_eci_reported;
  }
  if (scenario_.gnss_noise_m > 0.0)
    s.r_ecef_reported_m += scenario_.gnss_noise_m * knowledge_noise_.next3();
  if (scenario_.attitude_noise_deg > 0.0 || scenario_.gnss_noise_m > 0.0) {
    const Eigen::Vector3d h_eci_reported =
        igrf_eci_nT(s.utime, s.r_ecef_reported_m, gcrs_from_itrf);
    s.h_body_reported_nT = dcm_from_quaternion(s.q_body_from_eci_reported) * h_eci_reported;
  }
  return true;
}

std::vector<SimulatedSample> Simulator::run() {
  std::vector<SimulatedSample> out;
  out.reserve(static_cast<size_t>(count_ - k_));
  SimulatedSample s;
  while (next(&s)) out.push_back(s);
  return out;
}

TruthParameters Simulator::truth() const {
  const SensorModelParameters& p = sensor_.parameters();
  TruthParameters t;
  t.bias_nT = p.bias_nT;
  t.D = p.D;
  t.R_sensor_from_body = sensor_.sensor_from_body();
  const RollPitchYaw rpy = roll_pitch_yaw_from_dcm(t.R_sensor_from_body);
  t.alignment_deg = Eigen::Vector3d(rpy.roll_rad, rpy.pitch_rad, rpy.yaw_rad) / kDegToRad;
  t.installation_R = p.installation();
  t.installation_deg = p.installation_deg;
  t.internal_C = p.internal_misalignment();
  t.internal_misalignment_mrad = p.internal_misalignment_mrad;
  t.permeability = p.permeability;
  t.noise_sigma_nT = p.noise_sigma_nT;
  t.nonlinearity_fraction_fs = p.nonlinearity_fraction_fs;
  t.hysteresis_fraction_fs = p.hysteresis_fraction_fs;
  t.full_scale_nT = p.full_scale_nT;
  t.saturation = p.saturation;
  t.nbits = p.nbits;
  t.lsb_nT = p.lsb_nT();
  t.temperature_coefficient_nT_per_C = p.temperature_coefficient_nT_per_C;
  t.reference_temperature_C = p.reference_temperature_C;
  t.drift_nT_per_day = p.drift_nT_per_day;
  t.temperature_mean_C = p.temperature_mean_C;
  t.temperature_amplitude_C = p.temperature_amplitude_C;
  t.temperature_period_s = p.temperature_period_s;
  t.temperature_phase_deg = p.temperature_phase_deg;
  t.temperature_reported = scenario_.temperature_reported;
  t.attitude_noise_deg = scenario_.attitude_noise_deg;
  t.gnss_noise_m = scenario_.gnss_noise_m;
  return t;
}

}  // namespace magcal
