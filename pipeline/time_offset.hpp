// Time-tag offset between the measurement stream and the reference (position) stream: real
// recordings tag the two streams with clocks that disagree.
//
// Sign: tau > 0 means the reference for a measurement taken at t is evaluated at t + tau
// (e.g. position time tags that lag the magnetometer by 480 s give tau = +480 s).
//
// Method (attitude-independent, so it works without attitude):
//   for each tau on the grid tau_min, tau_min + step, ..., tau_max:
//     |h_k|(tau) = interpolate(reference series, t_k + tau)
//     fit (b, D) with the batch refit (pipeline/batch_calibration.hpp, centered + LM) and
//     take RSS(tau) = sum_k (|B_cal,k| - |h_k|(tau))^2 = N rms(tau)^2
//   minimum of the profile -> parabola through the three grid points around it -> golden-
//   section search with the full fit inside the bracketing grid interval.
//   Uncertainty from the profile's curvature (profile likelihood, delta chi-square = 1):
//     RSS(tau) ≈ RSS_min + 1/2 RSS'' (tau - tau_hat)^2,  s^2 = RSS_min / (N - 10),
//     sigma_tau = sqrt(2 s^2 / RSS''),  RSS'' by a central difference of the full fit at
//     tau_hat +- curvature_step_s.
//   That is valid for white residuals (sigma_tau_white_s). Unmodelled effects make the
//   residuals serially correlated, so sigma_tau_s inflates it with the AR(1) factor
//   sqrt((1 + rho) / (1 - rho)), rho = lag-1 autocorrelation of the residuals at tau_hat in
//   time order (clamped to [0, 0.99]). Even so it is optimistic on real data whose lag drifts
//   (ISS: the two halves give 446 s and 490 s, whole 478 s, sigma_tau_s 2.4 s).
//   Only samples whose t + tau stays inside the reference series (and away from gaps longer
//   than max_gap_s) for every tau in [tau_min, tau_max] are used, so all profile points are
//   fits of the same samples.
#pragma once

#include <limits>
#include <string>
#include <vector>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

// A scalar reference series, e.g. |H| (nT) from IGRF at each position time tag.
struct ReferenceSeries {
  std::vector<double> t_s;       // strictly increasing, seconds since 1970 (utime / 1e6)
  std::vector<double> value_nT;  // same length; non-finite values are not allowed
  std::string validate() const;  // empty when valid
};

enum class Interpolation {
  kLinear,
  kCubic,  // cubic Hermite, tangents by finite differences (exact for quadratics on a grid)
};

// Value at t (NaN outside [t_s.front(), t_s.back()] or inside a gap longer than max_gap_s).
double interpolate(const ReferenceSeries& series, double t_s, Interpolation method,
                   double max_gap_s = std::numeric_limits<double>::infinity());

struct TimeOffsetOptions {
  double tau_min_s = -1000.0;
  double tau_max_s = 1000.0;
  double step_s = 5.0;  // profile grid spacing
  Interpolation interpolation = Interpolation::kCubic;
  double max_gap_s = std::numeric_limits<double>::infinity();  // reference gaps not bridged
  double refine_tolerance_s = 1e-3;  // golden-section stop (interval width)
  double curvature_step_s = 0.0;     // <= 0: step_s / 2
  int max_profile_points = 20001;
  int min_samples = 50;
  BatchCalibrationOptions fit;   // alignment and gates are switched off internally
  std::string validate() const;  // empty when valid
};

enum class TimeOffsetStatus {
  kOk = 0,             // interior minimum, refined, with uncertainty
  kAtBoundary = 1,     // minimum on the edge of [tau_min, tau_max]: widen the range
  kFitFailed = 2,      // the fit failed at (almost) every candidate offset
  kTooFewSamples = 3,  // too few samples overlap the reference for the whole range
  kInvalidInput = 4,   // invalid options / series / samples
};
const char* to_string(TimeOffsetStatus s);  // "ok", "at_boundary", ...

struct TimeOffsetResult {
  TimeOffsetStatus status = TimeOffsetStatus::kInvalidInput;
  std::string message;
  double tau_s = 0.0;
  double sigma_tau_s = std::numeric_limits<double>::quiet_NaN();        // AR(1)-inflated
  double sigma_tau_white_s = std::numeric_limits<double>::quiet_NaN();  // white-residual value
  double residual_lag1_correlation = 0.0;                               // rho at tau_s
  double residual_rms_nT = std::numeric_limits<double>::quiet_NaN();    // at tau_s
  // rms at tau = 0 on the same samples (NaN when 0 is outside the range) — the "before".
  double residual_rms_at_zero_nT = std::numeric_limits<double>::quiet_NaN();
  int n_samples = 0;  // samples used (common to all offsets)
  int n_fits = 0;
  std::vector<double> profile_tau_s;   // the grid, for plots
  std::vector<double> profile_rms_nT;  // NaN where the fit failed

  bool ok() const { return status == TimeOffsetStatus::kOk; }
};

// samples: utime and b_sensor_nT are used (h_body_nT ignored; |h| comes from the series).
TimeOffsetResult estimate_time_offset(const SampleSet& samples, const ReferenceSeries& reference,
                                      const TimeOffsetOptions& options = {});

// The samples with |h| taken from the series at t + tau (h_body_nT = (|h|, 0, 0),
// has_reference_direction = false). Samples where the series has no value are dropped;
// returns how many were dropped.
int apply_time_offset(const SampleSet& samples, const ReferenceSeries& reference, double tau_s,
                      Interpolation method, SampleSet* out,
                      double max_gap_s = std::numeric_limits<double>::infinity());

}  // namespace magcal
