// Bias temperature model for the batch refit: the bias of a fluxgate or AMR sensor
// follows its temperature, b(T) = b0 + k (T - T0), k per axis in nT/degC, T0 the mean temperature
// of the samples used (so b0 is the bias at the window's mean temperature).
//
// With c(T) = (I + D) b(T) = c0 + kappa dT (kappa = (I + D) k, dT = T - T0) the scalar
// measurement (estimation.md 2) is exactly
//   z_k = L_k theta - |b0|^2 + 2 dT_k B_k^T kappa - 2 dT_k b0^T k - dT_k^2 |k|^2
//       = L_k theta - |b0|^2 + 2 dT_k y_k^T k - dT_k^2 |k|^2,    y_k = (I + D) B_k - b0.
// Two linear forms, estimated jointly with theta (their marginal theta covariance then includes
// what estimating k costs); a sample without a temperature gets zero columns:
// - LM refinement (twostep): columns 2 dT_k y_k, unknowns k, y_k at an estimate of b0, D (as the
//   model extension's), refitted once with y_k at the result. The alternative below leaves
//   beta free: its column -dT_k is orbit-periodic like the bias columns 2 y_k of a nadir
//   spacecraft, and took their precision (paper 12 h, +-15 degC, 24 seeds: bias sigma (1.05,
//   1.64, 0.47) nT with it, against (0.39, 1.47, 0.26) without a temperature swing).
// - centered solution (no estimate to linearise at): columns [2 dT_k B_k; -dT_k], unknowns
//   a = [kappa; beta], beta = 2 b0^T k left free; k = (I + D)^-1 kappa.
// The term dT^2 |k|^2 left out is at most 15^2 x 3 x 2^2 = 2 700 nT^2 at +-15 degC and
// 2 nT/degC, against a scalar noise of 2 |h| sigma ~ 2.4e5 nT^2 per sample: it moves b by
// ~2 700 / (2 |h|) ~ 0.03 nT at most.
#pragma once

#include <cmath>
#include <string>

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

using Vector4d = Eigen::Matrix<double, 4, 1>;
using Matrix4d = Eigen::Matrix<double, 4, 4>;

// The model is a candidate only when enough samples carry a finite temperature with a usable
// spread (batch_calibration.cpp chooses it by BIC among the candidates):
// - at least kMinTemperatureSampleFraction of the samples (the fit then runs on those alone: a
//   sample of unknown temperature has an unknown bias; below half, that would discard most of
//   the window) and at least kMinTemperatureSamples (a third of an orbit at the paper's 10 s: a
//   floor chosen, not measured);
// - a standard deviation of at least kMinTemperatureSpread_C. Paper 12 h, 2 nT/degC on every
//   axis, 3 seeds each: at 0.5 degC std BIC took the model in 3/3 (the fit without it was up to
//   2.7 sigma off on x); at 0.2 and 0.1 degC in 0/3, the fit without it within its sigmas. Below
//   0.2 degC the extra fits are not run.
constexpr double kMinTemperatureSampleFraction = 0.5;
constexpr int kMinTemperatureSamples = 200;
constexpr double kMinTemperatureSpread_C = 0.2;

// The samples' temperatures: how many are finite, their mean and standard deviation.
struct TemperatureSpread {
  int n_with_temperature = 0;
  double mean_C = 0.0;
  double std_C = 0.0;
};
TemperatureSpread temperature_spread(const SampleSet& samples);

// The mean temperature of the samples that carry one, degC; NaN when none does. A window's T0.
double mean_temperature_C(const SampleSet& samples);

// Too few samples carry a temperature for the temperature model (or a constant temperature) to
// tell anything of the bias's thermal motion: fewer than kMinTemperatureSamples or than
// kMinTemperatureSampleFraction of n_samples.
bool too_few_temperatures(const TemperatureSpread& spread, int n_samples);

// Empty when the temperature model is a candidate for these samples, else why not.
std::string temperature_model_unusable(const TemperatureSpread& spread, int n_samples);

// The LM refinement's columns 2 dT y for one sample, y at p (zero when the temperature is
// unknown).
inline Eigen::Vector3d temperature_columns_at(const CalibrationSample& s,
                                              const CalibrationParameters& p,
                                              double reference_temperature_C) {
  const double dT = s.temperature_C - reference_temperature_C;
  if (!std::isfinite(dT)) return Eigen::Vector3d::Zero();
  return 2.0 * dT * p.apply(s.b_sensor_nT);
}

// The centered solution's columns [2 dT B; -dT] for one sample (zero when the temperature is
// unknown).
inline Vector4d temperature_columns_centered(const CalibrationSample& s,
                                             double reference_temperature_C) {
  const double dT = s.temperature_C - reference_temperature_C;
  if (!std::isfinite(dT)) return Vector4d::Zero();
  Vector4d phi;
  phi << 2.0 * dT * s.b_sensor_nT, -dT;
  return phi;
}

// Centered solution: k = (I + D)^-1 kappa and its covariance (I + D)^-1 Cov(kappa) (I + D)^-T from
// a = [kappa; beta] and Cov(a). D's own error is left out: it moves k by |dD| |k| ~ 3e-4 x 2 = 6e-4
// nT/degC on the paper scenario, against sigma(k) ~ 0.03 nT/degC.
void temperature_coefficient_from_terms(const Vector4d& a, const Matrix4d& a_covariance,
                                        const Eigen::Matrix3d& D, Eigen::Vector3d* k_nT_per_C,
                                        Eigen::Matrix3d* k_covariance);

// The sensor-frame shift of a measurement per degC, (I + D)^-1 k (nT/degC): B' = B - shift (T - T0)
// is the measurement of a sensor at T0. Non-finite when I + D is singular.
Eigen::Vector3d temperature_shift_per_C(const Eigen::Matrix3d& D,
                                        const Eigen::Vector3d& k_nT_per_C);

// A result with a bias temperature model as the bias at temperature_C: b(T) = b + k_T (T - T0),
// its bias variance grown by var(k_T) (T - T0)^2 (b at T0 and k_T are uncorrelated to first
// order: T0 is the mean temperature of the samples that fitted them), and T0 = temperature_C.
// Unchanged without a model or with a non-finite temperature. For comparing two results' biases
// (the refit's change gate, `magcal status`): each is the bias at its own window's T0.
CalibrationResult at_temperature(CalibrationResult result, double temperature_C);

// Linear bias rate: b(t) = b_end + r (t - t_end) is the temperature model with
// time in hours before the window's end in place of the temperature (the same columns, the same
// BIC choice; batch_calibration.cpp makes it a candidate when no temperature model is taken). A
// refit over a window in which the bias moves otherwise estimates the window's mean bias, with a
// covariance that says nothing of the motion: measured through the daemon's early refits (45
// drifts of 0.3-3 nT/h x 24 h), ok snapshots up to 7 sigma off the current bias.
// The model is a candidate only on windows of at least kMinBiasRateWindow_h. Measured on the paper
// sensor with a constant bias: on 2.8 h windows BIC took it in 1 of 5 seeds (rate sigma 2-4 nT/h,
// so no use against the drifts it is for); at 6 h and more the rate sigma is <= ~0.3 nT/h.
constexpr double kMinBiasRateWindow_h = 6.0;

// The samples with temperature_C replaced by the time before the last sample, hours (<= 0): the
// covariate of the bias rate model. The window's span, h, in *span_h.
SampleSet with_hours_before_window_end(const SampleSet& samples, double* span_h);

// A fit of with_hours_before_window_end() samples that took the temperature model, published as
// a bias rate: the bias at the window's end (at_temperature(result, 0)), the coefficient as
// bias_rate_nT_per_h, no temperature model.
CalibrationResult as_bias_rate(CalibrationResult result);

// A result with a bias rate as the bias at utime (after its window's end): b + r dt, its bias
// covariance grown by var(r) ((dc + dt)^2 - dc^2), dc the time from the window's centre to its
// end (the fit's b and r are uncorrelated about the mean time of the samples: the centre for
// evenly spread samples). Unchanged without a rate. For the daemon's re-anchor, whose filter has
// run past the refit's window.
CalibrationResult at_utime(CalibrationResult result, int64_t utime);

// The samples with the temperature term removed: B' = B - (I + D)^-1 k (T - T0), so that
// (I + D) B' - b0 = (I + D) B - b(T). Every stage after the stage-1 solve (residual evidence,
// bootstrap, alignment) works on these. Samples without a temperature are copied unchanged.
SampleSet temperature_corrected_samples(const SampleSet& samples, const Eigen::Matrix3d& D,
                                        const Eigen::Vector3d& k_nT_per_C,
                                        double reference_temperature_C);

}  // namespace magcal
