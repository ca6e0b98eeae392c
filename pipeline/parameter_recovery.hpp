// Recovery of the bias b and the symmetric D from theta = [c; E] (estimation.md 2c), and the
// inverse map.
//
//   E = 2D + D^2,  c = (I + D) b                          (theta_from_parameters)
//   I + E = U diag(s) U^T  (SelfAdjointEigenSolver only: an SVD would hide negative s)
//   I + D = U diag(sqrt(s)) U^T,  D = U diag(sqrt(s) - 1) U^T,  b = (I + D)^-1 c
//
// Any s <= 0 (or non-finite theta) means the data do not support the solution: the result is
// failed, never NaN. Covariance: Cov(p) = J Cov(theta) J^T with J = dp/dtheta, obtained as the
// inverse of the analytic Jacobian dtheta/dp of the forward map (exact, no step sizes).
// Only the principal square root is recovered: D with I + D positive definite.
#pragma once

#include <string>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

enum class RecoveryStatus {
  kOk = 0,                   // b, D valid
  kNotPositiveDefinite = 1,  // an eigenvalue of I + E is <= min_eigenvalue
  kInvalidInput = 2,         // theta has NaN/Inf
};
const char* to_string(RecoveryStatus s);

struct RecoveryResult {
  RecoveryStatus status = RecoveryStatus::kInvalidInput;
  std::string message;
  CalibrationParameters parameters;
  Matrix9d covariance = Matrix9d::Zero();  // of p = [b; D packed]; zero if not requested
  Eigen::Vector3d eigenvalues = Eigen::Vector3d::Zero();  // s of I + E, ascending
  bool ok() const { return status == RecoveryStatus::kOk; }
};

// theta -> (b, D). theta_covariance may be null (covariance left zero).
RecoveryResult recover_parameters(const Vector9d& theta, const Matrix9d* theta_covariance = nullptr,
                                  double min_eigenvalue = 1e-9);

// (b, D) -> theta = [(I + D) b; pack(2D + D^2)].
Vector9d theta_from_parameters(const CalibrationParameters& p);

// dtheta/dp at p (analytic; 9x9).
Matrix9d theta_jacobian(const CalibrationParameters& p);

}  // namespace magcal
