// The batch refit pipeline used by `magcal fit` (centered/twostep), `magcal refit`, the daemon's
// scheduled refits and the nightly fleet refit:
//
//   validate input (count, NaN/Inf, zero vectors, |B| within a sensor's range, |h| > 0,
//   direction coverage)
//   -> stage-1 solve: centered solution (estimation.md 2a, weights from B_k), [twostep]
//      Levenberg–Marquardt refinement (2b; from an algebraic ellipsoid fit when the centered
//      solution is degenerate), HAC covariance
//   -> [twostep] model choice by BIC: the sensor-model extension (estimation.md section 7)
//   -> model choice by BIC: the bias temperature coefficient (pipeline/temperature_model.hpp),
//      where the samples carry temperatures; every later stage sees the samples with the
//      temperature term removed
//   -> recovery of b, D and their covariance (2c)
//   -> [twostep] estimator bias: where noise is large against the coverage, a parametric
//      bootstrap measures the bias of this estimator and removes it (see below)
//   -> residual evidence: rms of |B_cal| - |h|, B_cal = (I + D) B - b (|R^T v| = |v|), outliers,
//      scaled Fisher condition number at the estimate (2d): unobservable above a limit
//   -> stage 2 alignment, Procrustes, on samples with has_reference_direction (section 4)
//   -> acceptance gates (pipeline/acceptance_gates.hpp) -> verdict
//   (robust: a Huber IRLS refinement finds the outliers, then all of it again without them;
//   zero field vectors, a sensor's dropouts, are left out first)
//
// Estimator bias. The scalar measurement regresses on the noisy B (errors in variables), and the
// map from theta to b, D is curved: the least-squares optimum is biased by O(sigma^2), in units
// of its own sigma by O(sigma x curvature / coverage). Negligible at a few nT; with 150 nT noise
// and a sensor tilted only +-45 deg it put b_z 5-6 sigma off. A parametric bootstrap (refits of
// data simulated from the estimate with the residuals' noise) measures that bias for exactly the
// estimator that runs (start, refinement, recovery), where a second-order formula would need each
// of those terms derived and kept in step with the code. It runs only where the noise exceeds
// 0.1 % of |h| and a scale factor's sigma 1e-4 (bench captures with tens to hundreds of nT of
// noise), so the paper scenario's and well-covered refits pay nothing. The bootstrap's scatter
// and its finite replicate count join the covariance.
//
// Never returns a silent garbage estimate: too few samples / NaN / not PD -> kFailed,
// geometry that does not determine the parameters -> kUnobservable, with a message.
// Allocation-light: the estimators run on the caller's sample vector; only the alignment pairs
// (and the robust residual buffer) are allocated once per call.
#pragma once

#include <string>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

struct BatchCalibrationOptions {
  enum class Method { kCentered, kTwoStep };  // "centered" | "twostep" (centered + LM)
  Method method = Method::kTwoStep;
  double sigma_nT = 3.0;  // magnetometer white noise per axis (weights, covariance)
  // A Huber IRLS refinement (robust scale) finds the outliers (residual more than 5 robust
  // sigmas from the median; gross spikes screened first on |B| - |h|); the result is the
  // ordinary fit of `method` on the samples left (n_downweighted: how many were left out;
  // residual_rms_all_nT: over all samples).
  bool robust = false;
  double huber_k = 3.0;
  int max_iterations = 50;   // LM
  double tolerance = 1e-10;  // LM stop on dtheta^T F dtheta
  int min_samples = 20;
  // twostep: also fit the sensor-model extension (per-axis nonlinearity and hysteresis,
  // pipeline/model_extension.hpp) and keep it when BIC prefers it (off on white-noise data).
  bool model_extension = true;
  // Also fit the bias temperature coefficient k_T (pipeline/temperature_model.hpp) jointly with
  // b and D and keep it when BIC prefers it, where enough samples carry a temperature with a
  // usable spread. When only some do, a result with the model rests on those alone (n_samples
  // and the window count them); without it, on all samples.
  bool temperature_model = true;
  // twostep: also fit a linear bias rate (pipeline/temperature_model.hpp: time as the covariate)
  // and keep it when BIC prefers it, on windows of at least kMinBiasRateWindow_h (beside a
  // temperature model taken: on the samples moved to T0). The published bias is then that at the
  // window's end.
  bool bias_rate_model = true;
  // twostep: on windows of at least kMinBiasRateWindow_h, measure how far the bias moves about its
  // window average (pipeline/bias_variability.hpp) and add that variance to the covariance.
  bool bias_variability = true;
  // twostep, where too few samples carry a temperature (too_few_temperatures(): none, or a sparse
  // housekeeping rate), on windows of at least one orbit: the
  // variance an orbit-synchronous bias swing leaves between the published and the current bias
  // (pipeline/orbit_synchronous_bias.hpp), where it exceeds the blocks' measure above, into the
  // covariance and bias_variability_nT2.
  bool orbit_synchronous_swing = true;
  // Hard geometry limits (beyond them no estimate is reported: kUnobservable). The acceptance
  // gates have their own, stricter, thresholds for "computed but not trusted".
  double min_coverage_eigenvalue = 1e-4;  // smallest eigenvalue of mean(d d^T), d = B/|B|
  double max_fisher_condition = 1e10;     // scaled Fisher matrix at the estimate
  bool alignment = true;                  // stage 2 when reference directions are available
  int min_alignment_samples = 10;
  bool estimate_attitude_lag = false;  // fit the attitude-magnetometer lag with the rotation
  bool gates = true;                   // apply the acceptance gates
  // twostep: remove the estimator's bias measured by a parametric bootstrap where it can matter
  // (header comment); bootstrap_replicates refits when it runs.
  bool bias_correction = true;
  int bootstrap_replicates = 32;
  // |B| beyond this is no measurement of any magnetometer (wide-range AMR/Hall parts measure up
  // to +-16 G = 1.6e6 nT): a wrapped signed count or a wrong unit, refused naming the magnitude.
  double max_field_nT = 2e6;
  GateOptions gate_options;

  std::string validate() const;  // empty when valid
};

// Why one sample cannot enter a fit, or "" when it can: non-finite values, a zero field vector
// (a sensor dropout), |B| beyond max_field_nT, a zero reference. Shared by every estimator's
// input check.
std::string sample_input_problem(const CalibrationSample& s, double max_field_nT);
bool is_zero_field_vector(const CalibrationSample& s);

const char* to_string(BatchCalibrationOptions::Method m);  // "centered", "twostep"
// Parses "centered" / "twostep"; false for anything else.
bool parse_batch_method(const std::string& name, BatchCalibrationOptions::Method* m);

// previous_accepted: last accepted result of the same spacecraft (change gate), may be null.
// window times are taken from the samples' utimes (min/max); utime = window end.
CalibrationResult calibrate_batch(const SampleSet& samples, const BatchCalibrationOptions& options,
                                  const CalibrationResult* previous_accepted = nullptr);

// Stage 2 (estimation.md section 4) for a result whose parameters and covariance are set (a
// batch refit, a filter snapshot): Procrustes on the samples with a reference direction, from
// the calibrated vectors with the sensor-model extension removed (the result's own when it has
// one, else that of `refit` (a batch refit of the same samples, e.g. for a filter's estimate),
// else one fitted at its b, D when BIC supports it: fit_extension_at_estimate), angle covariance
// from the residuals' structure plus the stage-1 error propagated
// (alignment_covariance_from_stage1). Sets r->has_alignment and r->alignment; leaves r unchanged
// when fewer than min_alignment_samples carry a direction or Procrustes fails. The joint fit's
// extension is the better one: at a 9-parameter b, D part of the hysteresis is already absorbed
// (tumbling, 24 h: fitted amplitude 7 nT against 10 in truth, yaw 20 arcsec off; joint: 0.5).
// The rotation then checks itself (pipeline/alignment_check.hpp: r->alignment.inconsistency,
// the attitude lag), with the lag fitted jointly when estimate_attitude_lag.
void estimate_alignment(const SampleSet& samples, double sigma_nT, int min_alignment_samples,
                        CalibrationResult* r, const CalibrationResult* refit = nullptr,
                        bool estimate_attitude_lag = false);

}  // namespace magcal
