#include "pipeline/ellipsoid_fit.hpp"

#include <cmath>

#include <Eigen/Dense>

namespace magcal {

bool ellipsoid_fit_start(const SampleSet& samples, Vector9d* theta) {
  using Vector10d = Eigen::Matrix<double, 10, 1>;
  using Matrix10d = Eigen::Matrix<double, 10, 10>;
  if (samples.size() < 10) return false;
  double sum_b2 = 0.0, sum_h2 = 0.0;
  for (const CalibrationSample& s : samples) {
    sum_b2 += s.b_sensor_nT.squaredNorm();
    sum_h2 += s.h_body_nT.squaredNorm();
  }
  const double n = static_cast<double>(samples.size());
  const double scale = std::sqrt(sum_b2 / n);
  const double H2 = sum_h2 / n;
  if (!(scale > 0.0) || !(H2 > 0.0) || !std::isfinite(scale) || !std::isfinite(H2)) return false;

  Matrix10d M = Matrix10d::Zero();
  for (const CalibrationSample& s : samples) {
    const Eigen::Vector3d B = s.b_sensor_nT / scale;
    Vector10d phi;
    phi << B(0) * B(0), B(1) * B(1), B(2) * B(2), 2 * B(0) * B(1), 2 * B(0) * B(2), 2 * B(1) * B(2),
        -2 * B(0), -2 * B(1), -2 * B(2), 1.0;
    M.noalias() += phi * phi.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Matrix10d> eig(M);
  if (eig.info() != Eigen::Success) return false;
  const Vector10d q = eig.eigenvectors().col(0);
  Eigen::Matrix3d A = unpack_symmetric(q.head<6>());  // in scaled units
  const Eigen::Vector3d a = q.segment<3>(6);
  const double alpha = q(9);
  const Eigen::LDLT<Eigen::Matrix3d> ldlt(A);
  if (ldlt.info() != Eigen::Success) return false;
  const Eigen::Vector3d v = ldlt.solve(a);  // centre (scaled units)
  const double kappa = v.dot(A * v) - alpha;
  if (!std::isfinite(kappa) || kappa == 0.0) return false;
  A /= kappa;  // (B - v)^T A (B - v) = 1; A must now be positive definite
  const Eigen::Vector3d ev =
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(A, Eigen::EigenvaluesOnly).eigenvalues();
  if (!(ev.minCoeff() > 0.0)) return false;
  // Back to nT: B = scale B~, so (B - scale v)^T (A / scale^2) (B - scale v) = 1.
  const Eigen::Matrix3d I_E = (H2 / (scale * scale)) * A;
  const Eigen::Vector3d c = I_E * (scale * v);
  theta->head<3>() = c;
  theta->tail<6>() = pack_symmetric(I_E - Eigen::Matrix3d::Identity());
  return theta->allFinite();
}

}  // namespace magcal
