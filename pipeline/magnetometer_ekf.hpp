// Online stage-1 calibration: extended Kalman filter on the scalar measurement, square-root
// form (estimation.md section 3; Crassidis, Lai & Harman 2005).
//
// State x = p = [b1 b2 b3 D11 D22 D33 D12 D13 D23] (nT, 1), static with optional random walk Q.
// Per sample (B_k sensor frame nT, |h_k| nT, utime), with the Cholesky factor S (P = S S^T):
//   predict   S <- chol(S S^T + Q(dt))                          (filter_common.hpp)
//   y_k = |B|^2 - |h|^2 - 3 sigma^2,  y_hat = h(x, B)           (scalar_measurement.hpp)
//   H   = dz/dp at the prior x (the CRLB row, estimation.md 2d)
//   f = S^T H^T,  S_y = |f|^2 + R_k,  x += S f (y - y_hat) / S_y,
//   S <- cholupdate(S, S f / sqrt(S_y), -)   (P - K S_y K^T as a rank-1 downdate; always PD)
// Start from data, adaptive R, gating, monitor and evidence as documented in filter_common.hpp.
// Fixed-size Eigen only: update() does not allocate.
#pragma once

#include <cstdint>
#include <memory>

#include <Eigen/Core>

#include "pipeline/filter_common.hpp"

namespace magcal {

class MagnetometerEkf : public ScalarFilterBase {
 public:
  using Options = FilterOptions;
  const Options& options() const { return filter_options(); }

  // options must be valid (Options::validate() empty); asserted. This one keeps its own copy;
  // the second shares `options` with every filter built from the same pointer (a fleet).
  explicit MagnetometerEkf(const Options& options = Options());
  explicit MagnetometerEkf(std::shared_ptr<const Options> options);

  // One sample: b_sensor_nT = measured field (sensor frame), h_norm_nT = |reference field|,
  // utime = sample time (microseconds; the filter predicts by the time since the last sample,
  // dt <= 0 predicts nothing).
  FilterUpdate update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT, int64_t utime);
};

}  // namespace magcal
