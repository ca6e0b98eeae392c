// Starting an online filter from data (estimation.md section 7, "start from data, not from
// zero"): the whole weighted nonlinear least-squares problem of stage 1 is determined by a
// fixed-size moment matrix, so a filter can collect it per sample (no allocation, ~1 KB with the
// lag-1 products) and solve the batch problem (linear start -> Gauss-Newton/LM) once the data
// observe the parameters.
//
// With weights fixed from the measured field, w_k = 1 / (4 sigma^2 |B_k|^2 + 6 sigma^4)
// (scalar_measurement.hpp with y = B), and v_k = [L_k (1x9), 1, y_k], y_k = z_k - mu:
//   r_k(theta) = y_k - L_k theta + |b(theta)|^2 = v_k c(theta),  c = [-theta; |b(theta)|^2; 1]
//   sum w_k r_k^2 = c^T M c,  M = sum w_k v_k^T v_k                 (11x11, symmetric)
//   dr_k/dtheta = v_k G,  G = [-I_9; g_b^T; 0]  (g_b = d|b|^2/dtheta, lm_refinement.hpp)
//   Gauss-Newton information G^T M G, gradient G^T M c                 (estimation.md 2b)
// The lag-1 products sum sqrt(w_k w_{k-1}) r_k r_{k-1} = c^T M1 c (M1 = symmetrised
// sum sqrt(w_k w_{k-1}) v_k^T v_{k-1}) give the residuals' lag-1 autocorrelation at the
// solution without storing residuals.
//
// Start candidates: the linear solution of y = [L, -1][theta; |b|^2] (the centered solution of
// estimation.md 2a, solved from the moments); when the reference magnitude is (nearly)
// constant that system is degenerate along one direction (estimation.md 7: E = -I, c = 0 fits
// exactly), and the point on that line where the intercept equals |b(theta)|^2 is taken instead
// (an algebraic ellipsoid fit); and theta = 0. Each is refined by LM on the moments; the lowest
// cost wins. Then b, D and the covariance come from parameter_recovery.hpp.
#pragma once

#include <cstdint>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "pipeline/packed_triangle.hpp"

namespace magcal {

using Vector11d = Eigen::Matrix<double, 11, 1>;
using Matrix11d = Eigen::Matrix<double, 11, 11>;
using PackedSymmetric11 = PackedTriangle<11>;

// The lag-1 products of the moments (file comment): the start's residual correlation needs them,
// nothing after it (a started filter drops them). Plain data, serialisable.
struct ScalarLag1Moments {
  PackedSymmetric11 m = PackedSymmetric11::Zero();  // symmetrised sum sqrt(w w') v^T v'
  Vector11d previous = Vector11d::Zero();           // sqrt(w) v of the previous sample
  Matrix11d matrix() const;
  bool operator==(const ScalarLag1Moments& o) const;
};

// Moments of the scalar problem (see the file comment). Plain data, serialisable.
struct ScalarMoments {
  PackedSymmetric11 m = PackedSymmetric11::Zero();  // sum w v^T v
  int64_t n = 0;                                    // samples added

  // Adds one sample: B sensor frame (nT), y = z - mu (nT^2), w its weight (1/nT^4); with lag1,
  // also its lag-1 products with the previous sample added.
  void add(const Eigen::Vector3d& b_sensor_nT, double y_nT2, double weight,
           ScalarLag1Moments* lag1 = nullptr);
  Matrix11d matrix() const;
  bool operator==(const ScalarMoments& o) const;
};

// sum w r^2 (chi-square units), G^T M G and G^T M c at theta. False if I + E is singular.
bool moments_cost(const Matrix11d& M, const Vector9d& theta, double* cost, Matrix9d* info_theta,
                  Vector9d* gradient);

// Scaled condition number (estimation.md 2d) of the information in p = [b; D] at parameters p
// implied by the moments: J^T (G^T M G) J, J = dtheta/dp. +inf when singular.
double moments_fisher_condition(const Matrix11d& M, const Vector9d& p);

struct FilterStartOptions {
  int min_samples = 60;          // at least this many samples before a start is tried
  double max_condition = 1e4;    // scaled Fisher condition (the observability gate's default)
  double max_correlation = 0.9;  // cap on the lag-1 autocorrelation used for the inflation
  bool correlation_inflation = true;
  // A filter runs a start attempt only when start_precheck_condition() <= precheck_margin x
  // max_condition (filter_common.hpp has the schedule). The margin covers the measured ratio
  // of the pre-check figure to the start's own condition at the first possible start (<= 25).
  double precheck_margin = 100.0;
};

enum class FilterStartStatus : int8_t {
  kOk = 0,
  kTooFewSamples = 1,
  kNoSolution = 2,    // no candidate converged to I + E positive definite
  kUnobservable = 3,  // solution found but the Fisher condition is above max_condition
};

struct FilterStartResult {
  FilterStartStatus status = FilterStartStatus::kTooFewSamples;
  Vector9d p = Vector9d::Zero();  // [b; D packed]
  // Covariance of p: inverse information x max(1, noise_scale^2) x correlation inflation.
  Matrix9d covariance = Matrix9d::Zero();
  double noise_scale2 = 1.0;              // chi2 / (n - 9): (effective noise / sigma)^2, >= 1
  double residual_autocorrelation = 0.0;  // lag-1, of the weighted residuals
  double inflation = 1.0;                 // (1 + rho) / (1 - rho), rho clipped to [0, max]
  double fisher_condition = 0.0;          // +inf when there is no solution (kNoSolution)
  int iterations = 0;
};

// Solves the batch problem from the moments (lag1: their lag-1 products, collected alongside).
// Does not allocate.
FilterStartResult solve_filter_start(const ScalarMoments& moments, const ScalarLag1Moments& lag1,
                                     const FilterStartOptions& options = {});

// Cheap observability pre-check before a start attempt (one 10x10 eigenvalue solve, ~3 us; an
// attempt on data that do not observe p runs LM to its iteration limit, 0.5-5 ms measured):
// the scaled condition of the linear start's information A (the leading 10x10 block of M, in
// u = [theta; |b|^2]) taken against its SECOND-smallest eigenvalue, lambda_max / lambda_2.
// Why the second: at any theta the Gauss-Newton information is T^T A T with T = [-I_9; g_b^T],
// a 9-dimensional subspace of R^10 that a 2-dimensional near-null space of A always meets, so
// two small eigenvalues mean no theta is observed; one alone is the constant-|h| degeneracy
// (file comment) that the constraint |b|^2 = u_10 resolves. A heuristic, not a bound: measured
// at the first successful start, this figure / the start's Fisher condition is 0.3-2 for
// |b| << |h| (paper, pure, ingest-bench data) and up to ~25 for |b| = 3 |h| (constant or
// varying |h|, |D_ij| up to 0.3). +inf when A has a non-positive diagonal element.
double start_precheck_condition(const ScalarMoments& moments);

}  // namespace magcal
