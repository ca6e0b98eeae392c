// Truth magnetometer model (estimation.md section 5; simulator only).
//
//   x_k = C_int R h_k                                   noise-free field on the sensor axes
//   B_k = Q_nbits( sat( (I+D)^-1 ( x_k + P x_k + b(t, T) + n_nl + n_hyst + eps_k ) ) )
//
//   C_int  internal misalignment: Rx(a1) Ry(a2) Rz(a3), a = internal_misalignment_mrad * 1e-3
//   R      installation R_sensor_from_body = dcm_from_roll_pitch_yaw(installation_deg)
//   P      permeability (soft-iron-like), 3x3, dimensionless
//   b(t,T) = b0 + k_T (T - T0) + k_drift t        (t: seconds since the scenario epoch)
//   T(t)   = T_mean + T_amp sin(2 pi t / T_period + phase)   (simple orbital thermal cycle)
//   n_nl,i = k_nl x_i^2 / FS
//   n_hyst,i = s_i k_h FS,  s_i = sign of the last non-zero change of x_i (initially +1)
//   eps_k ~ N(0, sigma^2 I)
//   sat: clip to [-FS, FS];  Q: LSB = 2 FS / 2^nbits, round(B / LSB) LSB, clip [-FS, FS - LSB]
// All fields in nT, sensor frame. Every effect is off when its parameter is zero/false.
#pragma once

#include <cstdint>
#include <random>
#include <string>

#include <Eigen/Core>

namespace magcal {

// Standard normal deviates from a seeded mt19937_64 with our own Box–Muller transform, so the
// sequence is the same on every standard library (std::normal_distribution is not).
class NormalSampler {
 public:
  explicit NormalSampler(uint64_t seed) : engine_(seed) {}
  double next();  // N(0, 1)
  Eigen::Vector3d next3() {
    const double a = next(), b = next(), c = next();
    return {a, b, c};
  }

 private:
  std::mt19937_64 engine_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

struct SensorModelParameters {
  Eigen::Vector3d bias_nT = Eigen::Vector3d::Zero();       // b0
  Eigen::Matrix3d D = Eigen::Matrix3d::Zero();             // symmetric
  Eigen::Matrix3d permeability = Eigen::Matrix3d::Zero();  // P
  Eigen::Vector3d internal_misalignment_mrad = Eigen::Vector3d::Zero();
  Eigen::Vector3d installation_deg = Eigen::Vector3d::Zero();  // roll, pitch, yaw
  double noise_sigma_nT = 0.0;
  double nonlinearity_fraction_fs = 0.0;  // k_nl (0.01 % => 1e-4)
  double hysteresis_fraction_fs = 0.0;    // k_h
  double full_scale_nT = 100000.0;        // FS (used by nl, hysteresis, saturation, quantisation)
  bool saturation = false;
  int nbits = 0;  // 0 = no quantisation
  Eigen::Vector3d temperature_coefficient_nT_per_C = Eigen::Vector3d::Zero();  // k_T
  double reference_temperature_C = 20.0;                                       // T0
  Eigen::Vector3d drift_nT_per_day = Eigen::Vector3d::Zero();  // k_drift (per day in files)
  // Thermal cycle T(t); period 0 = the orbital period (set by the simulator).
  double temperature_mean_C = 20.0;
  double temperature_amplitude_C = 0.0;
  double temperature_period_s = 0.0;
  double temperature_phase_deg = 0.0;

  // "" if valid, else names the bad key (as in scenario files: "sensor.<key>").
  std::string validate() const;

  Eigen::Matrix3d internal_misalignment() const;  // C_int
  Eigen::Matrix3d installation() const;           // R (installation_R)
  double lsb_nT() const;                          // 0 if nbits == 0
};

class SensorModel {
 public:
  // parameters must validate; a zero temperature_period_s must have been replaced by the caller.
  explicit SensorModel(const SensorModelParameters& parameters);

  double temperature_C(double t_s) const;
  Eigen::Vector3d bias_nT(double t_s, double temperature_C) const;  // b(t, T)

  // One measurement of the body-frame field h at t_s seconds since the epoch. Updates the
  // hysteresis state; noise drawn from `normal` only when sigma > 0.
  Eigen::Vector3d measure(const Eigen::Vector3d& h_body_nT, double t_s, NormalSampler& normal);

  // The deterministic chain after the noise is added (exposed for tests): sat and Q of
  // (I+D)^-1 y.
  Eigen::Vector3d digitise(const Eigen::Vector3d& y_nT) const;

  const Eigen::Matrix3d& sensor_from_body() const { return M_; }  // C_int R
  const SensorModelParameters& parameters() const { return p_; }

 private:
  SensorModelParameters p_;
  Eigen::Matrix3d M_;  // C_int R
  Eigen::Matrix3d inv_I_plus_D_;
  bool has_last_x_ = false;
  Eigen::Vector3d last_x_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d hyst_sign_ = Eigen::Vector3d::Ones();
};

}  // namespace magcal
