#include "pipeline/temperature_model.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <utility>

#include <Eigen/Dense>

namespace magcal {

TemperatureSpread temperature_spread(const SampleSet& samples) {
  TemperatureSpread out;
  double sum = 0.0;
  for (const CalibrationSample& s : samples) {
    if (!std::isfinite(s.temperature_C)) continue;
    ++out.n_with_temperature;
    sum += s.temperature_C;
  }
  if (out.n_with_temperature == 0) return out;
  out.mean_C = sum / out.n_with_temperature;
  double sum_sq = 0.0;  // about the mean: no cancellation at large mean temperatures
  for (const CalibrationSample& s : samples) {
    if (std::isfinite(s.temperature_C)) sum_sq += std::pow(s.temperature_C - out.mean_C, 2);
  }
  out.std_C = std::sqrt(sum_sq / out.n_with_temperature);
  return out;
}

double mean_temperature_C(const SampleSet& samples) {
  const TemperatureSpread spread = temperature_spread(samples);
  return spread.n_with_temperature > 0 ? spread.mean_C : std::numeric_limits<double>::quiet_NaN();
}

Eigen::Vector3d temperature_shift_per_C(const Eigen::Matrix3d& D,
                                        const Eigen::Vector3d& k_nT_per_C) {
  return (Eigen::Matrix3d::Identity() + D).partialPivLu().solve(k_nT_per_C);
}

CalibrationResult at_temperature(CalibrationResult result, double temperature_C) {
  if (!result.has_temperature_model || !std::isfinite(temperature_C) ||
      !std::isfinite(result.reference_temperature_C)) {
    return result;
  }
  const double dT = temperature_C - result.reference_temperature_C;
  result.parameters.bias_nT += result.temperature_coefficient_nT_per_C * dT;
  result.covariance.topLeftCorner<3, 3>() += result.temperature_coefficient_covariance * (dT * dT);
  result.reference_temperature_C = temperature_C;
  return result;
}

bool too_few_temperatures(const TemperatureSpread& spread, int n_samples) {
  return spread.n_with_temperature < kMinTemperatureSamples ||
         spread.n_with_temperature < kMinTemperatureSampleFraction * n_samples;
}

std::string temperature_model_unusable(const TemperatureSpread& spread, int n_samples) {
  char buf[160];
  if (too_few_temperatures(spread, n_samples)) {
    std::snprintf(buf, sizeof buf, "%d of %d samples carry a temperature",
                  spread.n_with_temperature, n_samples);
    return buf;
  }
  if (!(spread.std_C >= kMinTemperatureSpread_C)) {
    std::snprintf(buf, sizeof buf, "temperature spread %.2g degC < %.2g degC", spread.std_C,
                  kMinTemperatureSpread_C);
    return buf;
  }
  return {};
}

void temperature_coefficient_from_terms(const Vector4d& a, const Matrix4d& a_covariance,
                                        const Eigen::Matrix3d& D, Eigen::Vector3d* k_nT_per_C,
                                        Eigen::Matrix3d* k_covariance) {
  const Eigen::Matrix3d to_k = (Eigen::Matrix3d::Identity() + D).inverse();
  *k_nT_per_C = to_k * a.head<3>();
  *k_covariance = to_k * a_covariance.topLeftCorner<3, 3>() * to_k.transpose();
}

SampleSet with_hours_before_window_end(const SampleSet& samples, double* span_h) {
  SampleSet out = samples;
  *span_h = 0.0;
  if (samples.empty()) return out;
  const auto [first, last] = std::minmax_element(
      samples.begin(), samples.end(),
      [](const CalibrationSample& a, const CalibrationSample& b) { return a.utime < b.utime; });
  const int64_t end_utime = last->utime;
  *span_h = static_cast<double>(end_utime - first->utime) / 3.6e9;
  for (CalibrationSample& s : out) {
    s.temperature_C = static_cast<double>(s.utime - end_utime) / 3.6e9;
  }
  return out;
}

CalibrationResult as_bias_rate(CalibrationResult result) {
  if (!result.has_temperature_model) return result;
  result = at_temperature(std::move(result), 0.0);
  result.has_bias_rate = true;
  result.bias_rate_nT_per_h = result.temperature_coefficient_nT_per_C;
  result.bias_rate_covariance = result.temperature_coefficient_covariance;
  result.has_temperature_model = false;
  result.reference_temperature_C = std::numeric_limits<double>::quiet_NaN();
  result.temperature_coefficient_nT_per_C.setZero();
  result.temperature_coefficient_covariance.setZero();
  return result;
}

CalibrationResult at_utime(CalibrationResult result, int64_t utime) {
  if (!result.has_bias_rate) return result;
  const double dt_h = static_cast<double>(utime - result.window_end_utime) / 3.6e9;
  const double dc_h =
      0.5 * static_cast<double>(result.window_end_utime - result.window_start_utime) / 3.6e9;
  result.parameters.bias_nT += result.bias_rate_nT_per_h * dt_h;
  result.covariance.topLeftCorner<3, 3>() +=
      result.bias_rate_covariance * ((dc_h + dt_h) * (dc_h + dt_h) - dc_h * dc_h);
  return result;
}

SampleSet temperature_corrected_samples(const SampleSet& samples, const Eigen::Matrix3d& D,
                                        const Eigen::Vector3d& k_nT_per_C,
                                        double reference_temperature_C) {
  const Eigen::Vector3d shift_per_C = temperature_shift_per_C(D, k_nT_per_C);
  SampleSet out = samples;
  for (CalibrationSample& s : out) {
    const double dT = s.temperature_C - reference_temperature_C;
    if (std::isfinite(dT)) s.b_sensor_nT -= dT * shift_per_C;
  }
  return out;
}

}  // namespace magcal
