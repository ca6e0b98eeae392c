// Full nonlinear refinement of theta = [c; E] (estimation.md 2b; TWOSTEP step 2, the paper's
// Levenberg–Marquardt), with an optional outlier-resistant (Huber IRLS) weighting.
//
//   r_k(theta) = z_k - mu_k - L_k theta + |b(theta)|^2,    J = 1/2 sum w_k u_k r_k^2
//   |b(theta)|^2 = c^T (I + E)^-1 c,   x = (I + E)^-1 c   (= (I + D)^-1 b)
//   d|b|^2/dc = 2x,  d|b|^2/dE_ii = -x_i^2,  d|b|^2/dE_ij = -2 x_i x_j     (gradient g_b)
//   dr_k/dtheta = -L_k + g_b^T
//   w_k = 1/sigma_k^2 at the current estimate: |y_k|^2 = |B_k|^2 - (L_k theta - |b|^2)
//   LM step: (F + lambda diag F) dtheta = -sum w u J_k^T r_k,  F = sum w u J_k^T J_k
//   stop when dtheta^T F dtheta < tolerance (chi-square units) or after max_iterations.
//   Covariance: F^-1 (undamped, lambda = 0) with the weights at the solution (white noise),
//   and the HAC sandwich from the per-sample scores (pipeline/hac_covariance.hpp), reported.
//
// Robust mode (Huber IRLS): e_k = r_k sqrt(w_k) is the normalised residual, s = max(1, 1.4826
// median |e_k|) a robust scale (1 when the model noise explains the residuals; larger when
// unmodelled effects or a poor start dominate), u_k = min(1, huber_k s / |e_k|). Samples with
// u_k < 1 at the solution are reported as down-weighted. Without robust mode u_k = 1.
// No per-sample allocation (robust mode allocates one residual buffer per call).
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

struct LmOptions {
  double sigma_nT = 3.0;
  int max_iterations = 50;
  double tolerance = 1e-10;  // on dtheta^T F dtheta
  double initial_lambda = 1e-3;
  int max_lambda_increases = 12;  // per iteration, before giving up on improving the cost
  bool robust = false;
  double huber_k = 3.0;  // in units of the robust scale; 3: ~0.3 % of clean samples affected
  int min_samples = 10;
  // Report the HAC (Newey–West) covariance, never below the white-noise one
  // (pipeline/hac_covariance.hpp); false: the white-noise inverse information only.
  bool hac = true;
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
  int n_parameters = 9;                   // 9, or 15 with the model extension
  Vector6d extension = Vector6d::Zero();  // refine_lm_extended: the coefficients a
  Matrix6d extension_covariance = Matrix6d::Zero();  // white-noise, marginal
  int iterations = 0;                                // accepted or attempted outer iterations
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

// Refines theta0 (e.g. the centered solution, or zero). When I + E is not positive definite at
// theta0 the refinement starts from [c; 0].
LmResult refine_lm(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options = {});

// The same refinement with 6 linear model-extension columns phi_k (fixed per sample, e.g. the
// sensor nonlinearity and hysteresis terms of pipeline/model_extension.hpp):
//   r_k = z_k - mu_k - L_k theta + |b(theta)|^2 - phi_k^T a,   unknowns [theta; a], a0 = 0.
// theta_covariance(_white) are the marginal 9x9 blocks (a estimated jointly).
LmResult refine_lm_extended(const SampleSet& samples, const Vector9d& theta0,
                            const std::vector<Vector6d>& extension_regressors,
                            const LmOptions& options = {});

}  // namespace magcal
