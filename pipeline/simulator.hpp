// Truth simulator: orbit -> attitude -> IGRF reference field -> truth magnetometer model.
//
//   r_eci(t) from the orbit; r_ecef = itrf_from_gcrs(t) r_eci (precession-nutation cached);
//   H_eci = gcrs_from_itrf(t) IGRF_ecef(r_ecef, t);  h_body = A(q_body_from_eci) H_eci;
//   B_sensor = sensor model (pipeline/sensor_model.hpp) of h_body.
// Reported knowledge: q_reported = dq ⊗ q_true with dq a small rotation of N(0, s_att^2) per
// axis; r_ecef_reported = r_ecef + N(0, s_gnss^2 I). h_body_reported is the reference field a
// ground system computes from the reported quantities (equal to h_body when both are off).
// One seeded mt19937_64 per Simulator: same scenario and seed => bit-identical samples.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/attitude_profile.hpp"
#include "pipeline/calibration_types.hpp"
#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/orbit.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/sensor_model.hpp"

namespace magcal {

struct SimulatedSample {
  int64_t utime = 0;
  int64_t index = 0;                                            // k, t = epoch + k * period
  Eigen::Vector3d b_sensor_nT = Eigen::Vector3d::Zero();        // truth-model output
  Eigen::Vector3d h_body_nT = Eigen::Vector3d::Zero();          // true reference, body frame
  Eigen::Vector3d h_eci_nT = Eigen::Vector3d::Zero();           // IGRF in GCRS
  double h_norm_nT = 0.0;                                       // |h| (true)
  QuaternionWxyz q_body_from_eci = QuaternionWxyz(1, 0, 0, 0);  // true attitude
  Eigen::Vector3d r_eci_m = Eigen::Vector3d::Zero();            // true position
  Eigen::Vector3d v_eci_m_s = Eigen::Vector3d::Zero();
  Eigen::Vector3d r_ecef_m = Eigen::Vector3d::Zero();
  // What the spacecraft reports (noisy when the knowledge noises are on).
  QuaternionWxyz q_body_from_eci_reported = QuaternionWxyz(1, 0, 0, 0);
  Eigen::Vector3d r_ecef_reported_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d h_body_reported_nT = Eigen::Vector3d::Zero();  // IGRF from reported r, q
  double temperature_C = 0.0;                                    // true sensor temperature
  double temperature_reported_C = 0.0;  // what the sample carries: NaN without a channel

  // The estimators' view: B and the reported reference field (with direction).
  CalibrationSample calibration_sample() const;
};

// Every effect's true value (what `magcal sim --truth` writes).
struct TruthParameters {
  Eigen::Vector3d bias_nT = Eigen::Vector3d::Zero();  // b0
  Eigen::Matrix3d D = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d R_sensor_from_body = Eigen::Matrix3d::Identity();  // C_int R (stage 2 sees it)
  Eigen::Vector3d alignment_deg = Eigen::Vector3d::Zero();           // roll, pitch, yaw of it
  Eigen::Matrix3d installation_R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d installation_deg = Eigen::Vector3d::Zero();
  Eigen::Matrix3d internal_C = Eigen::Matrix3d::Identity();
  Eigen::Vector3d internal_misalignment_mrad = Eigen::Vector3d::Zero();
  Eigen::Matrix3d permeability = Eigen::Matrix3d::Zero();
  double noise_sigma_nT = 0.0;
  double nonlinearity_fraction_fs = 0.0;
  double hysteresis_fraction_fs = 0.0;
  double full_scale_nT = 0.0;
  bool saturation = false;
  int nbits = 0;
  double lsb_nT = 0.0;
  Eigen::Vector3d temperature_coefficient_nT_per_C = Eigen::Vector3d::Zero();
  double reference_temperature_C = 0.0;
  Eigen::Vector3d drift_nT_per_day = Eigen::Vector3d::Zero();
  double temperature_mean_C = 0.0, temperature_amplitude_C = 0.0, temperature_period_s = 0.0;
  double temperature_phase_deg = 0.0;  // T(t) = mean + amplitude sin(2 pi t / period + phase)
  bool temperature_reported = true;    // false: the samples carry no temperature
  double attitude_noise_deg = 0.0;
  double gnss_noise_m = 0.0;
};

class Simulator {
 public:
  // scenario.validate() must be "" (check it first; user errors are reported there).
  explicit Simulator(const Scenario& scenario);

  int64_t sample_count() const { return count_; }
  // Produces the next sample; false after the last one. Samples come in time order.
  bool next(SimulatedSample* out);
  // All remaining samples.
  std::vector<SimulatedSample> run();

  TruthParameters truth() const;
  const Scenario& scenario() const { return scenario_; }
  const Orbit& orbit() const { return orbit_; }

 private:
  Eigen::Vector3d igrf_eci_nT(int64_t utime, const Eigen::Vector3d& r_ecef_m,
                              const Eigen::Matrix3d& gcrs_from_itrf);

  Scenario scenario_;
  Orbit orbit_;
  AttitudeProfile attitude_;
  SensorModel sensor_;
  IgrfModel igrf_;
  EarthOrientationCache earth_;
  NormalSampler sensor_noise_;     // measurement noise
  NormalSampler knowledge_noise_;  // attitude / GNSS noise (separate stream: switching them
                                   // on does not change the measurement noise)
  int64_t count_ = 0;
  int64_t k_ = 0;
};

}  // namespace magcal
