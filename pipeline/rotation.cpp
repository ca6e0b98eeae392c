// Rotations: estimation.md section 0 conventions (see rotation.hpp).
#include "pipeline/rotation.hpp"

#include <algorithm>
#include <cmath>

namespace magcal {

Eigen::Matrix3d dcm_from_quaternion(const QuaternionWxyz& q_in) {
  const QuaternionWxyz q = q_in.normalized();
  const double w = q(0), x = q(1), y = q(2), z = q(3);
  Eigen::Matrix3d A;
  A << 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),  //
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),   //
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y);
  return A;
}

QuaternionWxyz quaternion_from_dcm(const Eigen::Matrix3d& A) {
  // Shepperd's method: pivot on the largest of (w^2, x^2, y^2, z^2) for conditioning.
  const double tr = A.trace();
  QuaternionWxyz q;
  if (tr >= A(0, 0) && tr >= A(1, 1) && tr >= A(2, 2)) {
    const double s = 2.0 * std::sqrt(std::max(0.0, 1.0 + tr));  // 4w
    q << 0.25 * s, (A(2, 1) - A(1, 2)) / s, (A(0, 2) - A(2, 0)) / s, (A(1, 0) - A(0, 1)) / s;
  } else if (A(0, 0) >= A(1, 1) && A(0, 0) >= A(2, 2)) {
    const double s = 2.0 * std::sqrt(std::max(0.0, 1.0 + A(0, 0) - A(1, 1) - A(2, 2)));  // 4x
    q << (A(2, 1) - A(1, 2)) / s, 0.25 * s, (A(0, 1) + A(1, 0)) / s, (A(0, 2) + A(2, 0)) / s;
  } else if (A(1, 1) >= A(2, 2)) {
    const double s = 2.0 * std::sqrt(std::max(0.0, 1.0 + A(1, 1) - A(0, 0) - A(2, 2)));  // 4y
    q << (A(0, 2) - A(2, 0)) / s, (A(0, 1) + A(1, 0)) / s, 0.25 * s, (A(1, 2) + A(2, 1)) / s;
  } else {
    const double s = 2.0 * std::sqrt(std::max(0.0, 1.0 + A(2, 2) - A(0, 0) - A(1, 1)));  // 4z
    q << (A(1, 0) - A(0, 1)) / s, (A(0, 2) + A(2, 0)) / s, (A(1, 2) + A(2, 1)) / s, 0.25 * s;
  }
  q.normalize();
  if (std::abs(q(0)) < 1e-12) {  // half turn: which sign w has is rounding noise
    q(0) = 0.0;
    const int first = std::abs(q(1)) > 1e-9 ? 1 : (std::abs(q(2)) > 1e-9 ? 2 : 3);
    if (q(first) < 0.0) q = -q;
  } else if (q(0) < 0.0) {
    q = -q;
  }
  return q;
}

QuaternionWxyz quaternion_multiply(const QuaternionWxyz& p, const QuaternionWxyz& q) {
  const double pw = p(0), qw = q(0);
  const Eigen::Vector3d pv = p.tail<3>(), qv = q.tail<3>();
  QuaternionWxyz r;
  r(0) = pw * qw - pv.dot(qv);
  r.tail<3>() = pw * qv + qw * pv + pv.cross(qv);
  return r;
}

QuaternionWxyz quaternion_conjugate(const QuaternionWxyz& q) {
  return QuaternionWxyz(q(0), -q(1), -q(2), -q(3));
}

Eigen::Vector3d rotate_vector(const QuaternionWxyz& q, const Eigen::Vector3d& v) {
  // q ⊗ (0, v) ⊗ q* for a unit q, in the expanded form v + 2w (u x v) + 2 u x (u x v).
  const QuaternionWxyz qn = q.normalized();
  const Eigen::Vector3d u = qn.tail<3>();
  const Eigen::Vector3d t = 2.0 * u.cross(v);
  return v + qn(0) * t + u.cross(t);
}

Eigen::Matrix3d frame_rotation_x(double a) {
  const double c = std::cos(a), s = std::sin(a);
  Eigen::Matrix3d R;
  R << 1, 0, 0, 0, c, s, 0, -s, c;
  return R;
}

Eigen::Matrix3d frame_rotation_y(double a) {
  const double c = std::cos(a), s = std::sin(a);
  Eigen::Matrix3d R;
  R << c, 0, -s, 0, 1, 0, s, 0, c;
  return R;
}

Eigen::Matrix3d frame_rotation_z(double a) {
  const double c = std::cos(a), s = std::sin(a);
  Eigen::Matrix3d R;
  R << c, s, 0, -s, c, 0, 0, 0, 1;
  return R;
}

Eigen::Matrix3d dcm_from_roll_pitch_yaw(const RollPitchYaw& rpy) {
  return frame_rotation_x(rpy.roll_rad) * frame_rotation_y(rpy.pitch_rad) *
         frame_rotation_z(rpy.yaw_rad);
}

RollPitchYaw roll_pitch_yaw_from_dcm(const Eigen::Matrix3d& R) {
  RollPitchYaw rpy;
  rpy.pitch_rad = -std::asin(std::clamp(R(0, 2), -1.0, 1.0));
  rpy.roll_rad = std::atan2(R(1, 2), R(2, 2));
  rpy.yaw_rad = std::atan2(R(0, 1), R(0, 0));
  return rpy;
}

double rotation_angle(const Eigen::Matrix3d& R) {
  // atan2 of (sin, cos) stays accurate near 0 and pi, unlike acos((tr - 1) / 2).
  const Eigen::Vector3d v(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));
  return std::atan2(0.5 * v.norm(), 0.5 * (R.trace() - 1.0));
}

Eigen::Matrix3d orbit_from_inertial(const Eigen::Vector3d& r_m, const Eigen::Vector3d& v_m_s) {
  const Eigen::Vector3d z = -r_m.normalized();
  const Eigen::Vector3d y = -r_m.cross(v_m_s).normalized();
  const Eigen::Vector3d x = y.cross(z);
  Eigen::Matrix3d A;
  A.row(0) = x.transpose();
  A.row(1) = y.transpose();
  A.row(2) = z.transpose();
  return A;
}

}  // namespace magcal
