// Time-tag offset estimation by profiling the attitude-independent fit residual. Math in the
// header.
#include "pipeline/time_offset.hpp"

#include <algorithm>
#include <cmath>

#include "pipeline/acceptance_gates.hpp"

namespace magcal {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Index i with t[i] <= t <= t[i+1], or -1 outside the series.
long bracket(const std::vector<double>& t, double x) {
  if (t.size() < 2 || !(x >= t.front()) || !(x <= t.back())) return -1;
  const auto it = std::upper_bound(t.begin(), t.end(), x);
  const long i = static_cast<long>(it - t.begin()) - 1;
  return std::min(i, static_cast<long>(t.size()) - 2);
}

// Tangent at node i, exact for quadratics on any spacing; one-sided at ends and next to gaps.
double tangent(const ReferenceSeries& s, long i, double max_gap_s) {
  const auto& t = s.t_s;
  const auto& v = s.value_nT;
  const long n = static_cast<long>(t.size());
  const bool has_left = i > 0 && t[i] - t[i - 1] <= max_gap_s;
  const bool has_right = i + 1 < n && t[i + 1] - t[i] <= max_gap_s;
  if (has_left && has_right) {
    const double h0 = t[i] - t[i - 1], h1 = t[i + 1] - t[i];
    const double d0 = (v[i] - v[i - 1]) / h0, d1 = (v[i + 1] - v[i]) / h1;
    return (d0 * h1 + d1 * h0) / (h0 + h1);
  }
  if (has_right) return (v[i + 1] - v[i]) / (t[i + 1] - t[i]);
  if (has_left) return (v[i] - v[i - 1]) / (t[i] - t[i - 1]);
  return 0.0;
}

}  // namespace

std::string ReferenceSeries::validate() const {
  if (t_s.size() != value_nT.size()) return "reference series: t and value lengths differ";
  if (t_s.size() < 2) return "reference series: needs at least 2 points";
  for (std::size_t i = 0; i < t_s.size(); ++i) {
    if (!std::isfinite(t_s[i]) || !std::isfinite(value_nT[i]))
      return "reference series: non-finite value at index " + std::to_string(i);
    if (i > 0 && !(t_s[i] > t_s[i - 1]))
      return "reference series: times not strictly increasing at index " + std::to_string(i);
  }
  return {};
}

double interpolate(const ReferenceSeries& s, double t, Interpolation method, double max_gap_s) {
  const long i = bracket(s.t_s, t);
  if (i < 0) return kNaN;
  const double t0 = s.t_s[i], t1 = s.t_s[i + 1];
  const double h = t1 - t0;
  if (h > max_gap_s) return kNaN;
  const double x = (t - t0) / h;
  const double v0 = s.value_nT[i], v1 = s.value_nT[i + 1];
  if (method == Interpolation::kLinear) return v0 + x * (v1 - v0);
  const double m0 = tangent(s, i, max_gap_s) * h, m1 = tangent(s, i + 1, max_gap_s) * h;
  const double x2 = x * x, x3 = x2 * x;
  return (2 * x3 - 3 * x2 + 1) * v0 + (x3 - 2 * x2 + x) * m0 + (-2 * x3 + 3 * x2) * v1 +
         (x3 - x2) * m1;
}

std::string TimeOffsetOptions::validate() const {
  if (!std::isfinite(tau_min_s) || !std::isfinite(tau_max_s) || !(tau_min_s < tau_max_s))
    return "time offset: need finite tau_min < tau_max";
  if (!(step_s > 0.0) || !std::isfinite(step_s)) return "time offset: step must be > 0";
  if ((tau_max_s - tau_min_s) / step_s + 1.0 > max_profile_points)
    return "time offset: range / step gives more than " + std::to_string(max_profile_points) +
           " profile points";
  if ((tau_max_s - tau_min_s) / step_s < 2.0)
    return "time offset: the range must hold at least 3 grid points";
  if (!(max_gap_s > 0.0)) return "time offset: max_gap_s must be > 0";
  if (!(refine_tolerance_s > 0.0)) return "time offset: refine_tolerance_s must be > 0";
  if (min_samples < 11) return "time offset: min_samples must be > 10";
  return fit.validate();
}

const char* to_string(TimeOffsetStatus s) {
  switch (s) {
    case TimeOffsetStatus::kOk:
      return "ok";
    case TimeOffsetStatus::kAtBoundary:
      return "at_boundary";
    case TimeOffsetStatus::kFitFailed:
      return "fit_failed";
    case TimeOffsetStatus::kTooFewSamples:
      return "too_few_samples";
    case TimeOffsetStatus::kInvalidInput:
      return "invalid_input";
  }
  return "unknown";
}

int apply_time_offset(const SampleSet& samples, const ReferenceSeries& reference, double tau_s,
                      Interpolation method, SampleSet* out, double max_gap_s) {
  out->clear();
  out->reserve(samples.size());
  int dropped = 0;
  for (const auto& s : samples) {
    const double h =
        interpolate(reference, static_cast<double>(s.utime) * 1e-6 + tau_s, method, max_gap_s);
    if (!std::isfinite(h)) {
      ++dropped;
      continue;
    }
    CalibrationSample c = s;
    c.h_body_nT = Eigen::Vector3d(h, 0.0, 0.0);
    c.has_reference_direction = false;
    out->push_back(c);
  }
  return dropped;
}

TimeOffsetResult estimate_time_offset(const SampleSet& samples, const ReferenceSeries& reference,
                                      const TimeOffsetOptions& options) {
  TimeOffsetResult out;
  std::string err = options.validate();
  if (err.empty()) err = reference.validate();
  if (!err.empty()) {
    out.message = err;
    return out;
  }
  BatchCalibrationOptions fit = options.fit;
  fit.alignment = false;  // only |h| is known here
  fit.gates = false;      // the profile needs the residual whatever the verdict
  // One model at every offset: a BIC choice that flips between offsets would put steps into the
  // residual profile the minimum is read from.
  fit.model_extension = false;

  // Samples usable for every offset of the range: the whole interval [t + tau_min, t + tau_max]
  // inside the series and free of gaps (prefix count of gaps over the bracketing intervals).
  const auto& ts = reference.t_s;
  std::vector<int> gaps_before(ts.size(), 0);
  for (std::size_t i = 1; i < ts.size(); ++i)
    gaps_before[i] = gaps_before[i - 1] + (ts[i] - ts[i - 1] > options.max_gap_s ? 1 : 0);
  SampleSet work;
  std::vector<double> t_k;
  work.reserve(samples.size());
  t_k.reserve(samples.size());
  for (const auto& s : samples) {
    if (!s.b_sensor_nT.allFinite() || !(s.b_sensor_nT.norm() > 0.0)) continue;
    const double t = static_cast<double>(s.utime) * 1e-6;
    const long i0 = bracket(ts, t + options.tau_min_s);
    const long i1 = bracket(ts, t + options.tau_max_s);
    if (i0 < 0 || i1 < 0 || gaps_before[i1 + 1] - gaps_before[i0] != 0) continue;
    CalibrationSample c = s;
    c.has_reference_direction = false;
    work.push_back(c);
    t_k.push_back(t);
  }
  out.n_samples = static_cast<int>(work.size());
  if (out.n_samples < options.min_samples) {
    out.status = TimeOffsetStatus::kTooFewSamples;
    out.message = "time offset: " + std::to_string(out.n_samples) +
                  " samples overlap the reference for every offset in the range (need " +
                  std::to_string(options.min_samples) + ")";
    return out;
  }

  // rms of |B_cal| - |h|(tau) after the batch fit; NaN when the fit gives no estimate.
  CalibrationParameters last_parameters;
  auto rms_at = [&](double tau) {
    for (std::size_t k = 0; k < work.size(); ++k)
      work[k].h_body_nT = Eigen::Vector3d(
          interpolate(reference, t_k[k] + tau, options.interpolation, options.max_gap_s), 0, 0);
    const CalibrationResult r = calibrate_batch(work, fit);
    ++out.n_fits;
    last_parameters = r.parameters;
    if (r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable)
      return kNaN;
    return r.residual_rms_nT;
  };
  const double n = static_cast<double>(work.size());
  auto rss_at = [&](double tau) {
    const double r = rms_at(tau);
    return n * r * r;
  };

  const int points = static_cast<int>(std::floor(
                         (options.tau_max_s - options.tau_min_s) / options.step_s + 1e-9)) +
                     1;
  int best = -1;
  for (int i = 0; i < points; ++i) {
    const double tau = options.tau_min_s + i * options.step_s;
    const double rms = rms_at(tau);
    out.profile_tau_s.push_back(tau);
    out.profile_rms_nT.push_back(rms);
    if (std::isfinite(rms) && (best < 0 || rms < out.profile_rms_nT[best])) best = i;
  }
  if (options.tau_min_s <= 0.0 && options.tau_max_s >= 0.0)
    out.residual_rms_at_zero_nT = rms_at(0.0);
  if (best < 0) {
    out.status = TimeOffsetStatus::kFitFailed;
    out.message = "time offset: the fit failed at every candidate offset";
    return out;
  }
  out.tau_s = out.profile_tau_s[best];
  out.residual_rms_nT = out.profile_rms_nT[best];
  if (best == 0 || best == points - 1 || !std::isfinite(out.profile_rms_nT[best - 1]) ||
      !std::isfinite(out.profile_rms_nT[best + 1])) {
    out.status = TimeOffsetStatus::kAtBoundary;
    out.message =
        "time offset: the residual minimum is on the edge of the searched range (or "
        "next to a failed fit); widen [tau_min, tau_max]";
    return out;
  }

  // Golden-section search inside the bracketing grid interval, started from the parabola
  // through the three grid points (kept if the search does not beat it).
  const double step = options.step_s;
  const double r_m = out.profile_rms_nT[best - 1], r_0 = out.profile_rms_nT[best],
               r_p = out.profile_rms_nT[best + 1];
  const double denom = r_m * r_m - 2 * r_0 * r_0 + r_p * r_p;
  double tau_best = out.tau_s, rms_best = r_0;
  if (denom > 0.0) {
    const double tau_parab = out.tau_s + 0.5 * step * (r_m * r_m - r_p * r_p) / denom;
    const double rms_parab = rms_at(tau_parab);
    if (rms_parab < rms_best) tau_best = tau_parab, rms_best = rms_parab;
  }
  const double g = 0.5 * (std::sqrt(5.0) - 1.0);
  double a = out.tau_s - step, b = out.tau_s + step;
  double x1 = b - g * (b - a), x2 = a + g * (b - a);
  double f1 = rms_at(x1), f2 = rms_at(x2);
  while (b - a > options.refine_tolerance_s) {
    // NaN compares false: a failed fit is treated as the larger value.
    if (f1 < f2 || std::isnan(f2)) {
      b = x2, x2 = x1, f2 = f1;
      x1 = b - g * (b - a), f1 = rms_at(x1);
    } else {
      a = x1, x1 = x2, f1 = f2;
      x2 = a + g * (b - a), f2 = rms_at(x2);
    }
  }
  const double tau_golden = f1 < f2 ? x1 : x2;
  const double rms_golden = std::min(f1, f2);
  if (rms_golden < rms_best) tau_best = tau_golden, rms_best = rms_golden;
  out.tau_s = tau_best;
  out.residual_rms_nT = rms_best;

  // Curvature of the profile -> sigma_tau (delta chi-square = 1).
  const double hc = options.curvature_step_s > 0.0 ? options.curvature_step_s : 0.5 * step;
  const double rss0 = n * rms_best * rms_best;
  const double curvature = (rss_at(tau_best + hc) + rss_at(tau_best - hc) - 2.0 * rss0) / (hc * hc);
  const double s2 = rss0 / (n - 10.0);
  out.status = TimeOffsetStatus::kOk;
  if (curvature > 0.0 && std::isfinite(curvature)) {
    out.sigma_tau_white_s = std::sqrt(2.0 * s2 / curvature);
    // Serial correlation of the residuals at tau_hat (time order): AR(1) variance inflation.
    rms_at(tau_best);
    std::vector<std::size_t> order(work.size());
    for (std::size_t k = 0; k < order.size(); ++k) order[k] = k;
    std::sort(order.begin(), order.end(),
              [&](std::size_t a, std::size_t b) { return t_k[a] < t_k[b]; });
    double c0 = 0.0, c1 = 0.0, prev = 0.0;
    for (std::size_t j = 0; j < order.size(); ++j) {
      const CalibrationSample& w = work[order[j]];
      const double r = last_parameters.apply(w.b_sensor_nT).norm() - w.h_body_nT.x();
      c0 += r * r;
      if (j > 0) c1 += r * prev;
      prev = r;
    }
    out.residual_lag1_correlation = c0 > 0.0 ? c1 / c0 : 0.0;
    out.sigma_tau_s =
        out.sigma_tau_white_s * std::sqrt(ar1_variance_factor(out.residual_lag1_correlation, 0.99));
  } else {
    out.message = "time offset: residual profile flat at the minimum; no uncertainty";
  }
  return out;
}

}  // namespace magcal
