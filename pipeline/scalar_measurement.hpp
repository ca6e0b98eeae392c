// The attitude-independent scalar measurement (estimation.md section 2), shared by the batch
// estimators, the EKF/UKF, the CRLB and the simulator checks, so there is one copy of it.
//
//   z_k = |B_k|^2 - |H_k|^2 = -B^T E B + 2 B^T c - |b|^2 + v_k,  E = 2D + D^2, c = (I+D) b
//   mu_k = E[v_k] = +tr(Sigma) = 3 sigma^2
//   sigma_k^2 = Var[v_k] = 4 y^T Sigma y + 2 tr(Sigma^2) = 4 sigma^2 |y|^2 + 6 sigma^4,
//   y = (I+D) B - b  (≈ R h; B itself at first)
//   Linear form z = L theta - |b|^2,  L = [2 B^T, -S],  S = [B1², B2², B3², 2B1B2, 2B1B3, 2B2B3],
//   theta = [c; E11 E22 E33 E12 E13 E23]
#pragma once

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

// z_k = |B|^2 - |h|^2 (nT^2)
inline double scalar_measurement(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT) {
  return b_sensor_nT.squaredNorm() - h_norm_nT * h_norm_nT;
}

// L_k = [2 B^T, -S_k] (1x9)
inline RowVector9d scalar_regressor(const Eigen::Vector3d& B) {
  RowVector9d L;
  L << 2.0 * B(0), 2.0 * B(1), 2.0 * B(2), -B(0) * B(0), -B(1) * B(1), -B(2) * B(2),
      -2.0 * B(0) * B(1), -2.0 * B(0) * B(2), -2.0 * B(1) * B(2);
  return L;
}

// E[v_k] for isotropic noise of sigma per axis.
inline double scalar_noise_mean(double sigma_nT) {
  return 3.0 * sigma_nT * sigma_nT;
}

// Var[v_k] for isotropic noise, given y = (I+D)B - b (or B as the first approximation).
inline double scalar_noise_variance(const Eigen::Vector3d& y_nT, double sigma_nT) {
  const double s2 = sigma_nT * sigma_nT;
  return 4.0 * s2 * y_nT.squaredNorm() + 6.0 * s2 * s2;
}

// h(p, B) = -B^T E B + 2 B^T (I + D) b - |b|^2, the noise-free z for parameters p.
// (Equivalently |(I+D)B - b|^2 - |B|^2 ... rearranged: z = |B|^2 - |(I+D)B - b|^2.)
inline double predicted_scalar_measurement(const Vector9d& p, const Eigen::Vector3d& B) {
  const Eigen::Vector3d y = CalibrationParameters::from_packed(p).apply(B);
  return B.squaredNorm() - y.squaredNorm();
}

// dz/dp at p (estimation.md 2d; also the EKF's measurement Jacobian).
//   dz/db = 2 y^T,  dz/dD = -2 [B1y1, B2y2, B3y3, B1y2+B2y1, B1y3+B3y1, B2y3+B3y2]
// Given y = (I + D) B - b already (the CRLB needs it for the weight too).
inline RowVector9d scalar_measurement_jacobian_at(const Eigen::Vector3d& y,
                                                  const Eigen::Vector3d& B) {
  RowVector9d J;
  J << 2.0 * y(0), 2.0 * y(1), 2.0 * y(2), -2.0 * B(0) * y(0), -2.0 * B(1) * y(1),
      -2.0 * B(2) * y(2), -2.0 * (B(0) * y(1) + B(1) * y(0)), -2.0 * (B(0) * y(2) + B(2) * y(0)),
      -2.0 * (B(1) * y(2) + B(2) * y(1));
  return J;
}
inline RowVector9d scalar_measurement_jacobian(const Vector9d& p, const Eigen::Vector3d& B) {
  return scalar_measurement_jacobian_at(CalibrationParameters::from_packed(p).apply(B), B);
}

}  // namespace magcal
