#include "pipeline/roll_pitch_yaw_report.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace magcal {

RollPitchYawReport roll_pitch_yaw_report(const Eigen::Matrix3d& R,
                                         const Eigen::Matrix3d& rotation_covariance_rad2,
                                         double singular_margin_rad) {
  RollPitchYawReport out;
  const RollPitchYaw rpy = roll_pitch_yaw_from_dcm(R);
  const double cp = std::cos(rpy.pitch_rad);
  const double sp = std::sin(rpy.pitch_rad);
  const Eigen::Matrix3d Rx = frame_rotation_x(rpy.roll_rad);
  const Eigen::Vector3d e1 = Eigen::Vector3d::UnitX();
  const Eigen::Vector3d x_e2 = Rx * Eigen::Vector3d::UnitY();
  const Eigen::Vector3d x_e3 = Rx * Eigen::Vector3d::UnitZ();
  // An unknown covariance (NaN) gives unknown sigmas, never 0.
  const auto sigma = [&](const Eigen::Vector3d& g) {
    const double variance = g.dot(rotation_covariance_rad2 * g);
    return std::isnan(variance) ? variance : std::sqrt(std::max(0.0, variance));
  };
  out.sigma_rad(1) = sigma(x_e2);
  // Within a few sigmas of the pole pitch is the distance to it, two-dimensional (the tilt of
  // the sensor x axis in any direction): its error is the norm of dtheta across e1.
  const double across_e1_rad2 = rotation_covariance_rad2.trace() - rotation_covariance_rad2(0, 0);
  if (std::numbers::pi / 2 - std::abs(rpy.pitch_rad) <
      3.0 * std::sqrt(std::max(0.0, across_e1_rad2))) {
    out.sigma_rad(1) = std::sqrt(std::max(0.0, across_e1_rad2));
  }
  out.singular = std::abs(rpy.pitch_rad) >= std::numbers::pi / 2 - singular_margin_rad;
  if (!out.singular) {
    out.rpy = rpy;
    out.sigma_rad(0) = sigma(e1 + (sp / cp) * x_e3);
    out.sigma_rad(2) = sigma(x_e3 / cp);
    return out;
  }
  const double s = rpy.pitch_rad >= 0.0 ? 1.0 : -1.0;
  out.combination_name = s > 0 ? "yaw_minus_roll" : "yaw_plus_roll";
  // At the pole itself roll and yaw are atan2 of rounding noise, their combination is not:
  // R21 = -sin(yaw - s roll), R22 = cos(yaw - s roll) there.
  out.combination_rad =
      cp < 1e-6 ? std::atan2(-R(1, 0), R(1, 1))
                : std::remainder(rpy.yaw_rad - s * rpy.roll_rad, 2.0 * std::numbers::pi);
  out.combination_sigma_rad = sigma(-s * e1 + (cp / (1.0 + std::abs(sp))) * x_e3);
  out.rpy.roll_rad = 0.0;
  out.rpy.pitch_rad = rpy.pitch_rad;
  out.rpy.yaw_rad = out.combination_rad;
  out.canonical_rotation_error_rad =
      rotation_angle(dcm_from_roll_pitch_yaw(out.rpy) * R.transpose());
  return out;
}

}  // namespace magcal
