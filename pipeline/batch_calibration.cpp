#include "pipeline/batch_calibration.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <optional>
#include <random>
#include <tuple>
#include <utility>
#include <vector>

#include <Eigen/Eigenvalues>

#include "pipeline/alignment.hpp"
#include "pipeline/alignment_check.hpp"
#include "pipeline/bias_variability.hpp"
#include "pipeline/centered_solution.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/ellipsoid_fit.hpp"
#include "pipeline/lm_refinement.hpp"
#include "pipeline/model_extension.hpp"
#include "pipeline/orbit_synchronous_bias.hpp"
#include "pipeline/parameter_recovery.hpp"
#include "pipeline/temperature_model.hpp"

namespace magcal {

// See the model-extension decision in calibrate_batch_core().
constexpr double kMaxExtensionResidualRatio = 2.0;
// A refused extension's disagreement with the 9-parameter fit joins the covariance when its
// effects are of a sensor's size (per axis within 2.5 % of |h|): paper scenario, 3 h windows the
// extension is refused on, 1.0-1.6 %. Beyond it the "extension" soaks up what is no sensor
// effect and says nothing about the 9-parameter fit's error (ISS Astro Pi: 3.7-220 %; with the
// term its bias sigma went from (300, 600, 220) to (1330, 6360, 1290) nT).
constexpr double kMaxAmbiguityEffectFraction = 0.025;
// Robust fits: a sample whose residual | |B_cal| - |h| | lies more than this many robust sigmas
// (1.4826 x the median absolute deviation) from the median is an outlier and is left out of the
// final fit. For Gaussian noise 5 sigmas leave out 6e-7 of clean samples; the spike recordings
// robust mode exists for have outliers of 10^2-10^4 sigmas.
constexpr double kOutlierRobustSigmas = 5.0;
// A least-squares fit with a residual beyond this many robust sigmas (as above) is refused: one
// spike of 2 000-10 000 nT in 4 h of paper data moved the bias by up to 35 nT (3.9 sigma) and the
// angles by 5 sigma while the residual RMS stayed within its gate (trial). Clean data, 10 seeds
// each of 3, 12 and 24 h: the largest residual is 3.5 (paper), 3.2 (tumbling), 4.7 (pure model,
// Gaussian) robust sigmas.
constexpr double kOutlierGateRobustSigmas = 10.0;
// Robust fits leave out samples with |B| beyond the sensor range (a spike, one wrapped count)
// while they are at most this share of the window; more is a systematic fault (negative counts
// read as unsigned wrap every sample with a negative axis, a wrong unit wraps all of them), and
// a fit of the rest would rest on a biased subset: refused, naming the magnitude.
constexpr double kMaxLeftOutBeyondRangeFraction = 0.01;
// Where the fit's own residuals show no outlier (a spike large enough to wreck the fit makes
// every residual large), the raw residuals |B| - |h| are screened: a sample beyond
// kOutlierGateRobustSigmas robust sigmas of their median and beyond this share of the mean |h|
// from it is a spike no sensor error explains (a 30 % scale error moves |B| by 30 % of |h|, and
// it moves every sample).
constexpr double kRawSpikeFractionOfField = 0.5;
// The estimator-bias bootstrap (correct_estimator_bias()) runs where the noise (residual rms) is
// above kBootstrapNoiseFraction of |h| and a scale factor's sigma above kBootstrapScaleSigma: the
// O(sigma^2) terms are then a sizeable part of a sigma on weak coverage (bench, 150 nT, tilt
// +-45 deg: 3e-3 and 2.2e-3, bias 2-2.5 sigma; at 30 nT, 6e-4, the uncorrected fit covers). The
// paper scenario (2e-4 of |h|, sigma(D) 3e-4 on 12 h, 3e-3 on 3 h) and well-covered captures
// (sigma(D) 5e-5 tumbled or turned over at 30 nT) never pay for it.
constexpr double kBootstrapNoiseFraction = 1e-3;
constexpr double kBootstrapScaleSigma = 1e-4;
// A window whose median |B| is beyond this factor of the reference field's median |h| (either
// way) is in another unit (uT, G, mG, raw counts), wrapped on many samples (negative counts of a
// 16-bit sensor read as unsigned: +65536 LSB) or fitted against the wrong reference. No
// calibration error a gate accepts comes near a factor of 5 (scale factors within 0.3; even a
// hard-iron bias of 2/3 of |h| leaves the median near 1), and a fit of such data fails every
// bound at once without naming the cause.
constexpr double kMaxFieldMagnitudeRatio = 5.0;

bool is_zero_field_vector(const CalibrationSample& s) {
  return s.b_sensor_nT.squaredNorm() == 0.0 && s.h_body_nT.allFinite();
}

bool beyond_sensor_range(const CalibrationSample& s, double max_field_nT) {
  return s.b_sensor_nT.allFinite() && s.b_sensor_nT.norm() > max_field_nT;
}

std::string sample_input_problem(const CalibrationSample& s, double max_field_nT) {
  if (!s.b_sensor_nT.allFinite() || !s.h_body_nT.allFinite()) {
    return "non-finite measured/reference field (NaN/Inf in input)";
  }
  if (s.b_sensor_nT.squaredNorm() == 0.0) return "zero field vector (sensor dropout)";
  const double b = s.b_sensor_nT.norm();
  if (b > max_field_nT) {
    char buf[160];
    std::snprintf(buf, sizeof buf,
                  "|B| %.2g nT: beyond the sensor range (wrapped or wrong unit?; no magnetometer "
                  "measures beyond %.2g nT)",
                  b, max_field_nT);
    return buf;
  }
  if (!(s.h_body_nT.norm() > 0.0)) return "zero reference field";
  return {};
}

const char* to_string(BatchCalibrationOptions::Method m) {
  return m == BatchCalibrationOptions::Method::kCentered ? "centered" : "twostep";
}

bool parse_batch_method(const std::string& name, BatchCalibrationOptions::Method* m) {
  if (name == "centered") {
    *m = BatchCalibrationOptions::Method::kCentered;
  } else if (name == "twostep") {
    *m = BatchCalibrationOptions::Method::kTwoStep;
  } else {
    return false;
  }
  return true;
}

std::string BatchCalibrationOptions::validate() const {
  if (!(sigma_nT > 0.0) || !std::isfinite(sigma_nT)) return "sigma_nT must be positive";
  if (!(huber_k > 0.0)) return "huber_k must be positive";
  if (max_iterations < 1) return "max_iterations must be at least 1";
  if (!(tolerance > 0.0)) return "tolerance must be positive";
  if (min_samples < 10) return "min_samples must be at least 10";
  if (!(min_coverage_eigenvalue >= 0.0)) return "min_coverage_eigenvalue must be >= 0";
  if (!(max_fisher_condition > 1.0)) return "max_fisher_condition must exceed 1";
  if (min_alignment_samples < 3) return "min_alignment_samples must be at least 3";
  if (bootstrap_replicates < 8) return "bootstrap_replicates must be at least 8";
  if (!(max_field_nT > 0.0)) return "max_field_nT must be positive";
  if (gates) {
    if (std::string e = gate_options.validate(); !e.empty()) return "gates: " + e;
  }
  return {};
}

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// std(|h|) / mean(|h|) over the samples.
double reference_magnitude_relative_spread(const SampleSet& samples) {
  double sum = 0.0, sum_sq = 0.0;
  for (const CalibrationSample& s : samples) {
    const double h = s.h_body_nT.norm();
    sum += h;
    sum_sq += h * h;
  }
  const double n = static_cast<double>(samples.size());
  const double mean = sum / n;
  return std::sqrt(std::max(0.0, sum_sq / n - mean * mean)) / mean;
}

// rms of |(I + D) B - b| - |h| at p over the samples, and the residuals themselves.
double residual_rms(const SampleSet& samples, const CalibrationParameters& p,
                    std::vector<double>* residuals) {
  double sum_sq = 0.0;
  if (residuals) residuals->resize(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    const double e = p.apply(s.b_sensor_nT).norm() - s.h_body_nT.norm();
    if (residuals) (*residuals)[k] = e;
    sum_sq += e * e;
  }
  return std::sqrt(sum_sq / static_cast<double>(samples.size()));
}

// residual_rms at theta (the direct, weight-independent misfit; +inf when theta does not map to
// b, D). The LM cost is not comparable across solutions: its weights 1/sigma_k^2 shrink as the
// estimated |y| grows, so an inflated D lowers it.
double geometric_residual_rms(const SampleSet& samples, const Vector9d& theta) {
  const RecoveryResult rec = recover_parameters(theta);
  if (!rec.ok()) return kInf;
  return residual_rms(samples, rec.parameters, nullptr);
}

// A usable refinement (converged or not) with the lower geometric residual wins.
bool better_refinement(const SampleSet& samples, const LmResult& a, const LmResult& b) {
  auto usable = [](const LmResult& x) {
    return x.status == LmStatus::kOk || x.status == LmStatus::kNotConverged;
  };
  if (usable(a) != usable(b)) return usable(a);
  if (!usable(a)) return false;
  return geometric_residual_rms(samples, a.theta) < geometric_residual_rms(samples, b.theta);
}

CalibrationResult fail(CalibrationResult r, CalibrationStatus status, std::string message) {
  r.status = status;
  r.message = std::move(message);
  r.converged = false;
  r.accepted = false;
  r.rejection_reasons.push_back(to_string(status) + std::string(": ") + r.message);
  return r;
}

// The median of *x (the upper one for an even count), reordering *x.
double median_in_place(std::vector<double>* x) {
  auto mid = x->begin() + static_cast<std::ptrdiff_t>(x->size() / 2);
  std::nth_element(x->begin(), mid, x->end());
  return *mid;
}

// keep[k] = |e_k - median(e)| <= n_sigmas x max(1.4826 MAD(e), floor_nT) (a robust sigma never
// below the nominal noise: on noise-free data the MAD is rounding). Returns whether any keep[k]
// changed. `scratch` is reused.
bool mark_outliers(const std::vector<double>& e, double n_sigmas, double floor_nT,
                   std::vector<double>* scratch, std::vector<char>* keep) {
  std::vector<double>& sorted = *scratch;
  sorted = e;
  const double median = median_in_place(&sorted);
  for (double& x : sorted) x = std::abs(x - median);
  const double cut = n_sigmas * std::max(1.4826 * median_in_place(&sorted), floor_nT);
  bool changed = false;
  for (std::size_t k = 0; k < e.size(); ++k) {
    const char in = std::abs(e[k] - median) <= cut ? 1 : 0;
    changed = changed || in != (*keep)[k];
    (*keep)[k] = in;
  }
  return changed;
}

// Empty when the window's median |B| is within kMaxFieldMagnitudeRatio of its median |h|; else
// the reason, naming both and the likely cause. Samples the per-sample check refuses (zero,
// non-finite, beyond the range) are not counted.
std::string field_magnitude_mismatch(const SampleSet& samples) {
  std::vector<double> b_nT, h_nT;
  b_nT.reserve(samples.size());
  h_nT.reserve(samples.size());
  for (const CalibrationSample& s : samples) {
    if (!s.b_sensor_nT.allFinite() || !s.h_body_nT.allFinite() || is_zero_field_vector(s)) {
      continue;
    }
    b_nT.push_back(s.b_sensor_nT.norm());
    h_nT.push_back(s.h_body_nT.norm());
  }
  if (b_nT.empty()) return {};
  const double b = median_in_place(&b_nT), h = median_in_place(&h_nT);
  const double ratio = b / h;
  if (ratio <= kMaxFieldMagnitudeRatio && ratio >= 1.0 / kMaxFieldMagnitudeRatio) return {};
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "median |B| %.6g nT is %.3g times the reference field's median |h| %.6g nT: the "
                "samples are in another unit (uT: x 1e-3, G: x 1e-5, mG: x 1e-2, or raw counts), "
                "wrapped (negative counts read as unsigned) or the reference field is wrong; "
                "convert them to nT (a recording CSV: magcal fit --field-unit)",
                b, ratio, h);
  return buf;
}

// Input check: the options, the sample count, each sample (sample_input_problem), the window's
// times, the window's field magnitude against the reference (field_magnitude_mismatch). False (r
// failed) when the data cannot enter a fit.
bool check_input(const SampleSet& samples, const BatchCalibrationOptions& options,
                 CalibrationResult* r) {
  if (std::string err = options.validate(); !err.empty()) {
    *r = fail(*r, CalibrationStatus::kFailed, "invalid options: " + err);
    return false;
  }
  if (r->n_samples < options.min_samples) {
    *r = fail(*r, CalibrationStatus::kFailed,
              "too few samples: " + std::to_string(r->n_samples) + " < " +
                  std::to_string(options.min_samples));
    return false;
  }
  int64_t t0 = samples.front().utime, t1 = samples.front().utime;
  std::size_t n_zero = 0, first_zero = 0;
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    if (is_zero_field_vector(s)) {
      if (n_zero++ == 0) first_zero = k;
      continue;
    }
    if (std::string problem = sample_input_problem(s, options.max_field_nT); !problem.empty()) {
      if (beyond_sensor_range(s, options.max_field_nT)) {
        problem +=
            ": a robust fit (magcal fit --robust, [refit] robust = true) leaves such a "
            "sample out while they are at most " +
            std::to_string(static_cast<int>(100.0 * kMaxLeftOutBeyondRangeFraction)) +
            " % of the samples";
      }
      *r = fail(*r, CalibrationStatus::kFailed, sample_label(k, s.utime) + ": " + problem);
      return false;
    }
    t0 = std::min(t0, s.utime);
    t1 = std::max(t1, s.utime);
  }
  if (n_zero > 0) {
    char buf[200];
    std::snprintf(buf, sizeof buf,
                  "%s: zero field vector (sensor dropout); %zu of %zu samples are (0, 0, "
                  "0): a robust fit (magcal fit --robust, [refit] robust = true) leaves them out",
                  sample_label(first_zero, samples[first_zero].utime).c_str(), n_zero,
                  samples.size());
    *r = fail(*r, CalibrationStatus::kFailed, buf);
    return false;
  }
  if (std::string problem = field_magnitude_mismatch(samples); !problem.empty()) {
    *r = fail(*r, CalibrationStatus::kFailed, problem);
    return false;
  }
  r->window_start_utime = t0;
  r->window_end_utime = t1;
  r->utime = t1;
  return true;
}

// What stage 1 hands on: theta = [c; E], its covariances, and the part of the covariance that
// comes from the model choice.
struct Stage1Solution {
  Vector9d theta = Vector9d::Zero();
  Matrix9d covariance = Matrix9d::Zero();
  Matrix9d covariance_white = Matrix9d::Zero();
  Vector9d refused_extension_shift = Vector9d::Zero();  // p_ext - p_9 when BIC's pick is refused
  double mean_h_nT = 0.0;
  // The model extension's columns when choose_model_by_bic() computed them.
  std::vector<Vector6d> extension_regressors;
  // The temperature model is a candidate (temperature_model_unusable() says nothing against it)
  // about this reference temperature.
  bool temperature_candidate = false;
  double reference_temperature_C = 0.0;
  // The candidate's temperature is the time before the window's end
  // (with_hours_before_window_end()): the model is a bias rate.
  bool bias_rate = false;
};

LmOptions lm_options(const BatchCalibrationOptions& options, int min_samples) {
  LmOptions lopt;
  lopt.sigma_nT = options.sigma_nT;
  lopt.max_iterations = options.max_iterations;
  lopt.tolerance = options.tolerance;
  lopt.robust = options.robust;
  lopt.huber_k = options.huber_k;
  lopt.min_samples = min_samples;
  return lopt;
}

// LM from the centered solution; when that is degenerate, not positive definite or does not
// converge, also from the algebraic ellipsoid fit, keeping the better refinement.
LmResult refine_from_best_start(const SampleSet& samples, const CenteredResult& centered,
                                bool centered_degenerate, const LmOptions& lopt) {
  LmResult lm;
  bool have_lm = false;
  if (!centered_degenerate) {
    lm = refine_lm(samples, centered.theta, lopt);
    have_lm = true;
  }
  if (!have_lm || lm.status != LmStatus::kOk) {
    Vector9d theta_ellipsoid;
    if (ellipsoid_fit_start(samples, &theta_ellipsoid)) {
      LmResult alt = refine_lm(samples, theta_ellipsoid, lopt);
      if (!have_lm || better_refinement(samples, alt, lm)) lm = std::move(alt);
      have_lm = true;
    }
  }
  if (!have_lm) lm = refine_lm(samples, centered.theta, lopt);  // [c; 0] fallback inside
  return lm;
}

// Model choice by BIC: the sensor-model extension (nonlinearity + hysteresis,
// pipeline/model_extension.hpp) replaces the converged 9-parameter solution in *lm when BIC
// prefers it and what it describes are small sensor effects that leave the published b, D a fit
// of the data. Not in the robust outlier pass: BIC's Gaussian likelihood does not hold with
// outliers (spikes made BIC pick the extension and moved the bias by > 1000 nT);
// calibrate_batch() refits without them. Where BIC prefers an extension of a sensor's size that
// is not published, the two models' disagreement goes to s1->refused_extension_shift.
// With lopt.temperature_model both fits carry the temperature columns. base9: the 9-parameter
// fit, whose moments the extended fit reuses.
void choose_model_by_bic(const SampleSet& samples, const LmOptions& lopt, const LmResult& base9,
                         LmResult* lm, Stage1Solution* s1, CalibrationResult* r) {
  const RecoveryResult base = recover_parameters(lm->theta, &lm->theta_covariance);
  if (!base.ok()) return;
  s1->extension_regressors =
      model_extension_regressors(extension_inputs(samples, base.parameters, lopt.sigma_nT));
  const std::vector<Vector6d>& phi = s1->extension_regressors;
  // From the converged theta and a = 0 (linear in a) plain Gauss-Newton converges in ~3
  // iterations instead of ~5 with the default damping (paper scenario).
  LmOptions ext_options = lopt;
  ext_options.initial_lambda = 0.0;
  LmResult ext = refine_lm_extended(samples, lm->theta, phi, ext_options, &base9);
  const RecoveryResult extended = recover_parameters(ext.theta);
  // The published b, D alone (what calibration_t carries) must fit the data within
  // kMaxExtensionResidualRatio of the 9-parameter fit's residual: they are closer to the truth,
  // so somewhat worse (paper scenario, the worst of 10 seeds: 1.11x on 12 h, 1.33x on 6 h, 1.75x
  // on 3 h, where the 9-parameter fit bends b by up to 31 nT to absorb the unmodelled effects),
  // never far worse (ISS Astro Pi, whose effects the extension does not describe: 18 500 vs
  // 3 400 nT, 5.4x). A bound on the bias shift in units of the 9-parameter sigma would refuse
  // the extension where it is right: on a tumbling spacecraft that sigma is 0.2 nT while the
  // hysteresis biases the 9-parameter fit by ~1 nT.
  const bool supported = ext.status == LmStatus::kOk && extended.ok() &&
                         bic_prefers_extension(2.0 * lm->cost, 2.0 * ext.cost, r->n_samples);
  if (supported && extension_effects_small(ext.extension, s1->mean_h_nT) &&
      geometric_residual_rms(samples, ext.theta) <=
          kMaxExtensionResidualRatio * geometric_residual_rms(samples, lm->theta)) {
    *lm = std::move(ext);
    r->model_error = base.parameters.packed() - extended.parameters.packed();
    r->has_nonlinearity = true;
    r->nonlinearity_k3 = lm->extension.head<3>();
    r->hysteresis_nT = lm->extension.tail<3>();
    r->extension_covariance = lm->extension_covariance;
  } else if (supported &&
             extension_effects_small(ext.extension, s1->mean_h_nT, kMaxAmbiguityEffectFraction)) {
    // Sensor-sized effects the 9-parameter model leaves out, in a form we do not publish: the
    // data cannot say which model is right, so their disagreement joins the covariance (paper
    // scenario, 40 seeds of 3 h: where this happened the bias was 3.5-4.4 sigma off on x with
    // the HAC covariance alone, 0.96-1.19 with it). Stage 2 then removes the extension fitted
    // at b, D (estimate_alignment).
    s1->refused_extension_shift = extended.parameters.packed() - base.parameters.packed();
    r->model_error = -s1->refused_extension_shift;  // a 9-parameter filter has the same doubt
  }
}

// Publishes the temperature model a fit chose.
void set_temperature_model(const Eigen::Vector3d& k_nT_per_C, const Eigen::Matrix3d& k_covariance,
                           const Stage1Solution& s1, CalibrationResult* r) {
  r->has_temperature_model = true;
  r->reference_temperature_C = s1.reference_temperature_C;
  r->temperature_coefficient_nT_per_C = k_nT_per_C;
  r->temperature_coefficient_covariance = k_covariance;
}

// The refinement from base9 with the model extension's columns (s1.extension_regressors) and/or
// the temperature columns.
// The temperature columns are linearised at base9, then once more at that fit's estimate (the
// 9-parameter fit of a thermal set can be tens of nT off, which would leave ~1 % of the scalar
// noise in the columns).
LmResult refine_with_columns(const SampleSet& samples, const LmOptions& lopt, const LmResult& base9,
                             const Stage1Solution& s1, bool extension, bool temperature) {
  LmOptions o = lopt;
  o.temperature_model = temperature;
  o.reference_temperature_C = s1.reference_temperature_C;
  o.initial_lambda = 0.0;  // linear in the new terms: plain Gauss-Newton from base9
  auto fit = [&] {
    return extension ? refine_lm_extended(samples, base9.theta, s1.extension_regressors, o, &base9)
                     : refine_lm(samples, base9.theta, o, &base9);
  };
  const RecoveryResult at_base = recover_parameters(base9.theta);
  if (!temperature || !at_base.ok()) return fit();
  o.temperature_linearisation = at_base.parameters;
  LmResult first = fit();
  const RecoveryResult at_first = recover_parameters(first.theta);
  if (first.status != LmStatus::kOk || !at_first.ok()) return first;
  o.temperature_linearisation = at_first.parameters;
  return fit();
}

// BIC takes the bias rate on a likelihood that treats the residuals as white; where they are
// strongly autocorrelated (an unmodelled sensor or field error, which drifts with the orbit),
// that overstates how well a slow trend is determined. The rate is kept only where it is
// significant also with its covariance inflated by the AR(1) factor (1 + rho) / (1 - rho) of the
// residuals' lag-1 autocorrelation rho, at the 0.1 % tail. Measured: the paper sensor drifting
// 0.3-3 nT/h (12 h, rho 0.01-0.06) scores 320-3000 against 16.3; the ISS recording (450 nT
// residuals, rho 0.86-0.99) scored 17-39 unscaled, and its two halves' rates, -100 and +31 nT/h
// on x, disagreed: a trend of the misfit, not of the bias; scaled, at most 2. with_rate: the fit
// with the rate (its coefficient, marginal covariance and residual autocorrelation).
bool bias_rate_significant(const LmResult& with_rate) {
  const Eigen::Vector3d& rate_nT_per_h = with_rate.temperature_coefficient;
  const Eigen::LDLT<Eigen::Matrix3d> ldlt(with_rate.temperature_covariance);
  if (ldlt.info() != Eigen::Success) return false;
  const double chi2 = rate_nT_per_h.dot(ldlt.solve(rate_nT_per_h));
  return chi2 / ar1_variance_factor(with_rate.residual_autocorrelation) >
         chi_square_upper_quantile(3.0, 1e-3);
}

// Model choice by BIC, twostep, between the 9-parameter fit (base9), the sensor-model extension
// and the bias temperature model (3 columns, fitted jointly with everything else):
// - the extension is decided first, with the temperature columns in both its fits when BIC
//   prefers them to the 9-parameter model (so that a temperature effect does not make the
//   extension look wrong: paper scenario, +-15 degC, 1-2 nT/degC, where the extension decided
//   without them was refused, the bias came out 16 nT off with the temperature model on top);
// - the temperature model is then kept when BIC prefers it on top of the extension's choice (so
//   that the orbit-periodic residual of the nonlinearity and hysteresis, which an
//   orbit-synchronous temperature resembles, is not taken for a temperature effect).
// A bias rate (s1->bias_rate) is kept only where it is also significant (bias_rate_significant());
// otherwise the choice is the one without it, exactly as choose_model_by_bic() makes it from
// base9: where the rate was not first, the extension's choice made here; where it was, one more
// extension fit (the extension was chosen with the rate's columns beside it).
void choose_model_by_bic_with_temperature(const SampleSet& samples, const LmOptions& lopt,
                                          const BatchCalibrationOptions& options,
                                          const LmResult& base9, LmResult* lm, Stage1Solution* s1,
                                          CalibrationResult* r) {
  auto bic_prefers_temperature = [&](const LmResult& without, const LmResult& with) {
    return with.status == LmStatus::kOk && recover_parameters(with.theta).ok() &&
           bic_prefers_more_parameters(2.0 * without.cost, 2.0 * with.cost, r->n_samples, 3);
  };
  LmResult temperature_only = refine_with_columns(samples, lopt, base9, *s1, false, true);
  const bool temperature_first = bic_prefers_temperature(base9, temperature_only);
  std::optional<std::pair<Stage1Solution, CalibrationResult>> before_choice;
  if (s1->bias_rate && temperature_first) before_choice.emplace(*s1, *r);
  LmOptions extension_options = lopt;
  if (temperature_first) {
    *lm = temperature_only;
    extension_options.temperature_model = true;
    extension_options.reference_temperature_C = s1->reference_temperature_C;
    extension_options.temperature_linearisation = recover_parameters(lm->theta).parameters;
  }
  if (options.model_extension) {
    choose_model_by_bic(samples, extension_options, base9, lm, s1, r);
  }
  const bool extension = r->has_nonlinearity;
  LmResult without = extension && temperature_first
                         ? refine_with_columns(samples, lopt, base9, *s1, true, false)
                         : (temperature_first ? base9 : *lm);
  LmResult with = extension ? refine_with_columns(samples, lopt, base9, *s1, true, true)
                            : std::move(temperature_only);
  const bool temperature =
      bic_prefers_temperature(without, with) && (!s1->bias_rate || bias_rate_significant(with));
  if (!temperature && before_choice) {
    *lm = base9;
    std::tie(*s1, *r) = std::move(*before_choice);
    if (options.model_extension) choose_model_by_bic(samples, lopt, base9, lm, s1, r);
    return;
  }
  *lm = temperature ? std::move(with) : std::move(without);
  if (lm->status != LmStatus::kOk) return;
  if (temperature) {
    set_temperature_model(lm->temperature_coefficient, lm->temperature_covariance, *s1, r);
  }
  if (extension) {  // the published extension is the final fit's
    r->nonlinearity_k3 = lm->extension.head<3>();
    r->hysteresis_nT = lm->extension.tail<3>();
    r->extension_covariance = lm->extension_covariance;
    const RecoveryResult p9 = recover_parameters(base9.theta), p = recover_parameters(lm->theta);
    if (p9.ok() && p.ok()) r->model_error = p9.parameters.packed() - p.parameters.packed();
  }
}

// Stage 1: centered solution, [twostep] LM refinement and model choice. False (r failed) when
// no estimate comes out.
bool solve_stage1(const SampleSet& samples, const BatchCalibrationOptions& options,
                  CalibrationResult* r, Stage1Solution* s1) {
  CenteredOptions copt;
  copt.sigma_nT = options.sigma_nT;
  copt.min_samples = std::min(options.min_samples, r->n_samples);
  copt.residual_covariance = options.method == BatchCalibrationOptions::Method::kCentered;
  const CenteredResult centered = centered_solution(samples, copt);
  if (centered.status == CenteredStatus::kSingular) {
    *r = fail(*r, CalibrationStatus::kUnobservable, centered.message);
    return false;
  }
  if (centered.status != CenteredStatus::kOk &&
      centered.status != CenteredStatus::kNotPositiveDefinite) {
    *r = fail(*r, CalibrationStatus::kFailed, centered.message);
    return false;
  }
  // With a (nearly) constant reference magnitude the centered solution is degenerate
  // (E = -I, c = 0 fits the centered data exactly, estimation.md section 7): it is no estimate
  // and no start. Relative spread of |h| below 1e-3 (the paper orbit varies by ~30 %; a lab
  // or ground recording by far less than 0.1 %), or I + E close to singular (|D_ii| <= 0.3
  // keeps its eigenvalues >= 0.49), marks it.
  const bool centered_degenerate =
      centered.status != CenteredStatus::kOk ||
      reference_magnitude_relative_spread(samples) < 1e-3 ||
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(
          Eigen::Matrix3d::Identity() + unpack_symmetric(centered.theta.tail<6>()),
          Eigen::EigenvaluesOnly)
              .eigenvalues()
              .minCoeff() < 0.1;
  if (options.method == BatchCalibrationOptions::Method::kCentered) {
    if (centered.status != CenteredStatus::kOk) {
      *r = fail(*r, CalibrationStatus::kFailed, centered.message);
      return false;
    }
    if (centered_degenerate) {
      *r = fail(*r, CalibrationStatus::kFailed,
                "centered solution is degenerate (constant reference magnitude or I + E near "
                "singular): use twostep");
      return false;
    }
    const CenteredResult* chosen = &centered;
    CenteredResult with_temperature;
    if (s1->temperature_candidate) {
      // The temperature model's 4 columns in the same centered solve, kept when BIC prefers them.
      CenteredOptions topt = copt;
      topt.temperature_model = true;
      topt.reference_temperature_C = s1->reference_temperature_C;
      with_temperature = centered_solution(samples, topt);
      if (with_temperature.status == CenteredStatus::kOk &&
          bic_prefers_more_parameters(centered.chi2, with_temperature.chi2, r->n_samples, 4)) {
        const RecoveryResult rec = recover_parameters(with_temperature.theta);
        if (rec.ok()) {
          chosen = &with_temperature;
          Eigen::Vector3d k;
          Eigen::Matrix3d k_covariance;
          temperature_coefficient_from_terms(chosen->temperature_terms,
                                             chosen->temperature_covariance, rec.parameters.D, &k,
                                             &k_covariance);
          set_temperature_model(k, k_covariance, *s1, r);
        }
      }
    }
    s1->theta = chosen->theta;
    s1->covariance = chosen->theta_covariance;
    s1->covariance_white = chosen->theta_covariance_white;
    r->iterations = 0;
    r->converged = true;
    r->noise_scale = chosen->noise_scale;
    r->residual_autocorrelation = chosen->residual_autocorrelation;
    r->covariance_lag_window = chosen->lag_window;
    return true;
  }
  const LmOptions lopt = lm_options(options, copt.min_samples);
  LmResult lm = refine_from_best_start(samples, centered, centered_degenerate, lopt);
  if (lm.status == LmStatus::kSingular) {
    *r = fail(*r, CalibrationStatus::kUnobservable, lm.message);
    return false;
  }
  if (!options.robust && lm.status == LmStatus::kOk) {
    const LmResult base9 = lm;
    if (s1->temperature_candidate) {
      choose_model_by_bic_with_temperature(samples, lopt, options, base9, &lm, s1, r);
    } else if (options.model_extension) {
      choose_model_by_bic(samples, lopt, base9, &lm, s1, r);
    }
  }
  if (lm.status != LmStatus::kOk && lm.status != LmStatus::kNotConverged) {
    *r = fail(*r, CalibrationStatus::kFailed, lm.message);
    return false;
  }
  s1->theta = lm.theta;
  s1->covariance = lm.theta_covariance;
  s1->covariance_white = lm.theta_covariance_white;
  r->noise_scale = lm.noise_scale;
  r->residual_autocorrelation = lm.residual_autocorrelation;
  r->covariance_lag_window = lm.lag_window;
  r->iterations = lm.iterations;
  r->converged = lm.converged;
  r->n_downweighted = lm.n_downweighted;
  if (!lm.converged) r->message = lm.message;
  return true;
}

// The estimator's bias at parameters p (header comment): replicates
// B*_k = (I + D)^-1 (|h_k| u_k + b + s e_k), u_k the direction of the sample calibrated with p,
// e_k white (the same draws for every p: common random numbers), s the residual rms (the radial
// residual of isotropic noise has the per-axis sigma), each refined from p.
struct BootstrapBias {
  Vector9d bias = Vector9d::Zero();    // mean(p*) - p
  Matrix9d spread = Matrix9d::Zero();  // covariance of p* over the replicates
  int replicates = 0;
};

bool bootstrap_bias(const SampleSet& samples, const CalibrationParameters& p, double noise_nT,
                    const BatchCalibrationOptions& options, BootstrapBias* out) {
  const Eigen::Matrix3d to_sensor = (Eigen::Matrix3d::Identity() + p.D).inverse();
  const Vector9d theta = theta_from_parameters(p);
  LmOptions lopt = lm_options(options, std::min<int>(options.min_samples, samples.size()));
  lopt.robust = false;
  lopt.hac = false;
  std::mt19937_64 rng(0x6d616763616cULL ^ samples.size());  // reproducible per window size
  std::normal_distribution<double> normal(0.0, 1.0);
  // The noiseless part of every replicate, (I + D)^-1 (|h_k| u_k + b), is the same in each.
  std::vector<Eigen::Vector3d> noiseless(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const Eigen::Vector3d y = p.apply(samples[k].b_sensor_nT);
    noiseless[k] = to_sensor * (samples[k].h_body_nT.norm() / y.norm() * y + p.bias_nT);
  }
  const Eigen::Matrix3d noise_to_sensor = noise_nT * to_sensor;
  SampleSet replicate = samples;
  Eigen::Matrix<double, 9, Eigen::Dynamic> estimates(9, options.bootstrap_replicates);
  int n = 0;
  for (int rep = 0; rep < options.bootstrap_replicates; ++rep) {
    for (std::size_t k = 0; k < samples.size(); ++k) {
      const Eigen::Vector3d e(normal(rng), normal(rng), normal(rng));
      replicate[k].b_sensor_nT = noiseless[k] + noise_to_sensor * e;
    }
    const LmResult lm = refine_lm(replicate, theta, lopt);
    if (lm.status != LmStatus::kOk && lm.status != LmStatus::kNotConverged) continue;
    const RecoveryResult rec = recover_parameters(lm.theta);
    if (!rec.ok()) continue;
    estimates.col(n++) = rec.parameters.packed();
  }
  if (n < options.bootstrap_replicates / 2) return false;
  const Vector9d mean = estimates.leftCols(n).rowwise().mean();
  const Eigen::Matrix<double, 9, Eigen::Dynamic> centred = estimates.leftCols(n).colwise() - mean;
  out->bias = mean - p.packed();
  out->spread = centred * centred.transpose() / static_cast<double>(n - 1);
  out->replicates = n;
  return true;
}

// Removes the estimator's bias from r (twostep), where it can matter: the corrected p solves
// p + bias(p) = p_hat, two fixed-point steps from p_hat (the bias grows with the parameters'
// distance from a well-covered solution, so the bias measured at p_hat alone overshoots: +1
// sigma at 300 nT, tilt +-40 deg). The covariance takes the bootstrap's scatter where it exceeds
// the linearised one (the nonlinear regime the correction is for), the uncertainty of the bias
// estimate itself (spread / replicates) and the last fixed-point step (what a further one could
// still move).
void correct_estimator_bias(const SampleSet& samples, const BatchCalibrationOptions& options,
                            CalibrationResult* r) {
  const double noise_nT = residual_rms(samples, r->parameters, nullptr);
  double sum_h2 = 0.0;
  for (const CalibrationSample& s : samples) sum_h2 += s.h_body_nT.squaredNorm();
  const double noise_fraction = noise_nT / std::sqrt(sum_h2 / static_cast<double>(samples.size()));
  const double max_scale_sigma = r->covariance.diagonal().segment<3>(3).cwiseSqrt().maxCoeff();
  if (!(noise_fraction > kBootstrapNoiseFraction && max_scale_sigma > kBootstrapScaleSigma)) {
    return;
  }
  const Vector9d p_hat = r->parameters.packed();
  BootstrapBias first, second;
  if (!bootstrap_bias(samples, r->parameters, noise_nT, options, &first)) return;
  if (!bootstrap_bias(samples, CalibrationParameters::from_packed(p_hat - first.bias), noise_nT,
                      options, &second)) {
    return;
  }
  r->parameters = CalibrationParameters::from_packed(p_hat - second.bias);
  r->estimator_bias = second.bias;
  Matrix9d& P = r->covariance;
  const Vector9d ratio =
      (second.spread.diagonal().array() / P.diagonal().array()).max(1.0).sqrt().matrix();
  P = ratio.asDiagonal() * P * ratio.asDiagonal();
  const Vector9d step = second.bias - first.bias;
  P += second.spread / static_cast<double>(second.replicates) + step * step.transpose();
}

// Raw residuals |B| - |h| in *residuals; the samples beyond kOutlierGateRobustSigmas robust sigmas
// of their median and beyond kRawSpikeFractionOfField of the mean |h| from it marked 0 in
// *inlier. Returns how many.
int mark_raw_spikes(const SampleSet& samples, double sigma_nT, std::vector<double>* residuals,
                    std::vector<char>* inlier) {
  residuals->resize(samples.size());
  inlier->assign(samples.size(), 1);
  double mean_h_nT = 0.0;
  for (std::size_t k = 0; k < samples.size(); ++k) {
    (*residuals)[k] = samples[k].b_sensor_nT.norm() - samples[k].h_body_nT.norm();
    mean_h_nT += samples[k].h_body_nT.norm();
  }
  mean_h_nT /= static_cast<double>(std::max<std::size_t>(samples.size(), 1));
  const double floor_nT =
      std::max(sigma_nT, kRawSpikeFractionOfField * mean_h_nT / kOutlierGateRobustSigmas);
  std::vector<double> scratch;
  mark_outliers(*residuals, kOutlierGateRobustSigmas, floor_nT, &scratch, inlier);
  return static_cast<int>(std::count(inlier->begin(), inlier->end(), 0));
}

// A failed fit's message with the spikes among its samples named (mark_raw_spikes()): one sample
// far off the field can leave the centered solution without a solution at all ("I + E is not
// positive definite"), where the cause is the input, and --robust leaves it out.
void name_raw_spikes(const SampleSet& samples, double sigma_nT, CalibrationResult* r) {
  // (An input refusal that already names its sample and --robust says it all.)
  if (samples.empty() || r->message.find("--robust") != std::string::npos) return;
  std::vector<double> residuals;
  std::vector<char> inlier;
  const int n = mark_raw_spikes(samples, sigma_nT, &residuals, &inlier);
  if (n == 0) return;
  std::size_t worst = 0;
  for (std::size_t k = 0; k < residuals.size(); ++k) {
    if (inlier[k] == 0 && std::abs(residuals[k]) > std::abs(residuals[worst])) worst = k;
  }
  char buf[320];
  std::snprintf(buf, sizeof buf,
                "; %d sample(s) far off the field, the largest %s: |B| - |h| = %.4g nT (an "
                "outlier?): a robust fit (magcal fit --robust, [refit] robust = true) leaves such "
                "samples out",
                n, sample_label(worst, samples[worst].utime).c_str(), residuals[worst]);
  r->message += buf;
}

// Residual evidence at the published b, D: rms of |B_cal| - |h| (what a user of calibration_t
// gets; the model extension, when used, shows in noise_scale instead) and the samples the fit
// rests on as outliers (residuals beyond kOutlierGateRobustSigmas robust sigmas of the median).
void residual_evidence(const SampleSet& samples, const BatchCalibrationOptions& options,
                       CalibrationResult* r, GateInputs* gates) {
  std::vector<double> residuals;
  r->residual_rms_nT = residual_rms(samples, r->parameters, &residuals);
  r->residual_rms_all_nT = r->residual_rms_nT;
  std::vector<char> inlier(samples.size(), 1);
  std::vector<double> scratch;
  mark_outliers(residuals, kOutlierGateRobustSigmas, options.sigma_nT, &scratch, &inlier);
  gates->outliers.count = static_cast<int>(std::count(inlier.begin(), inlier.end(), 0));
  gates->outliers.robust_sigmas = kOutlierGateRobustSigmas;
  if (gates->outliers.count == 0) {  // a spike that wrecked the fit (kRawSpikeFractionOfField)
    gates->outliers.count = mark_raw_spikes(samples, options.sigma_nT, &residuals, &inlier);
    gates->outliers.raw = gates->outliers.count > 0;
  }
  if (gates->outliers.count > 0) {
    std::size_t worst = 0;
    for (std::size_t k = 0; k < residuals.size(); ++k) {
      if (std::abs(residuals[k]) > std::abs(residuals[worst])) worst = k;
    }
    gates->outliers.largest_sample = static_cast<int64_t>(worst);
    gates->outliers.largest_utime = samples[worst].utime;
    gates->outliers.largest_residual_nT = residuals[worst];
  }
}

// The bias's variance about its window average, where the window's short-block biases show it
// moving (pipeline/bias_variability.hpp), into the covariance (and model_error_covariance()).
// Windows of at least kMinBiasRateWindow_h: a shorter nadir window's 9-parameter D is too far off
// for its blocks (3 h paper refits: one of 12 scattered 29 times beyond the test's quantile). Not
// where the temperature model explains the bias's motion: there the blocks' scatter beyond their
// noise is the paper sensor's model error (temperature_model_test's thermal windows at the 1e-4
// tail: 5 of 24 alarmed, their b(T0) within 3 sigma in 72 of 72 axes).
void bias_variability_evidence(const SampleSet& samples, const BatchCalibrationOptions& options,
                               CalibrationResult* r) {
  if (r->has_temperature_model) return;
  const auto [t0, t1] = std::minmax_element(
      samples.begin(), samples.end(),
      [](const CalibrationSample& a, const CalibrationSample& b) { return a.utime < b.utime; });
  if (static_cast<double>(t1->utime - t0->utime) < kMinBiasRateWindow_h * 3600e6) return;
  r->bias_variability_nT2 = measure_bias_variability(samples, *r, options.sigma_nT).excess_nT2();
  r->covariance.diagonal().head<3>() += r->bias_variability_nT2;
}

// Where too few samples carry a temperature, the bias may swing with the orbit unseen by the
// residuals and the blocks (pipeline/orbit_synchronous_bias.hpp): the current bias's variance about
// the published bias, where it exceeds the blocks' measure, into the covariance and the model
// error.
void orbit_synchronous_swing_evidence(const SampleSet& samples,
                                      const BatchCalibrationOptions& options,
                                      CalibrationResult* r) {
  r->orbit_swing = unresolved_orbit_synchronous_bias_swing(samples, *r, options.sigma_nT);
  const Eigen::Vector3d added =
      (r->orbit_swing.variance_nT2 - r->bias_variability_nT2).cwiseMax(0.0);
  r->bias_variability_nT2 += added;
  r->covariance.diagonal().head<3>() += added;
}

// One fit of the samples; temperature: the temperature model is a candidate, about its mean.
// bias_rate: the samples' temperature_C is the time before the window's end
// (with_hours_before_window_end()), and a temperature model taken (only where significant) is
// published as a bias rate.
CalibrationResult calibrate_batch_window(const SampleSet& samples,
                                         const BatchCalibrationOptions& options,
                                         const CalibrationResult* previous_accepted,
                                         const TemperatureSpread* temperature,
                                         bool temperatures_too_few, bool bias_rate = false) {
  CalibrationResult r;
  r.method = to_string(options.method);
  r.n_samples = static_cast<int>(samples.size());
  r.residual_rms_nT = std::numeric_limits<double>::quiet_NaN();
  if (!check_input(samples, options, &r)) return r;

  const Eigen::Vector3d coverage = direction_coverage_eigenvalues(samples);
  if (!(coverage(0) >= options.min_coverage_eigenvalue)) {
    char buf[200];
    std::snprintf(buf, sizeof buf,
                  "unusable geometry: the field direction barely changes (smallest direction-"
                  "scatter eigenvalue %.2g < %.2g)",
                  coverage(0), options.min_coverage_eigenvalue);
    return fail(r, CalibrationStatus::kUnobservable, buf);
  }

  Stage1Solution s1;
  for (const CalibrationSample& s : samples) s1.mean_h_nT += s.h_body_nT.norm();
  s1.mean_h_nT /= static_cast<double>(samples.size());
  if (temperature) {
    s1.temperature_candidate = true;
    s1.reference_temperature_C = temperature->mean_C;
    s1.bias_rate = bias_rate;
  }
  if (!solve_stage1(samples, options, &r, &s1)) return r;

  const RecoveryResult rec = recover_parameters(s1.theta, &s1.covariance);
  if (!rec.ok()) return fail(r, CalibrationStatus::kFailed, rec.message);
  r.parameters = rec.parameters;
  r.covariance =
      rec.covariance + s1.refused_extension_shift * s1.refused_extension_shift.transpose();
  r.covariance_white_noise = recover_parameters(s1.theta, &s1.covariance_white).covariance;

  if (bias_rate) r = as_bias_rate(std::move(r));

  // Every later stage sees the samples as the published model explains them: with the fitted
  // temperature (or bias rate) term removed.
  SampleSet temperature_corrected;
  if (r.has_temperature_model) {
    temperature_corrected = temperature_corrected_samples(
        samples, r.parameters.D, r.temperature_coefficient_nT_per_C, r.reference_temperature_C);
  } else if (r.has_bias_rate) {
    temperature_corrected =
        temperature_corrected_samples(samples, r.parameters.D, r.bias_rate_nT_per_h, 0.0);
  }
  const SampleSet& corrected =
      r.has_temperature_model || r.has_bias_rate ? temperature_corrected : samples;

  GateInputs gate_inputs;
  if (options.method == BatchCalibrationOptions::Method::kTwoStep && options.bias_correction) {
    correct_estimator_bias(corrected, options, &r);
  }
  residual_evidence(corrected, options, &r, &gate_inputs);
  if (options.method == BatchCalibrationOptions::Method::kTwoStep && options.bias_variability) {
    bias_variability_evidence(corrected, options, &r);
    if (temperatures_too_few && options.orbit_synchronous_swing) {
      orbit_synchronous_swing_evidence(corrected, options, &r);
    }
  }

  const CrlbResult crlb = compute_crlb(corrected, r.parameters, options.sigma_nT);
  r.fisher_condition_number = crlb.condition_number;
  r.status = r.converged ? CalibrationStatus::kOk : CalibrationStatus::kNotConverged;
  if (!(crlb.condition_number <= options.max_fisher_condition)) {
    char buf[160];
    std::snprintf(buf, sizeof buf,
                  "scaled Fisher condition number %.3g > %.3g (field direction "
                  "does not vary enough)",
                  crlb.condition_number, options.max_fisher_condition);
    return fail(r, CalibrationStatus::kUnobservable, buf);
  }

  if (options.alignment) {
    estimate_alignment(corrected, options.sigma_nT, options.min_alignment_samples, &r, nullptr,
                       options.estimate_attitude_lag);
  }

  if (options.gates) {
    gate_inputs.min_coverage_eigenvalue = coverage(0);
    gate_inputs.fisher_min_eigenvalue = crlb.min_eigenvalue;
    gate_inputs.previous_accepted = previous_accepted;
    // The centered solution cannot take the sensor-model extension; whether the data support
    // it is evidence for its gate.
    gate_inputs.unmodelled_effects =
        options.method == BatchCalibrationOptions::Method::kCentered &&
        fit_extension_at_estimate(corrected,
                                  extension_inputs(corrected, r.parameters, options.sigma_nT),
                                  options.sigma_nT)
            .supported;
    apply_verdict(r, evaluate_gates(r, gate_inputs, options.gate_options));
  }
  return r;
}

// Coordinate descent between the bias rate and the temperature coefficient: at most this many
// rate fits, stopping once a coefficient refit moves it less than this many of its sigmas.
constexpr int kMaxRateTemperaturePasses = 4;
constexpr double kRateTemperatureSettled_sigma = 0.1;

// The samples with a bias rate removed: B' = B - (I + D)^-1 r (t - t_end), t in hours, so that the
// temperature model can be fitted without the drift it would otherwise partly absorb.
SampleSet without_bias_rate(const SampleSet& samples, const Eigen::Matrix3d& D,
                            const Eigen::Vector3d& rate_nT_per_h) {
  double span_h = 0.0;
  SampleSet out = temperature_corrected_samples(with_hours_before_window_end(samples, &span_h), D,
                                                rate_nT_per_h, 0.0);
  for (std::size_t i = 0; i < out.size(); ++i) out[i].temperature_C = samples[i].temperature_C;
  return out;
}

// A temperature model taken on a window of at least kMinBiasRateWindow_h: a drift beside it (a
// sensor ageing while its temperature cycles) is the bias rate of the samples moved to T0, chosen
// by BIC as without a temperature model; the result then carries both (its bias: at T0 and at the
// window's end). Without it, the shipped tumbling scenario (+-15 degC and 5 nT/day) published the
// bias at its 24 h window's end 18 sigma off (sigma 0.14 nT; a fresh-user trial). The coefficient
// is then refitted on the samples without the rate, and the rate on the samples moved to T0 with
// that coefficient, until the coefficient settles (block coordinate descent to the joint optimum):
// a coefficient fitted beside an unmodelled drift was up to 3.6 sigma off (24 h paper windows,
// k_z, 5 of 5 seeds on one side). The rate's and the coefficient's covariance are each their own
// fit's (their cross terms left out: a cycle of the orbit and a trend over hours are nearly
// orthogonal).
CalibrationResult with_bias_rate_beside_temperature(const SampleSet& samples,
                                                    const BatchCalibrationOptions& options,
                                                    const CalibrationResult* previous_accepted,
                                                    CalibrationResult thermal) {
  if (!thermal.has_temperature_model || !options.bias_rate_model ||
      options.method != BatchCalibrationOptions::Method::kTwoStep) {
    return thermal;
  }
  CalibrationResult drifting;
  bool settled = false;
  for (int pass = 0; pass < kMaxRateTemperaturePasses; ++pass) {
    double span_h = 0.0;
    const SampleSet timed = with_hours_before_window_end(
        temperature_corrected_samples(samples, thermal.parameters.D,
                                      thermal.temperature_coefficient_nT_per_C,
                                      thermal.reference_temperature_C),
        &span_h);
    if (span_h < kMinBiasRateWindow_h) return thermal;
    const TemperatureSpread timed_spread = temperature_spread(timed);
    CalibrationResult candidate =
        calibrate_batch_window(timed, options, previous_accepted, &timed_spread, false, true);
    if (!candidate.has_bias_rate) return pass == 0 ? thermal : drifting;
    drifting = std::move(candidate);
    drifting.has_temperature_model = true;
    drifting.reference_temperature_C = thermal.reference_temperature_C;
    drifting.temperature_coefficient_nT_per_C = thermal.temperature_coefficient_nT_per_C;
    drifting.temperature_coefficient_covariance = thermal.temperature_coefficient_covariance;
    if (settled) break;
    const SampleSet steady =
        without_bias_rate(samples, drifting.parameters.D, drifting.bias_rate_nT_per_h);
    const TemperatureSpread spread = temperature_spread(steady);
    CalibrationResult refitted =
        calibrate_batch_window(steady, options, previous_accepted, &spread, false);
    if (!refitted.has_temperature_model) break;
    const Eigen::Vector3d step =
        refitted.temperature_coefficient_nT_per_C - thermal.temperature_coefficient_nT_per_C;
    thermal = std::move(refitted);
    settled = (step.array().abs() <= kRateTemperatureSettled_sigma *
                                         thermal.temperature_coefficient_sigma_nT_per_C().array())
                  .all();
  }
  return drifting;
}

// The temperature model, where the samples allow it (temperature_model_unusable()), is chosen by
// BIC within one fit; when only some samples carry a temperature, that fit runs on those alone
// (a sample of unknown temperature has an unknown bias), and is kept only when it takes the
// temperature model: otherwise all samples enter the fit without it.
CalibrationResult calibrate_batch_core(const SampleSet& samples,
                                       const BatchCalibrationOptions& options,
                                       const CalibrationResult* previous_accepted) {
  // Without enough temperatures (none, or a sparse housekeeping rate) neither the temperature
  // model nor a constant temperature rules out a bias swinging with the orbit.
  const TemperatureSpread spread = temperature_spread(samples);
  const bool temperatures_too_few = too_few_temperatures(spread, static_cast<int>(samples.size()));
  if (options.temperature_model) {
    if (temperature_model_unusable(spread, static_cast<int>(samples.size())).empty()) {
      if (spread.n_with_temperature == static_cast<int>(samples.size())) {
        return with_bias_rate_beside_temperature(
            samples, options, previous_accepted,
            calibrate_batch_window(samples, options, previous_accepted, &spread, false));
      }
      SampleSet with_temperature;
      with_temperature.reserve(static_cast<std::size_t>(spread.n_with_temperature));
      for (const CalibrationSample& s : samples) {
        if (std::isfinite(s.temperature_C)) with_temperature.push_back(s);
      }
      CalibrationResult r =
          calibrate_batch_window(with_temperature, options, previous_accepted, &spread, false);
      if (r.has_temperature_model) {
        return with_bias_rate_beside_temperature(with_temperature, options, previous_accepted,
                                                 std::move(r));
      }
    }
  }
  // The bias rate only with the sensor-model extension beside it (twostep): the centered solution
  // took the paper sensor's nonlinearity and hysteresis for a rate (paper scenario, 12 h, 10 seeds:
  // bias MSE 4.1 -> 8.1 nT^2).
  if (options.bias_rate_model && options.method == BatchCalibrationOptions::Method::kTwoStep) {
    double span_h = 0.0;
    const SampleSet timed = with_hours_before_window_end(samples, &span_h);
    if (span_h >= kMinBiasRateWindow_h) {
      const TemperatureSpread timed_spread = temperature_spread(timed);
      return calibrate_batch_window(timed, options, previous_accepted, &timed_spread,
                                    temperatures_too_few, true);
    }
  }
  return calibrate_batch_window(samples, options, previous_accepted, nullptr, temperatures_too_few);
}
}  // namespace

void estimate_alignment(const SampleSet& samples, double sigma_nT, int min_alignment_samples,
                        CalibrationResult* r, const CalibrationResult* refit,
                        bool estimate_attitude_lag) {
  const ExtensionInputs in = extension_inputs(samples, r->parameters, sigma_nT);
  // The extension removed from the vectors: the one fitted jointly with b, D, else one fitted at
  // b, D when the data support it (the hysteresis is a lag of the field, much like a rotation
  // about the orbit normal: left in, it tilts the rotation; measured with the UKF's b, D, paper
  // scenario: pitch 25 sigma off on 12 h, 63 on 24 h).
  bool corrected = r->has_nonlinearity;
  Vector6d a;
  a << r->nonlinearity_k3, r->hysteresis_nT;
  Matrix6d a_covariance = r->extension_covariance;
  if (!corrected && refit != nullptr && refit->has_nonlinearity) {
    corrected = true;
    a << refit->nonlinearity_k3, refit->hysteresis_nT;
    a_covariance = refit->extension_covariance;
  }
  if (!corrected) {
    const ExtensionFitAtEstimate fit = fit_extension_at_estimate(samples, in, sigma_nT);
    if (fit.used) {
      corrected = true;
      a = fit.a;
      a_covariance = fit.covariance;
    }
  }
  std::vector<int64_t> utime;
  const std::vector<AlignmentPair> pairs = make_alignment_pairs(
      samples, corrected ? extension_corrected_vectors(in, a.head<3>(), a.tail<3>()) : in.y_nT,
      &utime);
  if (static_cast<int>(pairs.size()) < min_alignment_samples) return;
  const AlignmentResult al = align_procrustes(pairs);  // covariance from the residuals' structure
  if (!al.ok()) return;
  // The stage-1 estimate's own error moves the rotation too.
  const Eigen::Matrix3d stage1_covariance =
      alignment_covariance_from_stage1(samples, al.estimate.R_sensor_from_body, r->covariance,
                                       corrected ? &in : nullptr, a_covariance);
  apply_alignment_check(timed_alignment_pairs(pairs, utime), al, stage1_covariance,
                        {sigma_nT, r->residual_rms_nT, estimate_attitude_lag}, r);
}

namespace {

// Robust: a Huber IRLS refinement (robust scale) finds the outliers; the fit users get is the
// ordinary one (model extension, HAC covariance, alignment, gates) on the samples left, so its
// sigmas come from the same residual structure as a clean refit's. Large spikes can drag the
// (least-squares) centered start, and with it the first robust refinement, far off: the
// outliers are then only the worst ones, so the pass repeats on the samples left until the set
// of outliers (judged on all samples) stops changing.
CalibrationResult calibrate_batch_robust(const SampleSet& samples,
                                         const BatchCalibrationOptions& options,
                                         const CalibrationResult* previous_accepted) {
  constexpr int kMaxOutlierPasses = 8;
  BatchCalibrationOptions outlier_pass = options;
  outlier_pass.method = BatchCalibrationOptions::Method::kTwoStep;  // the IRLS is in the LM
  outlier_pass.model_extension = false;
  outlier_pass.temperature_model = false;
  outlier_pass.bias_rate_model = false;
  outlier_pass.bias_variability = false;
  outlier_pass.bias_correction = false;
  outlier_pass.alignment = false;
  outlier_pass.gates = false;
  std::vector<char> keep(samples.size(), 1);
  std::vector<double> e(samples.size()), sorted;
  // Before any fit, the gross spikes by the uncalibrated residual |B| - |h| (its spread is
  // bounded by |b| + |D||h|, so a cut of twice the usual robust sigmas leaves every clean sample;
  // a 3 G spike is 10^2-10^3 of them): a spike of 300 000 nT on a 4 h window dragged the centered
  // start so far that the first refinement failed (trial: 26 of 60 accepted).
  for (std::size_t k = 0; k < samples.size(); ++k) {
    e[k] = samples[k].b_sensor_nT.norm() - samples[k].h_body_nT.norm();
  }
  SampleSet kept;
  kept.reserve(samples.size());
  auto keep_marked = [&] {
    kept.clear();
    for (std::size_t k = 0; k < samples.size(); ++k) {
      if (keep[k]) kept.push_back(samples[k]);
    }
  };
  mark_outliers(e, 2.0 * kOutlierRobustSigmas, options.sigma_nT, &sorted, &keep);
  keep_marked();
  for (int pass = 0; pass < kMaxOutlierPasses; ++pass) {
    const CalibrationResult fit = calibrate_batch_core(kept, outlier_pass, nullptr);
    if (fit.status != CalibrationStatus::kOk && fit.status != CalibrationStatus::kNotConverged) {
      if (pass == 0) return fit;
      break;  // keep the last usable outlier set
    }
    for (std::size_t k = 0; k < samples.size(); ++k) {
      e[k] = fit.parameters.apply(samples[k].b_sensor_nT).norm() - samples[k].h_body_nT.norm();
    }
    const bool changed = mark_outliers(e, kOutlierRobustSigmas, options.sigma_nT, &sorted, &keep);
    if (!changed) break;
    keep_marked();
  }
  BatchCalibrationOptions final_pass = options;
  final_pass.robust = false;
  CalibrationResult r = calibrate_batch_core(kept, final_pass, previous_accepted);
  r.n_downweighted = static_cast<int>(samples.size() - kept.size());
  if (r.status == CalibrationStatus::kOk || r.status == CalibrationStatus::kNotConverged ||
      r.status == CalibrationStatus::kRejected) {
    r.residual_rms_all_nT = residual_rms(samples, r.parameters, nullptr);
  }
  return r;
}

}  // namespace

CalibrationResult calibrate_batch(const SampleSet& samples, const BatchCalibrationOptions& options,
                                  const CalibrationResult* previous_accepted) {
  if (!options.robust) {
    CalibrationResult r = calibrate_batch_core(samples, options, previous_accepted);
    if (r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable) {
      name_raw_spikes(samples, options.sigma_nT, &r);
    }
    return r;
  }
  // Zero field vectors (a sensor's dropouts) and isolated samples beyond the sensor range
  // (kMaxLeftOutBeyondRangeFraction) carry no measurement: left out before anything else, and
  // counted with the outliers.
  // Any other unusable sample (NaN, many wrapped or mis-scaled |B|) is no outlier of a
  // measurement but a broken input: refused, named, as without --robust.
  const auto failed = [&](const std::string& message) {
    CalibrationResult r;
    r.method = to_string(options.method);
    r.n_samples = static_cast<int>(samples.size());
    return fail(r, CalibrationStatus::kFailed, message);
  };
  SampleSet measured;
  measured.reserve(samples.size());
  std::size_t n_beyond_range = 0, first_beyond_range = 0;
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    if (is_zero_field_vector(s)) continue;
    if (beyond_sensor_range(s, options.max_field_nT)) {
      if (n_beyond_range++ == 0) first_beyond_range = k;
      continue;
    }
    if (std::string problem = sample_input_problem(s, options.max_field_nT); !problem.empty()) {
      return failed(sample_label(k, s.utime) + ": " + problem);
    }
    measured.push_back(s);
  }
  if (static_cast<double>(n_beyond_range) >
      kMaxLeftOutBeyondRangeFraction * static_cast<double>(samples.size())) {
    const CalibrationSample& s = samples[first_beyond_range];
    return failed(sample_label(first_beyond_range, s.utime) + ": " +
                  sample_input_problem(s, options.max_field_nT) + "; " +
                  std::to_string(n_beyond_range) + " of " + std::to_string(samples.size()) +
                  " samples are beyond it: a systematic fault (a robust fit leaves out at most " +
                  std::to_string(static_cast<int>(100.0 * kMaxLeftOutBeyondRangeFraction)) + " %)");
  }
  if (static_cast<int>(measured.size()) < options.min_samples) {
    if (measured.size() == samples.size()) return calibrate_batch_core(samples, options, nullptr);
    return failed("too few samples besides the " +
                  std::to_string(samples.size() - measured.size()) +
                  " zero field vectors (sensor dropouts) and samples beyond the sensor range: " +
                  std::to_string(measured.size()) + " < " + std::to_string(options.min_samples));
  }
  CalibrationResult r = calibrate_batch_robust(measured, options, previous_accepted);
  r.n_downweighted += static_cast<int>(samples.size() - measured.size());
  r.n_samples = static_cast<int>(samples.size());
  const auto [t0, t1] = std::minmax_element(
      samples.begin(), samples.end(),
      [](const CalibrationSample& a, const CalibrationSample& b) { return a.utime < b.utime; });
  r.window_start_utime = t0->utime;
  r.window_end_utime = t1->utime;
  r.utime = t1->utime;
  return r;
}

}  // namespace magcal
