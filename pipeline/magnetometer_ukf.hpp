// Online stage-1 calibration: square-root unscented Kalman filter on the scalar measurement
// (estimation.md sections 3 and 7; Crassidis, Lai & Harman 2005; van der Merwe & Wan 2001).
//
// State x = p = [b1 b2 b3 D11 D22 D33 D12 D13 D23] (nT, 1), static with optional random walk Q.
// Scaled unscented transform with n = 9, lambda = alpha^2 (n + kappa) - n, on the Cholesky
// factor S kept by the state (P = S S^T, filter_common.hpp):
//   X_0 = x, X_{+-i} = x +- sqrt(n + lambda) S_i
//   W0m = lambda / (n + lambda), W0c = W0m + 1 - alpha^2 + beta, Wi = 1 / (2 (n + lambda))
// Defaults alpha = 1, beta = 2, kappa = 3 - n: lambda = -6, spread sqrt(3), W0m = -2, W0c = 0,
// Wi = 1/6. W0c >= 0 is required: then S_y >= Pxz^T P^-1 Pxz + R and the downdate below is
// positive definite without a guard.
// Per sample: predict S <- chol(S S^T + Q(dt)); Z_i = h(X_i, B) (exact and cheap: y(p) is
// linear in p, see update()), y_hat = sum Wm Z_i,
//   S_y = sum Wc (Z_i - y_hat)^2 + R_k,  Pxz = sum Wc (X_i - x)(Z_i - y_hat),
//   x += Pxz (y - y_hat) / S_y,  S <- cholupdate(S, Pxz / sqrt(S_y), -)   (rank-1 downdate)
// Start from data, adaptive R, gating, monitor and evidence as documented in filter_common.hpp.
// Fixed-size Eigen only: update() does not allocate.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include <Eigen/Core>

#include "pipeline/filter_common.hpp"

namespace magcal {

// FilterOptions plus the unscented-transform parameters.
struct UkfOptions : FilterOptions {
  double alpha = 1.0;
  double beta = 2.0;
  double kappa = 3.0 - 9.0;      // 3 - n
  std::string validate() const;  // also requires n + lambda = alpha^2 (n + kappa) > 0
};

class MagnetometerUkf : public ScalarFilterBase {
 public:
  using Options = UkfOptions;

  // options must be valid (Options::validate() empty); asserted. This one keeps its own copy;
  // the second shares `options` with every filter built from the same pointer (a fleet).
  explicit MagnetometerUkf(const Options& options = Options());
  explicit MagnetometerUkf(std::shared_ptr<const Options> options);

  const Options& options() const { return static_cast<const Options&>(filter_options()); }

  // One sample: b_sensor_nT = measured field (sensor frame), h_norm_nT = |reference field|,
  // utime = sample time (microseconds; the filter predicts by the time since the last sample,
  // dt <= 0 predicts nothing).
  FilterUpdate update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT, int64_t utime);
};

}  // namespace magcal
