// Rotations with exactly the conventions of estimation.md section 0.
//
// Quaternions are (w, x, y, z), unit, Hamilton product (ij = k). q_b_from_a rotates vectors:
// v_b = q ⊗ v_a ⊗ q*, i.e. v_b = A v_a with A = dcm_from_quaternion(q) (section 0's matrix).
// Matrices are named X_to_from: R_sensor_from_body maps body vectors into the sensor frame.
// Roll, pitch, yaw: aerospace 3-2-1 sequence of *frame* rotations, R = Rx(roll) Ry(pitch)
// Rz(yaw) with Rx(a) = [[1,0,0],[0,c,s],[0,-s,c]] etc., so R ≈ I - [theta x] for small angles.
#pragma once

#include <numbers>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace magcal {

// Angle unit conversions (the one definition; use these, not local copies).
inline constexpr double kDegToRad = std::numbers::pi / 180.0;
inline constexpr double kRadToDeg = 180.0 / std::numbers::pi;

// Quaternion as a plain 4-vector (w, x, y, z), so no library's storage order leaks through.
using QuaternionWxyz = Eigen::Vector4d;

Eigen::Matrix3d dcm_from_quaternion(const QuaternionWxyz& q);  // normalises q first
// The canonical sign of q and -q (the same rotation): w > 0; for a half turn (|w| < 1e-12, the
// sign of w is rounding noise) w = 0 and the first of x, y, z that is not ~0 (|.| > 1e-9)
// positive, so a mounting turned upside down reads the same every time.
QuaternionWxyz quaternion_from_dcm(const Eigen::Matrix3d& A);
QuaternionWxyz quaternion_multiply(const QuaternionWxyz& p, const QuaternionWxyz& q);  // p ⊗ q
QuaternionWxyz quaternion_conjugate(const QuaternionWxyz& q);
// v_b = q ⊗ v ⊗ q*
Eigen::Vector3d rotate_vector(const QuaternionWxyz& q, const Eigen::Vector3d& v);

// Frame rotations (section 0): Rx(a) = [[1,0,0],[0,c,s],[0,-s,c]], likewise Ry, Rz.
Eigen::Matrix3d frame_rotation_x(double angle_rad);
Eigen::Matrix3d frame_rotation_y(double angle_rad);
Eigen::Matrix3d frame_rotation_z(double angle_rad);

struct RollPitchYaw {
  double roll_rad = 0.0;
  double pitch_rad = 0.0;
  double yaw_rad = 0.0;
};
// R = Rx(roll) Ry(pitch) Rz(yaw)
Eigen::Matrix3d dcm_from_roll_pitch_yaw(const RollPitchYaw& rpy);
// pitch = -asin(R13), roll = atan2(R23, R33), yaw = atan2(R12, R11)
RollPitchYaw roll_pitch_yaw_from_dcm(const Eigen::Matrix3d& R);

// [v x], so that cross_matrix(a) * b = a × b.
inline Eigen::Matrix3d cross_matrix(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

// Rotation angle of a rotation matrix (rad, in [0, pi]); used for alignment errors.
double rotation_angle(const Eigen::Matrix3d& R);

// Orbit frame (estimation.md section 0): z to Earth's centre, y opposite the orbital angular
// momentum, x completes the right-handed set (≈ velocity on circular orbits).
// Returns A_orbit_from_inertial for position and velocity in the same inertial frame.
Eigen::Matrix3d orbit_from_inertial(const Eigen::Vector3d& r_m, const Eigen::Vector3d& v_m_s);

}  // namespace magcal
