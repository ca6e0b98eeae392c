// Roll, pitch, yaw as reported with their uncertainty, and what is reportable at gimbal lock.
#pragma once

#include <limits>

#include <Eigen/Core>

#include "pipeline/rotation.hpp"

namespace magcal {

// `rotation_covariance_rad2` is that of the small rotation dtheta in the sensor frame about R
// (R_true = (I - [dtheta x]) R, the AlignmentEstimate convention). To first order
// dtheta = e1 droll + Rx(roll) e2 dpitch + Rx(roll) Ry(pitch) e3 dyaw, so
//   droll = (e1 + tan(pitch) Rx e3) . dtheta,  dpitch = Rx e2 . dtheta,
//   dyaw = (Rx e3 / cos(pitch)) . dtheta:
// roll and yaw alone grow as 1 / cos(pitch), while at pitch = +90 deg R depends on
// yaw - roll only (on yaw + roll at -90 deg), whose gradient -s e1 + cos(pitch) / (1 +
// |sin(pitch)|) Rx e3 (s = sign(pitch)) stays bounded. Within `singular_margin_rad` of pitch = +-90
// deg the angles are `singular`: their split is the canonical one, roll = 0 and yaw = the
// determined combination (yaw - roll or yaw + roll), and only pitch and that combination carry a
// sigma (roll and yaw sigma NaN). Elsewhere they are section 0's extraction with sigmas from the
// gradients above (at small angles sqrt(diag) of the rotation covariance). A NaN covariance
// (unknown) gives NaN sigmas.
struct RollPitchYawReport {
  RollPitchYaw rpy;  // canonical (roll = 0) when singular
  Eigen::Vector3d sigma_rad = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
  bool singular = false;
  // Singular: the determined combination ("yaw_minus_roll" at pitch near +90 deg, "yaw_plus_roll"
  // near -90 deg; it equals rpy.yaw) and its sigma.
  const char* combination_name = "";
  double combination_rad = std::numeric_limits<double>::quiet_NaN();
  double combination_sigma_rad = std::numeric_limits<double>::quiet_NaN();
  // Singular: the angle of the rotation between dcm_from_roll_pitch_yaw(rpy) and R, rad. Roll = 0
  // moves the whole roll into the combination, exact at the pole only: roll r at pitch p leaves
  // about |r| cos(p) (30 deg at 88.5 deg: 0.8 deg), far beyond the combination's sigma. The
  // quaternion is R itself; 0 when not singular.
  double canonical_rotation_error_rad = 0.0;
};

// Default distance from pitch +-90 deg within which the angles are reported singular. The
// roll / yaw sigmas there exceed 1 / sin(2 deg) = 29 times the rotation's own: at the 0.01-0.1
// deg of a day's refit, 0.3-3 deg, so the split says nothing a canonical one would not, and the
// first-order propagation is still exact to (rotation sigma / margin) < 5 % at its edge.
inline constexpr double kDefaultGimbalLockMargin_deg = 2.0;

RollPitchYawReport roll_pitch_yaw_report(const Eigen::Matrix3d& R,
                                         const Eigen::Matrix3d& rotation_covariance_rad2,
                                         double singular_margin_rad);

}  // namespace magcal
