#include "pipeline/calibration_table.hpp"

#include <cmath>

#include <Eigen/SVD>

namespace magcal {
namespace {

constexpr double kMicrosPerHour = 3.6e9;

template <typename Derived>
Eigen::Matrix<double, Derived::RowsAtCompileTime, Derived::ColsAtCompileTime> float32_of(
    const Eigen::MatrixBase<Derived>& m) {
  return m.template cast<float>().template cast<double>();
}

}  // namespace

Eigen::Vector3d CalibrationTable::apply(const Eigen::Vector3d& b_sensor_nT, double temperature_C,
                                        int64_t utime) const {
  Eigen::Vector3d out = M * b_sensor_nT - offset_nT;
  if (has_temperature_term) out -= offset_per_C_nT * (temperature_C - reference_temperature_C);
  if (has_rate_term) {
    out -=
        offset_rate_nT_per_h * (static_cast<double>(utime - rate_reference_utime) / kMicrosPerHour);
  }
  return out;
}

CalibrationTable calibration_table(const CalibrationResult& r) {
  const Eigen::Matrix3d Rt = r.has_alignment
                                 ? Eigen::Matrix3d(r.alignment.R_sensor_from_body.transpose())
                                 : Eigen::Matrix3d(Eigen::Matrix3d::Identity());
  CalibrationTable t;
  t.M = Rt * (Eigen::Matrix3d::Identity() + r.parameters.D);
  t.offset_nT = Rt * r.parameters.bias_nT;
  t.has_temperature_term = r.has_temperature_model;
  if (r.has_temperature_model) {
    t.reference_temperature_C = r.reference_temperature_C;
    t.offset_per_C_nT = Rt * r.temperature_coefficient_nT_per_C;
  }
  t.has_rate_term = r.has_bias_rate;
  if (r.has_bias_rate) {
    t.rate_reference_utime = r.window_end_utime;
    t.offset_rate_nT_per_h = Rt * r.bias_rate_nT_per_h;
  }
  return t;
}

CalibrationTable float32_rounded(const CalibrationTable& t) {
  CalibrationTable out = t;
  out.M = float32_of(t.M);
  out.offset_nT = float32_of(t.offset_nT);
  out.reference_temperature_C = static_cast<double>(static_cast<float>(t.reference_temperature_C));
  out.offset_per_C_nT = float32_of(t.offset_per_C_nT);
  out.offset_rate_nT_per_h = float32_of(t.offset_rate_nT_per_h);
  return out;
}

TableRoundingError rounding_error(const CalibrationTable& exact, const CalibrationTable& rounded,
                                  double field_nT) {
  TableRoundingError e;
  e.field_nT = field_nT;
  const double dM_norm = Eigen::JacobiSVD<Eigen::Matrix3d>(rounded.M - exact.M).singularValues()(0);
  // T0 is rounded too: moving it shifts the offset by o_T dT0, part of the error at T0.
  double dT0_C = 0.0;
  if (exact.has_temperature_term)
    dT0_C = std::abs(rounded.reference_temperature_C - exact.reference_temperature_C);
  e.at_field_nT = dM_norm * field_nT + (rounded.offset_nT - exact.offset_nT).norm() +
                  rounded.offset_per_C_nT.norm() * dT0_C;
  e.per_C_nT = (rounded.offset_per_C_nT - exact.offset_per_C_nT).norm();
  e.per_h_nT = (rounded.offset_rate_nT_per_h - exact.offset_rate_nT_per_h).norm();
  return e;
}

std::vector<Eigen::Vector3d> calibrated_field(const CalibrationTable& table,
                                              const SampleSet& samples) {
  std::vector<Eigen::Vector3d> out;
  out.reserve(samples.size());
  for (const CalibrationSample& s : samples)
    out.push_back(table.apply(s.b_sensor_nT, s.temperature_C, s.utime));
  return out;
}

FieldError table_field_error(const CalibrationResult& result, const SampleSet& samples) {
  return field_error(calibrated_field(calibration_table(result), samples), samples);
}

}  // namespace magcal
