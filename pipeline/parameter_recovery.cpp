#include "pipeline/parameter_recovery.hpp"

#include <cmath>
#include <cstdio>

#include <Eigen/Dense>

namespace magcal {

const char* to_string(RecoveryStatus s) {
  switch (s) {
    case RecoveryStatus::kOk:
      return "ok";
    case RecoveryStatus::kNotPositiveDefinite:
      return "not_positive_definite";
    case RecoveryStatus::kInvalidInput:
      return "invalid_input";
  }
  return "invalid_input";
}

namespace {
// Symmetric unit matrix of packed element i (0..5: 11 22 33 12 13 23).
Eigen::Matrix3d packed_unit(int i) {
  Vector6d e = Vector6d::Zero();
  e(i) = 1.0;
  return unpack_symmetric(e);
}
}  // namespace

Vector9d theta_from_parameters(const CalibrationParameters& p) {
  const Eigen::Matrix3d I_D = Eigen::Matrix3d::Identity() + p.D;
  Vector9d theta;
  theta << I_D * p.bias_nT, pack_symmetric(2.0 * p.D + p.D * p.D);
  return theta;
}

Matrix9d theta_jacobian(const CalibrationParameters& p) {
  Matrix9d J = Matrix9d::Zero();
  // dc/db = I + D
  J.block<3, 3>(0, 0) = Eigen::Matrix3d::Identity() + p.D;
  for (int i = 0; i < 6; ++i) {
    const Eigen::Matrix3d dD = packed_unit(i);
    // dc = dD b;  dE = 2 dD + dD D + D dD
    J.block<3, 1>(0, 3 + i) = dD * p.bias_nT;
    J.block<6, 1>(3, 3 + i) = pack_symmetric(2.0 * dD + dD * p.D + p.D * dD);
  }
  return J;
}

RecoveryResult recover_parameters(const Vector9d& theta, const Matrix9d* theta_covariance,
                                  double min_eigenvalue) {
  RecoveryResult r;
  if (!theta.allFinite()) {
    r.status = RecoveryStatus::kInvalidInput;
    r.message = "theta has non-finite elements";
    return r;
  }
  const Eigen::Matrix3d I_E = Eigen::Matrix3d::Identity() + unpack_symmetric(theta.tail<6>());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(I_E);
  r.eigenvalues = eig.eigenvalues();
  if (eig.info() != Eigen::Success || !(r.eigenvalues.minCoeff() > min_eigenvalue)) {
    r.status = RecoveryStatus::kNotPositiveDefinite;
    char buf[160];
    std::snprintf(buf, sizeof buf,
                  "I + E is not positive definite (eigenvalues %.3g %.3g %.3g): the data do not "
                  "support a solution",
                  r.eigenvalues(0), r.eigenvalues(1), r.eigenvalues(2));
    r.message = buf;
    return r;
  }
  const Eigen::Matrix3d& U = eig.eigenvectors();
  const Eigen::Vector3d sqrt_s = r.eigenvalues.cwiseSqrt();
  const Eigen::Matrix3d I_D = U * sqrt_s.asDiagonal() * U.transpose();
  Eigen::Matrix3d D = I_D - Eigen::Matrix3d::Identity();
  D = 0.5 * (D + D.transpose()).eval();
  r.parameters.D = D;
  r.parameters.bias_nT = U * sqrt_s.cwiseInverse().asDiagonal() * U.transpose() * theta.head<3>();
  if (theta_covariance != nullptr) {
    const Matrix9d J_theta = theta_jacobian(r.parameters);
    const Matrix9d J = J_theta.partialPivLu().inverse();  // dp/dtheta
    Matrix9d C = J * (*theta_covariance) * J.transpose();
    r.covariance = 0.5 * (C + C.transpose());
  }
  r.status = RecoveryStatus::kOk;
  return r;
}

}  // namespace magcal
