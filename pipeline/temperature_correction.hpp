// The bias temperature model of the refit an online filter is anchored on. The filters' 9-state
// model has no temperature, so each sample is moved to the model's reference temperature T0
// before the update:
//   B' = B - (I + D_refit)^-1 k_T (T - T0)
// (estimation.md section 1 with b(T) = b + k_T (T - T0)), and the filter estimates the bias at
// T0, the refit's bias. A sample without a temperature (NaN) takes the last one seen when that is
// at most kTemperatureHoldMax_utime away (a temperature channel sampled slower than the
// magnetometer); the hold's error, k_T dT/dt times its age, stays below the noise (LEO thermal
// cycles move a sensor by at most ~1 degC/min). Otherwise its bias offset k_T (T - T0) is
// unknown: as large as the thermal swing (tens of nT), against a few nT of noise, so the filter
// does not use it (weighted by its true variance it would carry a few % of a sample's
// information; used as it is, it biases the filter by several sigma when temperatures are
// missing often). Such a sample is still stored, and the refits use it as their model allows.
#pragma once

#include <cstdint>
#include <limits>

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

struct TemperatureCorrection {
  static constexpr int64_t kTemperatureHoldMax_utime = 60'000'000;  // 60 s

  bool active = false;
  int64_t refit_id = 0;  // calibrations.id of the refit it came from (0: unknown)
  double reference_temperature_C = 0.0;
  Eigen::Vector3d coefficient_nT_per_C = Eigen::Vector3d::Zero();
  Eigen::Matrix3d coefficient_covariance = Eigen::Matrix3d::Zero();  // (nT/degC)^2
  Eigen::Vector3d sensor_shift_nT_per_C = Eigen::Vector3d::Zero();   // (I + D_refit)^-1 k_T
  // The newest sample temperature seen (for the hold), and its time.
  double held_temperature_C = std::numeric_limits<double>::quiet_NaN();
  int64_t held_temperature_utime = 0;
  int64_t n_unused_no_temperature = 0;  // samples the filter did not use (see above)

  // Takes the refit's model, or none when it has none (or an unusable one).
  void take_from(const CalibrationResult& refit, int64_t refit_calibration_id);
  // The sample moved to T0 (unchanged while inactive); false when it has no usable temperature
  // (then the filter must not use it). Updates the hold.
  bool correct(const CalibrationSample& s, Eigen::Vector3d& b_sensor_nT);
  // Marks an online result as using this model (its bias is the bias at T0); no-op if inactive.
  void describe(CalibrationResult& result) const;
};

}  // namespace magcal
