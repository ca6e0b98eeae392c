#include "pipeline/attitude_profile.hpp"

#include <cassert>
#include <cmath>

namespace magcal {

namespace {
// dq/dt = -1/2 (0, w) ⊗ q for q_body_from_eci.
QuaternionWxyz quaternion_rate(const QuaternionWxyz& q, const Eigen::Vector3d& w) {
  return -0.5 * quaternion_multiply(QuaternionWxyz(0.0, w.x(), w.y(), w.z()), q);
}
// Euler's equations, torque-free.
Eigen::Vector3d body_rate_derivative(const Eigen::Vector3d& J, const Eigen::Vector3d& w) {
  return (-w.cross(J.cwiseProduct(w))).cwiseQuotient(J);
}
bool finite(const Eigen::Vector3d& v) {
  return v.allFinite();
}
}  // namespace

std::string AttitudeProfileOptions::validate() const {
  if (!q0_body_from_eci.allFinite() || std::abs(q0_body_from_eci.norm() - 1.0) > 1e-6)
    return "attitude.q0_body_from_eci: must be a unit quaternion (w,x,y,z)";
  if (mode == AttitudeMode::spin) {
    if (!finite(spin_axis_body) || spin_axis_body.norm() < 1e-12)
      return "attitude.spin_axis_body: must be a non-zero vector";
    if (!std::isfinite(spin_rate_rad_s)) return "attitude.spin_rate_deg_s: not finite";
  }
  if (mode == AttitudeMode::tumbling) {
    if (!finite(inertia_kg_m2) || inertia_kg_m2.minCoeff() <= 0.0)
      return "attitude.inertia_kg_m2: principal moments must be positive";
    const Eigen::Vector3d J = inertia_kg_m2;
    if (J(0) > J(1) + J(2) || J(1) > J(0) + J(2) || J(2) > J(0) + J(1))
      return "attitude.inertia_kg_m2: violates the triangle inequality of a rigid body";
    if (!finite(omega0_body_rad_s)) return "attitude.omega0_deg_s: not finite";
    if (omega0_body_rad_s.norm() > 1.0)
      return "attitude.omega0_deg_s: rate above 57 deg/s is out of range";
    if (!std::isfinite(integration_step_s) || integration_step_s <= 0.0 ||
        integration_step_s > 10.0)
      return "attitude.integration_step_s: must be in (0, 10] s";
  }
  return "";
}

AttitudeProfile::AttitudeProfile(const AttitudeProfileOptions& options, int64_t epoch_utime)
    : options_(options),
      epoch_utime_(epoch_utime),
      q_(options.q0_body_from_eci.normalized()),
      omega_(options.omega0_body_rad_s) {
  assert(options.validate().empty());
  if (options_.mode == AttitudeMode::spin) options_.spin_axis_body.normalize();
}

void AttitudeProfile::rk4_step(double h, QuaternionWxyz& q, Eigen::Vector3d& w) const {
  const Eigen::Vector3d& J = options_.inertia_kg_m2;
  const QuaternionWxyz k1q = quaternion_rate(q, w);
  const Eigen::Vector3d k1w = body_rate_derivative(J, w);
  const QuaternionWxyz q2 = q + 0.5 * h * k1q;
  const Eigen::Vector3d w2 = w + 0.5 * h * k1w;
  const QuaternionWxyz k2q = quaternion_rate(q2, w2);
  const Eigen::Vector3d k2w = body_rate_derivative(J, w2);
  const QuaternionWxyz q3 = q + 0.5 * h * k2q;
  const Eigen::Vector3d w3 = w + 0.5 * h * k2w;
  const QuaternionWxyz k3q = quaternion_rate(q3, w3);
  const Eigen::Vector3d k3w = body_rate_derivative(J, w3);
  const QuaternionWxyz q4 = q + h * k3q;
  const Eigen::Vector3d w4 = w + h * k3w;
  const QuaternionWxyz k4q = quaternion_rate(q4, w4);
  const Eigen::Vector3d k4w = body_rate_derivative(J, w4);
  q += (h / 6.0) * (k1q + 2.0 * k2q + 2.0 * k3q + k4q);
  w += (h / 6.0) * (k1w + 2.0 * k2w + 2.0 * k3w + k4w);
  q.normalize();
}

QuaternionWxyz AttitudeProfile::q_body_from_eci(int64_t utime, const OrbitState& eci) {
  const double t_s = static_cast<double>(utime - epoch_utime_) * 1e-6;
  switch (options_.mode) {
    case AttitudeMode::nadir:
      return quaternion_from_dcm(orbit_from_inertial(eci.r_m, eci.v_m_s));
    case AttitudeMode::inertial:
      return options_.q0_body_from_eci.normalized();
    case AttitudeMode::spin: {
      const double half = 0.5 * options_.spin_rate_rad_s * t_s;
      const Eigen::Vector3d v = -std::sin(half) * options_.spin_axis_body;
      const QuaternionWxyz q_spin(std::cos(half), v.x(), v.y(), v.z());
      return quaternion_multiply(q_spin, options_.q0_body_from_eci.normalized());
    }
    case AttitudeMode::tumbling: {
      assert(utime >= epoch_utime_);
      const double h = options_.integration_step_s;
      const auto target = static_cast<int64_t>(std::floor(t_s / h));
      if (target < grid_index_) {  // going back: restart from the epoch (deterministic)
        grid_index_ = 0;
        q_ = options_.q0_body_from_eci.normalized();
        omega_ = options_.omega0_body_rad_s;
      }
      for (; grid_index_ < target; ++grid_index_) rk4_step(h, q_, omega_);
      const double rest = t_s - static_cast<double>(grid_index_) * h;
      if (rest <= 0.0) return q_;
      QuaternionWxyz q = q_;
      Eigen::Vector3d w = omega_;
      rk4_step(rest, q, w);
      return q;
    }
  }
  return q_;
}

}  // namespace magcal
