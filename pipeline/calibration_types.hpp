// Parameter conventions shared by every estimator (estimation.md section 0 and 1).
//
// Estimation model:  B_k = (I + D)^-1 (R h_k + b + eps_k),  eps_k ~ N(0, sigma^2 I)
// Parameter vector p = [b1 b2 b3 D11 D22 D33 D12 D13 D23]  (nT, nT, nT, 1, 1, 1, 1, 1, 1).
// Symmetric 3x3 matrices pack as 6-vectors [M11 M22 M33 M12 M13 M23].
#pragma once

#include <cstdint>
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace magcal {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Vector9d = Eigen::Matrix<double, 9, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Matrix9d = Eigen::Matrix<double, 9, 9>;
using RowVector9d = Eigen::Matrix<double, 1, 9>;

inline Vector6d pack_symmetric(const Eigen::Matrix3d& M) {
  Vector6d v;
  v << M(0, 0), M(1, 1), M(2, 2), M(0, 1), M(0, 2), M(1, 2);
  return v;
}

inline Eigen::Matrix3d unpack_symmetric(const Vector6d& v) {
  Eigen::Matrix3d M;
  M << v(0), v(3), v(4), v(3), v(1), v(5), v(4), v(5), v(2);
  return M;
}

// b and symmetric D, the stage-1 unknowns.
struct CalibrationParameters {
  Eigen::Vector3d bias_nT = Eigen::Vector3d::Zero();
  Eigen::Matrix3d D = Eigen::Matrix3d::Zero();  // symmetric

  Vector9d packed() const {
    Vector9d p;
    p << bias_nT, pack_symmetric(D);
    return p;
  }
  static CalibrationParameters from_packed(const Vector9d& p) {
    return {p.head<3>(), unpack_symmetric(p.tail<6>())};
  }
  // B_cal = (I + D) B - b, the stage-1 calibrated vector (≈ R h); stage 2 applies R^T.
  Eigen::Vector3d apply(const Eigen::Vector3d& b_sensor_nT) const {
    return (Eigen::Matrix3d::Identity() + D) * b_sensor_nT - bias_nT;
  }
};

// One sample as every estimator sees it.
struct CalibrationSample {
  int64_t utime = 0;
  Eigen::Vector3d b_sensor_nT = Eigen::Vector3d::Zero();  // measured, sensor frame
  // Reference field in the body frame. When has_reference_direction is false only its norm
  // is meaningful (stage 1 uses |h| only); stage 2 (alignment) skips such samples.
  Eigen::Vector3d h_body_nT = Eigen::Vector3d::Zero();
  bool has_reference_direction = true;
  // Sensor temperature, deg C; NaN = unknown. The bias temperature model uses only
  // samples that carry it.
  double temperature_C = std::numeric_limits<double>::quiet_NaN();
};

using SampleSet = std::vector<CalibrationSample>;

// How messages name one sample of a set: "sample K (t_s T)", K its 0-based index in the set
// (input order), T its time tag in seconds, the t_s column of the CSV (design.md).
inline std::string sample_label(std::size_t index, int64_t utime) {
  char buf[80];
  std::snprintf(buf, sizeof buf, "sample %zu (t_s %.3f)", index, static_cast<double>(utime) * 1e-6);
  return buf;
}

}  // namespace magcal
