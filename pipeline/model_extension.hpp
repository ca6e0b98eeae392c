// Sensor-model extension for the batch refit (estimation.md section 7): the effects a
// real AMR / fluxgate magnetometer has beyond b and D, as linear columns of the scalar model.
//
// Truth (estimation.md section 5): (I + D) B - b = x + n(x) + eps with, per axis i,
//   n_i = k_i x_i^2                    (nonlinearity; the paper sensor's is even in the field)
//       + eta_i s_i                    (hysteresis, s_i = +-1 the sign of the last change of x_i)
// With y = (I + D) B - b ≈ x, |h|^2 = |x|^2 ≈ |y|^2 - 2 y^T n(y), so the scalar measurement gains
//   z_k = L_k theta - |b|^2 + phi_k^T a,   phi_k = [2 y_i^3 (i = 1..3); 2 y_i s_i (i = 1..3)],
//   a = [k_1 k_2 k_3 (1/nT); eta_1 eta_2 eta_3 (nT)],
// linear in a with phi_k fixed by y from a 9-parameter solution (the second-order terms left out
// are of order k x^2 (D x + b) / |x|, ~0.1 nT by that estimate on the paper scenario). s_i is
// the sign of the last change of x_i in sample order, as the truth model defines it, estimated
// from the noisy y_i: the runs between its turning points, a turning point counting once y_i has
// moved 4 noise sigmas back from the run's extreme (a deadband), and placed by a fit of a
// parabola plus the hysteresis step to the samples within 16 sigmas of that extreme (the samples
// there get their expected sign under that fit). The sign of each sample-to-sample difference
// y_i(k) - y_i(k-1) it replaces flips with the noise near every turning point of a slowly
// varying axis; on a spinning craft those flips lock to the spin phase and bias the other axes'
// b (tumbling scenario spinning at 3 deg/s about body z, 1 s samples, 30 x 3 h: bias
// RMS(error/sigma) (2.66, 2.50, 0.98) with the sample differences; signs wrong on 2.5 % of the
// spin axis's samples, 0.2 % now). Like every lag here it assumes
// time order, and across a gap it joins the runs on both sides. An odd cubic term k3 x_i^3 was
// measured in its place (with the same hysteresis columns): paper scenario, 20 x
// 12 h, bias MSE 3.7 nT^2 with the cubic vs 1.15 nT^2 with this quadratic term (the truth
// nonlinearity is even).
//
// The extension is used only when the Bayesian information criterion prefers it:
//   n ln(chi2_9 / chi2_15) > 6 ln n   (chi2 = sum w r^2 at each solution),
// so on data the 9-parameter model explains (white noise) it stays off.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

// What the extension terms are built from, one entry per sample (sample order): the calibrated
// vectors y_k = p.apply(B_k) (sensor frame, nT) and their hysteresis signs s_k (+-1 per axis: the
// direction of the run between turning points the sample belongs to, see above; sigma_nT the
// nominal per-axis noise the turning-point deadband is set from; +1 when an axis never moves
// more than the deadband).
struct ExtensionInputs {
  std::vector<Eigen::Vector3d> y_nT;
  std::vector<Eigen::Vector3d> signs;
};
ExtensionInputs extension_inputs(const SampleSet& samples, const CalibrationParameters& p,
                                 double sigma_nT);

// phi_k for every sample, from the inputs of the 9-parameter estimate.
std::vector<Vector6d> model_extension_regressors(const ExtensionInputs& in);

// Calibrated vectors with a fitted extension removed, x_k = y_k - n(y_k) (the inverse of the model
// above to first order), n_i = k_i y_i^2 + eta_i s_i; sensor frame, nT, sample order (k_per_nT:
// CalibrationResult::nonlinearity_k3, eta_nT: hysteresis_nT).
std::vector<Eigen::Vector3d> extension_corrected_vectors(const ExtensionInputs& in,
                                                         const Eigen::Vector3d& k_per_nT,
                                                         const Eigen::Vector3d& eta_nT);

// BIC prefers a model with n_extra_parameters more (chi-square chi2_more) to the base one:
//   n ln(chi2_base / chi2_more) > n_extra_parameters ln n.
bool bic_prefers_more_parameters(double chi2_base, double chi2_more, int n_samples,
                                 int n_extra_parameters);
// BIC prefers the 6 extra parameters when this is true.
bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples);

// The effects a = [k (1/nT); eta (nT)] describes are small sensor effects: per axis |k_i| |h|^2
// and |eta_i| within 1 % of the mean |h| (mean_h_nT). Paper sensor, 3-12 h windows: at most
// 0.44 %; the ISS Astro Pi halves, where the "nonlinearity" soaks up 500-8 700 nT of what the
// station does to the field: 1.4-25 %. Beyond it the extension is not a sensor effect and is
// not used. max_fraction: the limit (default 1 %).
bool extension_effects_small(const Vector6d& a, double mean_h_nT, double max_fraction = 0.01);

// The extension fitted with b, D held at the estimate the inputs were computed from (linear
// least squares, estimation.md section 7): for the alignment of an estimate that did not fit it
// jointly (the centered solution, the online filters), whose calibrated vectors still carry the
// hysteresis lag (a rotation about the orbit normal, to first order).
//   r_k = |y_k|^2 - |h_k|^2 - mu = phi_k^T a + v_k,  w_k = 1 / sigma_k^2  (scalar_measurement.hpp)
//   a = (sum w phi phi^T)^-1 sum w phi r,  covariance: the HAC sandwich not below the white
//   inverse information (hac_covariance.hpp), as the joint fit's.
// `used` is true when BIC prefers a over a = 0 and extension_effects_small(a) holds; a and its
// covariance are then what extension_corrected_vectors() and alignment_covariance_from_stage1()
// take. Shapes: in and samples one entry per sample, same order; sigma_nT per-axis noise.
struct ExtensionFitAtEstimate {
  bool used = false;
  bool supported = false;  // BIC prefers a over a = 0, whatever the size of its effects
  Vector6d a = Vector6d::Zero();
  Matrix6d covariance = Matrix6d::Zero();
};
ExtensionFitAtEstimate fit_extension_at_estimate(const SampleSet& samples,
                                                 const ExtensionInputs& in, double sigma_nT);

}  // namespace magcal
