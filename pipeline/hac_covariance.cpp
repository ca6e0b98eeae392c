#include "pipeline/hac_covariance.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Dense>

namespace magcal {

double lag1_autocorrelation(const std::vector<double>& residuals) {
  if (residuals.size() < 3) return std::numeric_limits<double>::quiet_NaN();
  double num = 0.0, den = 0.0;
  for (std::size_t k = 0; k < residuals.size(); ++k) {
    den += residuals[k] * residuals[k];
    if (k + 1 < residuals.size()) num += residuals[k] * residuals[k + 1];
  }
  if (!(den > 0.0)) return std::numeric_limits<double>::quiet_NaN();
  return num / den;
}

int bartlett_lag_window(double rho, int n) {
  if (n < 4 || !std::isfinite(rho)) return 0;
  if (std::abs(rho) < 3.0 / std::sqrt(static_cast<double>(n))) return 0;
  const double r = std::clamp(rho, -0.97, 0.97);
  const double alpha = 4.0 * r * r / ((1.0 - r) * (1.0 - r) * (1.0 + r) * (1.0 + r));
  const double lag = std::ceil(1.1447 * std::cbrt(alpha * n));
  return static_cast<int>(std::min(lag, static_cast<double>(n / 4)));
}

Matrix9d covariance_not_below(const Matrix9d& white_covariance, const Matrix9d& hac_covariance) {
  // nT and dimensionless parameters differ by ~1e5: work on the diagonally scaled matrices.
  const Vector9d d = white_covariance.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite() || !hac_covariance.allFinite()) {
    return white_covariance;
  }
  const Vector9d scale = d.cwiseSqrt();
  const Vector9d inv = scale.cwiseInverse();
  const Matrix9d Cw = inv.asDiagonal() * white_covariance * inv.asDiagonal();
  const Matrix9d Ch = inv.asDiagonal() * hac_covariance * inv.asDiagonal();
  // Whiten with the symmetric square root of Cw: A = Cw^-1/2 Ch Cw^-1/2, clamp A >= I.
  const Eigen::SelfAdjointEigenSolver<Matrix9d> ew(Cw);
  if (!(ew.eigenvalues().minCoeff() > 0.0)) return white_covariance;
  const Vector9d root = ew.eigenvalues().cwiseSqrt();
  const Matrix9d Cw_half = ew.eigenvectors() * root.asDiagonal() * ew.eigenvectors().transpose();
  const Matrix9d Cw_inv_half =
      ew.eigenvectors() * root.cwiseInverse().asDiagonal() * ew.eigenvectors().transpose();
  Matrix9d A = Cw_inv_half * Ch * Cw_inv_half;
  A = 0.5 * (A + A.transpose());
  const Eigen::SelfAdjointEigenSolver<Matrix9d> ea(A);
  const Vector9d clamped = ea.eigenvalues().cwiseMax(1.0);
  const Matrix9d Cs =
      Cw_half * ea.eigenvectors() * clamped.asDiagonal() * ea.eigenvectors().transpose() * Cw_half;
  Matrix9d C = scale.asDiagonal() * Cs * scale.asDiagonal();
  return 0.5 * (C + C.transpose());
}

}  // namespace magcal
