// Full nonlinear refinement of theta = [c; E] (estimation.md 2b; TWOSTEP step 2, the paper's
// Levenberg–Marquardt), with an optional outlier-resistant (Huber IRLS) weighting.
//
//   r_k(theta) = z_k - mu_k - L_k theta + |b(theta)|^2,    J = 1/2 sum w_k u_k r_k^2
//   |b(theta)|^2 = c^T (I + E)^-1 c,   x = (I + E)^-1 c   (= (I + D)^-1 b)
//   d|b|^2/dc = 2x,  d|b|^2/dE_ii = -x_i^2,  d|b|^2/dE_ij = -2 x_i x_j     (gradient g_b)
//   dr_k/dtheta = -L_k + g_b^T
//   w_k = 1/sigma_k^2, sigma_k^2 = 4 sigma^2 |R h_k|^2 + 6 sigma^4 (estimation.md 2, first
//   line: |R h_k| = |h_k| is known, so the weights do not depend on theta or on the noise)
//   Covariance: F^-1 (undamped) at the solution (white noise), and the HAC sandwich from the
//   per-sample scores (pipeline/hac_covariance.hpp), reported.
//
// With weights that do not depend on theta, the cost, F and g at any theta follow from one
// moment matrix M = sum w u v^T v of the samples (scalar_moments_cost below), so the LM
// iterations (pipeline/levenberg_marquardt.hpp, the driver the filter start uses too) cost no
// pass over the samples: one pass builds M, one more gives the residual autocorrelation and the
// HAC scores at the solution.
//
// Robust mode (Huber IRLS): e_k = r_k sqrt(w_k) is the normalised residual, s = max(1, 1.4826
// median |e_k|) a robust scale (1 when the model noise explains the residuals; larger when
// unmodelled effects or a poor start dominate), u_k = min(1, huber_k s / |e_k|), re-evaluated at
// each LM solution until the Gauss–Newton decrement with the weights of the current estimate is
// below the tolerance (the same fixed point as re-weighting after every step). Samples with
// u_k < 1 at the solution are reported as down-weighted. Without robust mode u_k = 1.
// No per-sample allocation (one residual / score buffer per call).
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "pipeline/temperature_model.hpp"

namespace magcal {

struct LmOptions {
  double sigma_nT = 3.0;
  int max_iterations = 50;
  double tolerance = 1e-10;  // on dtheta^T F dtheta and the Gauss-Newton decrement
  double initial_lambda = 1e-3;
  int max_lambda_increases = 12;  // per iteration, before giving up on improving the cost
  bool robust = false;
  double huber_k = 3.0;  // in units of the robust scale; 3: ~0.3 % of clean samples affected
  int min_samples = 10;
  // Report the HAC (Newey–West) covariance, never below the white-noise one
  // (pipeline/hac_covariance.hpp); false: the white-noise inverse information only.
  bool hac = true;
  // Also fit the bias temperature coefficient k (pipeline/temperature_model.hpp: columns
  // 2 (T - T0) y_k, y_k at temperature_linearisation) about this reference temperature T0, degC.
  bool temperature_model = false;
  double reference_temperature_C = 0.0;
  CalibrationParameters temperature_linearisation;
  std::string validate() const;  // empty when valid
};

enum class LmStatus {
  kOk = 0,                   // converged
  kNotConverged = 1,         // max_iterations reached (estimate returned)
  kNotPositiveDefinite = 2,  // I + E not PD at the start and the fallback start failed too
  kSingular = 3,             // F singular at the solution
  kTooFewSamples = 4,
  kInvalidInput = 5,  // NaN/Inf, |h| <= 0, invalid options
};
const char* to_string(LmStatus s);

struct LmResult {
  LmStatus status = LmStatus::kInvalidInput;
  std::string message;
  Vector9d theta = Vector9d::Zero();
  // The covariance we stand behind: HAC sandwich, not below F^-1 (options.hac), else F^-1.
  Matrix9d theta_covariance = Matrix9d::Zero();
  Matrix9d theta_covariance_white = Matrix9d::Zero();  // F^-1 at the solution (statistical)
  double noise_scale = 0.0;  // sqrt(chi2 / (n - 9)), chi2 = sum w u r^2 at the solution
  double residual_autocorrelation = 0.0;  // lag 1, normalised residuals, sample order
  int lag_window = 0;                     // HAC Bartlett lag window (samples)
  std::vector<double> robust_weights;     // robust mode: u_k per sample (1 = kept unchanged)
  int n_parameters = 9;  // 9, + 6 with the model extension, + 4 with the temperature model
  Vector6d extension = Vector6d::Zero();  // refine_lm_extended: the coefficients a
  // Marginal covariance of a: the HAC one not below the white-noise one (as theta_covariance).
  Matrix6d extension_covariance = Matrix6d::Zero();
  // options.temperature_model: the temperature coefficient k (nT/degC) and its marginal
  // covariance (as extension_covariance).
  Eigen::Vector3d temperature_coefficient = Eigen::Vector3d::Zero();
  Eigen::Matrix3d temperature_covariance = Eigen::Matrix3d::Zero();
  // M = sum w u v^T v of the fit's samples about theta_ref (scalar_moments_cost, 9-parameter
  // rows): without robust weights refine_lm_extended takes it instead of summing that block again.
  Eigen::Matrix<double, 11, 11> moments = Eigen::Matrix<double, 11, 11>::Zero();
  Vector9d moments_reference = Vector9d::Zero();
  int iterations = 0;  // accepted or attempted outer iterations
  bool converged = false;
  double cost = 0.0;       // J at the solution
  int n_downweighted = 0;  // robust mode: samples with u_k < 1
  double robust_scale = 1.0;
};

// |b(theta)|^2 = c^T (I + E)^-1 c and its gradient (false if I + E is singular).
bool bias_norm_squared(const Vector9d& theta, double* bsq, Vector9d* gradient);

// r_k and dr_k/dtheta for one sample (z_minus_mu = z_k - mu_k).
double lm_residual(const Vector9d& theta, const Eigen::Vector3d& b_sensor_nT, double z_minus_mu);
RowVector9d lm_residual_jacobian(const Vector9d& theta, const Eigen::Vector3d& b_sensor_nT);

// I + E(theta) is positive definite (theta maps to b, D).
bool theta_positive_definite(const Vector9d& theta);

// The weighted scalar problem with NX linear extension columns phi_k (x = [theta; a]) from its
// moments (estimation.md 2b), taken about a reference estimate x_ref (zero: the plain form):
//   v_k = [L_k (1x9), 1, rho_k, phi_k^T (1xNX)],  rho_k = r_k(x_ref)  (= z_k - mu_k at x_ref = 0)
//   r_k(x) = rho_k - L_k (theta - theta_ref) + |b(theta)|^2 - |b(theta_ref)|^2 - phi_k^T (a -
//   a_ref)
//          = v_k c(x),  c = [-(theta - theta_ref); |b|^2 - |b_ref|^2; 1; -(a - a_ref)]
//   sum w r^2 = c^T M c,   M = sum w_k v_k^T v_k   ((11 + NX) x (11 + NX), symmetric)
//   dr_k/dx = v_k G,  G = [-I_9, 0; g_b^T, 0; 0, 0; 0, -I_NX]
//   F = G^T M G (Gauss–Newton information), g = G^T M c (gradient of 1/2 sum w r^2)
// About a reference near the solution the sums do not cancel: z_k is ~|B|^2 (1e9..1e11 nT^2)
// while r_k is ~|B| sigma, so moments about zero lose the chi-square to rounding for large
// fields and biases (measured: |b| = 3 |H| never met the 1e-10 tolerance).
// cost in chi-square units (sum w r^2). False if I + E is singular.
template <int NX>
struct MomentsReference {
  Eigen::Matrix<double, 9 + NX, 1> x = Eigen::Matrix<double, 9 + NX, 1>::Zero();
  double bsq = 0.0;  // |b(theta_ref)|^2
};

template <int NX>
bool scalar_moments_cost(const Eigen::Matrix<double, 11 + NX, 11 + NX>& M,
                         const Eigen::Matrix<double, 9 + NX, 1>& x, double* cost,
                         Eigen::Matrix<double, 9 + NX, 9 + NX>* F,
                         Eigen::Matrix<double, 9 + NX, 1>* g,
                         const MomentsReference<NX>& ref = {}) {
  constexpr int N = 11 + NX;
  constexpr int P = 9 + NX;
  double bsq = 0.0;
  Vector9d gb;
  const Vector9d theta = x.template head<9>();
  if (!bias_norm_squared(theta, &bsq, &gb)) return false;
  Eigen::Matrix<double, N, 1> c;
  c.template head<9>() = ref.x.template head<9>() - theta;
  c(9) = bsq - ref.bsq;
  c(10) = 1.0;
  if constexpr (NX > 0) c.template tail<NX>() = ref.x.template tail<NX>() - x.template tail<NX>();
  const Eigen::Matrix<double, N, 1> Mc = M * c;
  if (cost) *cost = c.dot(Mc);
  if (g) {
    g->template head<9>() = -Mc.template head<9>() + Mc(9) * gb;
    if constexpr (NX > 0) g->template tail<NX>() = -Mc.template tail<NX>();
  }
  if (F) {
    Eigen::Matrix<double, N, P> MG;  // M G, column by column of G
    MG.template leftCols<9>() = -M.template leftCols<9>() + M.col(9) * gb.transpose();
    if constexpr (NX > 0) MG.template rightCols<NX>() = -M.template rightCols<NX>();
    F->template topRows<9>() = -MG.template topRows<9>() + gb * MG.row(9);
    if constexpr (NX > 0) F->template bottomRows<NX>() = -MG.template bottomRows<NX>();
  }
  return true;
}

// Refines theta0 (e.g. the centered solution, or zero). When I + E is not positive definite at
// theta0 the refinement starts from [c; 0]. options.temperature_model: with the 3 temperature
// columns (r_k gains - phi_k^T k as below, phi_k = temperature_columns_at()).
// base: as for refine_lm_extended (only used with the temperature columns).
LmResult refine_lm(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options = {},
                   const LmResult* base = nullptr);

// The same refinement with 6 linear model-extension columns phi_k (fixed per sample, e.g. the
// sensor nonlinearity and hysteresis terms of pipeline/model_extension.hpp), and the temperature
// columns after them when options.temperature_model:
//   r_k = z_k - mu_k - L_k theta + |b(theta)|^2 - phi_k^T a,   unknowns [theta; a], a0 = 0.
// theta_covariance(_white) are the marginal 9x9 blocks (a estimated jointly).
// base: a non-robust refine_lm on the same samples and sigma (or nullptr), whose moments are
// reused.
LmResult refine_lm_extended(const SampleSet& samples, const Vector9d& theta0,
                            const std::vector<Vector6d>& extension_regressors,
                            const LmOptions& options = {}, const LmResult* base = nullptr);

}  // namespace magcal
