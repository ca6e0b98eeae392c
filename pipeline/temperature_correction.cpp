#include "pipeline/temperature_correction.hpp"

#include <cmath>

#include "pipeline/temperature_model.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

void TemperatureCorrection::take_from(const CalibrationResult& refit,
                                      int64_t refit_calibration_id) {
  active = false;
  refit_id = 0;
  if (!refit.has_temperature_model || !std::isfinite(refit.reference_temperature_C) ||
      !refit.temperature_coefficient_nT_per_C.allFinite()) {
    return;
  }
  const Eigen::Vector3d shift =
      temperature_shift_per_C(refit.parameters.D, refit.temperature_coefficient_nT_per_C);
  if (!shift.allFinite()) return;
  active = true;
  refit_id = refit_calibration_id;
  reference_temperature_C = refit.reference_temperature_C;
  coefficient_nT_per_C = refit.temperature_coefficient_nT_per_C;
  coefficient_covariance = refit.temperature_coefficient_covariance;
  sensor_shift_nT_per_C = shift;
}

bool TemperatureCorrection::correct(const CalibrationSample& s, Eigen::Vector3d& b_sensor_nT) {
  b_sensor_nT = s.b_sensor_nT;
  double temperature_C = s.temperature_C;
  if (std::isfinite(temperature_C)) {
    held_temperature_C = temperature_C;
    held_temperature_utime = s.utime;
  } else if (std::isfinite(held_temperature_C)) {
    const int64_t age = saturating_sub(s.utime, held_temperature_utime);  // either side
    if (age <= kTemperatureHoldMax_utime && age >= -kTemperatureHoldMax_utime)
      temperature_C = held_temperature_C;
  }
  if (!active) return true;
  if (!std::isfinite(temperature_C)) {
    ++n_unused_no_temperature;
    return false;
  }
  b_sensor_nT -= sensor_shift_nT_per_C * (temperature_C - reference_temperature_C);
  return true;
}

void TemperatureCorrection::describe(CalibrationResult& result) const {
  if (!active) return;
  result.has_temperature_model = true;
  result.reference_temperature_C = reference_temperature_C;
  result.temperature_coefficient_nT_per_C = coefficient_nT_per_C;
  result.temperature_coefficient_covariance = coefficient_covariance;
}

}  // namespace magcal
