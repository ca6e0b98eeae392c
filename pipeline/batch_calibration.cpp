#include "pipeline/batch_calibration.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <utility>
#include <vector>

#include "pipeline/alignment.hpp"
#include "pipeline/alignment_check.hpp"
#include "pipeline/batch_estimator_bias.hpp"
#include "pipeline/batch_model_selection.hpp"
#include "pipeline/batch_screening.hpp"
#include "pipeline/bias_variability.hpp"
#include "pipeline/calibration_table.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/model_extension.hpp"
#include "pipeline/orbit_synchronous_bias.hpp"
#include "pipeline/parameter_recovery.hpp"
#include "pipeline/temperature_model.hpp"

namespace magcal {

using batch_detail::beyond_sensor_range;
using batch_detail::check_input;
using batch_detail::correct_estimator_bias;
using batch_detail::fail;
using batch_detail::kMaxLeftOutBeyondRangeFraction;
using batch_detail::mark_outliers;
using batch_detail::name_raw_spikes;
using batch_detail::residual_evidence;
using batch_detail::residual_rms;
using batch_detail::solve_stage1;
using batch_detail::Stage1Solution;

// Robust fits: a sample whose residual | |B_cal| - |h| | lies more than this many robust sigmas
// (1.4826 x the median absolute deviation) from the median is an outlier and is left out of the
// final fit. For Gaussian noise 5 sigmas leave out 6e-7 of clean samples; the spike recordings
// robust mode exists for have outliers of 10^2-10^4 sigmas.
constexpr double kOutlierRobustSigmas = 5.0;

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
// bias at its 24 h window's end 18 sigma off (sigma 0.14 nT). The coefficient
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
                        {.sigma_nT = sigma_nT,
                         .stage1_residual_rms_nT = r->residual_rms_nT,
                         .estimate_attitude_lag = estimate_attitude_lag,
                         .stage1_parameter_covariance = r->covariance},
                        r);
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
  // start so far that the first refinement failed (26 of 60 accepted).
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

// The field error the estimate leaves on the samples it came from (kept as measured, outliers
// included: they are what the on-board software will meet).
CalibrationResult with_field_error(CalibrationResult r, const SampleSet& samples) {
  if (r.status != CalibrationStatus::kFailed && r.status != CalibrationStatus::kUnobservable)
    r.field_error = table_field_error(r, samples);
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
    return with_field_error(std::move(r), samples);
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
    if (measured.size() == samples.size())
      return with_field_error(calibrate_batch_core(samples, options, nullptr), samples);
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
  return with_field_error(std::move(r), measured);
}

}  // namespace magcal
