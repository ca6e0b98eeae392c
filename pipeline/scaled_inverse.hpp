// Inverse of a symmetric positive semi-definite information matrix in the diagonally scaled form
// S^-1 F S^-1 (S = sqrt(diag F)): its parameters mix units (b in nT, D unitless, the extension's
// 1/nT) whose information differs by ten orders of magnitude, so an unscaled inverse or condition
// number says more about the units than the geometry.
#pragma once

#include <limits>

#include <Eigen/Core>
#include <Eigen/Eigenvalues>

namespace magcal {

// F's inverse (when `inverse` is not null) and its scaled condition number (when `condition` is
// not null: infinity for a non-positive diagonal). False when the smallest scaled eigenvalue is not
// above singular_ratio times the largest (F singular for these purposes).
template <int N>
bool scaled_inverse(const Eigen::Matrix<double, N, N>& F, Eigen::Matrix<double, N, N>* inverse,
                    double* condition, double singular_ratio = 1e-14) {
  using Vec = Eigen::Matrix<double, N, 1>;
  using Mat = Eigen::Matrix<double, N, N>;
  const Vec d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) {
    if (condition) *condition = std::numeric_limits<double>::infinity();
    return false;
  }
  const Vec s_inv = d.cwiseSqrt().cwiseInverse();
  const Mat Fs = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Mat> eig(Fs);
  const double lmin = eig.eigenvalues()(0), lmax = eig.eigenvalues()(N - 1);
  const bool ok = lmin > singular_ratio * lmax;
  if (condition) *condition = lmin > 0.0 ? lmax / lmin : std::numeric_limits<double>::infinity();
  if (!ok) return false;
  if (inverse) {
    *inverse = s_inv.asDiagonal() * eig.eigenvectors() *
               eig.eigenvalues().cwiseInverse().asDiagonal() * eig.eigenvectors().transpose() *
               s_inv.asDiagonal();
  }
  return true;
}

}  // namespace magcal
