// The difference of two calibrations A and B of one sensor against their uncertainties:
//   dp = p_B - p_A  (p = [b1 b2 b3 D11 D22 D33 D12 D13 D23], estimation.md section 0),
//   z_i = dp_i / sqrt(C_A,ii + C_B,ii),   chi2 = dp^T (C_A + C_B)^-1 dp  (9 degrees of freedom),
// and, when both carry an alignment, the rotation between them as a rotation vector in the
// sensor frame, dtheta = log(R_B R_A^T) (R_B = exp([dtheta x]) R_A), against C_theta,A +
// C_theta,B (3 degrees of freedom). The two are taken as independent: for refits of overlapping
// windows the sum overstates the difference's variance, so "significant" errs towards "within
// the noise".
#pragma once

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

struct CalibrationDifference {
  Vector9d dp = Vector9d::Zero();
  Vector9d sigma = Vector9d::Zero();  // sqrt(C_A,ii + C_B,ii)
  Vector9d z = Vector9d::Zero();      // dp_i / sigma_i (NaN where sigma is 0)
  double chi2 = 0.0;                  // NaN when C_A + C_B is not positive definite
  bool significant = false;           // chi2 beyond kChi2Quantile99_9dof (or alignment's)
  // Both have the same terms (alignment, temperature model, bias rate). When not, the chi2
  // leaves out what only one has, and "not significant" does not make them equivalent.
  bool same_model = true;

  bool has_alignment = false;  // both carry one
  Eigen::Vector3d dtheta_rad = Eigen::Vector3d::Zero();
  double alignment_chi2 = 0.0;  // NaN when unknown (a covariance not positive definite or NaN)

  // The 99 % quantiles of chi-square with 9 and 3 degrees of freedom.
  static constexpr double kChi2Quantile99_9dof = 21.666;
  static constexpr double kChi2Quantile99_3dof = 11.345;
};

CalibrationDifference calibration_difference(const CalibrationResult& a,
                                             const CalibrationResult& b);

}  // namespace magcal
