// A calibration as on-board software applies it: one matrix and one offset in the BODY frame,
// with the bias's temperature and rate terms. From estimation.md section 1,
//   B_cal = R^T ((I + D) B - b(t, T)),   b(t, T) = b + k_T (T - T0) + r (t - t_ref),
// so
//   B_cal = M B - o - o_T (T - T0) - o_r (t - t_ref)
//   M = R^T (I + D),  o = R^T b,  o_T = R^T k_T,  o_r = R^T r
// with B the measured field (sensor frame, nT), B_cal its calibrated value in the body frame
// (nT), T the sensor temperature (degC), t - t_ref in hours. b is the bias at T0 and at t_ref:
// T0 = CalibrationResult::reference_temperature_C, t_ref = window_end_utime (the window's end,
// where a rate is fitted). A result without an alignment has R = I: B_cal is then in the sensor
// frame, taken for the body frame. The sensor-model extension (per-axis nonlinearity,
// hysteresis) has no term here.
#pragma once

#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

struct CalibrationTable {
  Eigen::Matrix3d M = Eigen::Matrix3d::Identity();
  Eigen::Vector3d offset_nT = Eigen::Vector3d::Zero();  // o, at T0 and t_ref
  bool has_temperature_term = false;
  double reference_temperature_C = std::numeric_limits<double>::quiet_NaN();  // T0
  Eigen::Vector3d offset_per_C_nT = Eigen::Vector3d::Zero();                  // o_T, nT/degC
  bool has_rate_term = false;
  int64_t rate_reference_utime = 0;                                // t_ref
  Eigen::Vector3d offset_rate_nT_per_h = Eigen::Vector3d::Zero();  // o_r, nT/h

  // B_cal of one measurement. With a temperature term a non-finite temperature gives NaN (the
  // bias is then unknown); without one the temperature is not used.
  Eigen::Vector3d apply(const Eigen::Vector3d& b_sensor_nT, double temperature_C,
                        int64_t utime) const;
};

CalibrationTable calibration_table(const CalibrationResult& result);

// Every value of the table rounded to the nearest float32 (what a float32 on-board table holds).
CalibrationTable float32_rounded(const CalibrationTable& table);

// What rounding a table changes in B_cal: at most ||dM||_2 |B| + |do| for a field of magnitude
// |B| <= field_nT at T0 and t_ref, plus |do_T| per degC from T0 and |do_r| per hour from t_ref.
struct TableRoundingError {
  double field_nT = 0.0;  // the |B| the first bound is for
  double at_field_nT = 0.0;
  double per_C_nT = 0.0;
  double per_h_nT = 0.0;
};
TableRoundingError rounding_error(const CalibrationTable& exact, const CalibrationTable& rounded,
                                  double field_nT);

// B_cal of every sample (NaN vectors where the table needs a temperature the sample lacks).
std::vector<Eigen::Vector3d> calibrated_field(const CalibrationTable& table,
                                              const SampleSet& samples);

// The field error (pipeline/field_error.hpp) the result's table leaves on `samples`.
FieldError table_field_error(const CalibrationResult& result, const SampleSet& samples);

}  // namespace magcal
