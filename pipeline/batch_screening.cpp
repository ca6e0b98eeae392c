#include "pipeline/batch_screening.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace magcal {

bool is_zero_field_vector(const CalibrationSample& s) {
  return s.b_sensor_nT.squaredNorm() == 0.0 && s.h_body_nT.allFinite();
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

namespace batch_detail {

bool beyond_sensor_range(const CalibrationSample& s, double max_field_nT) {
  return s.b_sensor_nT.allFinite() && s.b_sensor_nT.norm() > max_field_nT;
}

namespace {

// The median of *x (the upper one for an even count), reordering *x.
double median_in_place(std::vector<double>* x) {
  auto mid = x->begin() + static_cast<std::ptrdiff_t>(x->size() / 2);
  std::nth_element(x->begin(), mid, x->end());
  return *mid;
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

}  // namespace

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

CalibrationResult fail(CalibrationResult r, CalibrationStatus status, std::string message) {
  r.status = status;
  r.message = std::move(message);
  r.converged = false;
  r.accepted = false;
  r.rejection_reasons.push_back(to_string(status) + std::string(": ") + r.message);
  return r;
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

}  // namespace batch_detail
}  // namespace magcal
