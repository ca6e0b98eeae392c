// Cramér–Rao lower bound of p = [b; D11 D22 D33 D12 D13 D23] on an actual sample set
// (estimation.md 2d), and the observability figures every result reports.
//
//   y_k = (I + D) B_k - b,   dz_k/dp = scalar_measurement_jacobian(p, B_k)
//   F = sum_k (1/sigma_k^2) (dz_k/dp)^T (dz_k/dp),  sigma_k^2 = 4 sigma^2 |y_k|^2 + 6 sigma^4
//   Cov(p_hat) >= F^-1
//   Scaled F_s = S^-1 F S^-1, S = diag(sqrt(diag F)) (F mixes nT and dimensionless D):
//   condition number and smallest eigenvalue of F_s (trace 9) measure observability.
#pragma once

#include <string>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

struct CrlbResult {
  bool ok = false;  // F invertible (finite condition number below max_condition)
  std::string message;
  Matrix9d fisher = Matrix9d::Zero();      // F (1/nT^2, 1/nT, 1)
  Matrix9d covariance = Matrix9d::Zero();  // F^-1 (nT^2, nT, 1); zero if !ok
  Vector9d sigma = Vector9d::Zero();       // sqrt(diag F^-1)
  double condition_number = 0.0;           // of F_s (+inf if singular)
  double min_eigenvalue = 0.0;             // of F_s
  int n_samples = 0;                       // samples used (finite B, |h| > 0)
};

// Fisher information at parameters p; samples with non-finite B are skipped (counted out of
// n_samples). max_condition: above it F is declared singular (ok = false).
CrlbResult compute_crlb(const SampleSet& samples, const CalibrationParameters& p, double sigma_nT,
                        double max_condition = 1e14);

// Condition number and smallest eigenvalue of the scaled matrix S^-1 F S^-1.
void scaled_condition(const Matrix9d& F, double* condition_number, double* min_eigenvalue);

}  // namespace magcal
