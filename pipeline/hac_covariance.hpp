// Heteroskedasticity- and autocorrelation-consistent (HAC) covariance of an M-estimate
// (estimation.md section 7): the batch covariance derived from the residuals' actual structure
// instead of the nominal white noise.
//
//   white:    C_w   = F^-1,                  F = sum_k w_k J_k^T J_k  (9x9, undamped)
//   sandwich: C_hac = F^-1 Omega F^-1,       Omega = sum_{|l|<=L} k(l) sum_k u_k u_{k+l}^T
//             u_k = w_k r_k J_k^T (per-sample score), Bartlett kernel k(l) = 1 - |l|/(L+1)
//             (Newey & West 1987; positive semi-definite by construction).
//   reported: C = F^-1/2 max(I, F^1/2 C_hac F^1/2) F^-1/2 (eigenvalues clamped at 1): never
//             below the white-noise inverse information, so on data the model explains the
//             reported sigma stays at the CRLB (the HAC's own sampling noise cannot make it
//             over-confident), and above it whenever the residuals say the model leaves error.
//
// Lag window L from the residual autocorrelation: Andrews (1991) AR(1) plug-in for the Bartlett
// kernel, L = ceil(1.1447 (alpha n)^(1/3)), alpha = 4 rho^2 / ((1 - rho)^2 (1 + rho)^2), rho the
// lag-1 autocorrelation of the normalised residuals e_k = sqrt(w_k) r_k; L = 0 (plain
// Huber–White sandwich) when |rho| is below 3 / sqrt(n) (not distinguishable from white noise).
// Lags count samples in the caller's order (time order): unevenly spaced or gappy data are
// treated as if evenly spaced, which mis-weights correlation across a gap but never drops a
// sample; the window is capped at n / 4.
//
// Omega is computed exactly as (1/(L+1)) sum_t V_t V_t^T over the moving sums
// V_t = sum_{j = t..t+L} u_j (t = -L .. n-1, partial windows at both ends): O(n) 9x9 outer
// products for any L, instead of O(n L).
#pragma once

#include <vector>

#include <Eigen/Core>
#include <Eigen/Eigenvalues>

#include "pipeline/outer_product_sum.hpp"

namespace magcal {

// Lag-1 autocorrelation sum e_k e_{k+1} / sum e_k^2 of a (zero-mean) residual sequence; NaN
// for fewer than 3 values or all-zero residuals.
double lag1_autocorrelation(const std::vector<double>& residuals);
// The same for vector residuals (pooled over the axes): sum e_k . e_{k+1} / sum |e_k|^2.
double lag1_autocorrelation(const std::vector<Eigen::Vector3d>& residuals);

// Andrews' AR(1) plug-in Bartlett lag window for n samples with lag-1 autocorrelation rho
// (0 when |rho| < 3/sqrt(n); capped at n / 4; rho is clamped to [-0.97, 0.97]).
int bartlett_lag_window(double rho, int n);

// Omega = sum_{|l|<=L} (1 - |l|/(L+1)) sum_k u_k u_{k+l}^T for scores u (n x P, sample order).
template <int P>
Eigen::Matrix<double, P, P> newey_west_meat(const std::vector<Eigen::Matrix<double, P, 1>>& scores,
                                            int lag_window) {
  using V = Eigen::Matrix<double, P, 1>;
  const int n = static_cast<int>(scores.size());
  const int L = lag_window > 0 ? lag_window : 0;
  OuterProductSum<P> omega;
  if (L == 0) {
    for (const V& u : scores) omega.add(u);
    return omega.sum();
  }
  // Moving sum over [t, t + L], t = -L .. n - 1: add u_{t+L} entering, drop u_{t-1} leaving.
  V window = V::Zero();
  for (int t = -L; t < n; ++t) {
    if (t + L < n) window += scores[static_cast<std::size_t>(t + L)];
    if (t - 1 >= 0) window -= scores[static_cast<std::size_t>(t - 1)];
    omega.add(window);
  }
  return omega.sum() / static_cast<double>(L + 1);
}

// max(C_hac, F^-1) in the sense above, given F^-1 (symmetric positive definite) and C_hac
// (P x P). Returns the white covariance unchanged when either input is not usable.
template <int P>
Eigen::Matrix<double, P, P> covariance_not_below(
    const Eigen::Matrix<double, P, P>& white_covariance,
    const Eigen::Matrix<double, P, P>& hac_covariance) {
  using M = Eigen::Matrix<double, P, P>;
  using V = Eigen::Matrix<double, P, 1>;
  // Parameters in different units (nT and dimensionless differ by ~1e5): work on the diagonally
  // scaled matrices.
  const V d = white_covariance.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite() || !hac_covariance.allFinite()) {
    return white_covariance;
  }
  const V scale = d.cwiseSqrt();
  const V inv = scale.cwiseInverse();
  const M Cw = inv.asDiagonal() * white_covariance * inv.asDiagonal();
  const M Ch = inv.asDiagonal() * hac_covariance * inv.asDiagonal();
  // Whiten with the symmetric square root of Cw: A = Cw^-1/2 Ch Cw^-1/2, clamp A >= I.
  const Eigen::SelfAdjointEigenSolver<M> ew(Cw);
  if (!(ew.eigenvalues().minCoeff() > 0.0)) return white_covariance;
  const V root = ew.eigenvalues().cwiseSqrt();
  const M Cw_half = ew.eigenvectors() * root.asDiagonal() * ew.eigenvectors().transpose();
  const M Cw_inv_half =
      ew.eigenvectors() * root.cwiseInverse().asDiagonal() * ew.eigenvectors().transpose();
  M A = Cw_inv_half * Ch * Cw_inv_half;
  A = 0.5 * (A + A.transpose());
  const Eigen::SelfAdjointEigenSolver<M> ea(A);
  const V clamped = ea.eigenvalues().cwiseMax(1.0);
  const M Cs =
      Cw_half * ea.eigenvectors() * clamped.asDiagonal() * ea.eigenvectors().transpose() * Cw_half;
  const M C = scale.asDiagonal() * Cs * scale.asDiagonal();
  return 0.5 * (C + C.transpose());
}

// Compiled once, in hac_covariance.cpp, for the sizes the fits use: each instantiation (two
// fixed-size eigensolvers and their product chains) costs GCC about 10 s, which every includer
// would otherwise pay again (lm_refinement.cpp, which uses all three, compiles in half the time).
extern template Eigen::Matrix<double, 3, 3> covariance_not_below<3>(
    const Eigen::Matrix<double, 3, 3>&, const Eigen::Matrix<double, 3, 3>&);
extern template Eigen::Matrix<double, 6, 6> covariance_not_below<6>(
    const Eigen::Matrix<double, 6, 6>&, const Eigen::Matrix<double, 6, 6>&);
extern template Eigen::Matrix<double, 9, 9> covariance_not_below<9>(
    const Eigen::Matrix<double, 9, 9>&, const Eigen::Matrix<double, 9, 9>&);

}  // namespace magcal
