// Attitude profiles: the true q_body_from_eci (w,x,y,z; v_body = q ⊗ v_eci ⊗ q*) over time.
//
//   nadir     : body = orbit frame, A = orbit_from_inertial(r, v) (pipeline/rotation.hpp).
//   inertial  : A = A0 (q0_body_from_eci), constant.
//   spin      : constant rate w about a body axis k:  q(t) = q_spin(t) ⊗ q0,
//               q_spin = (cos(w t / 2), -k sin(w t / 2))   (frame rotation about k by w t).
//   tumbling  : torque-free rigid body, principal inertia J = diag(J1, J2, J3):
//               J dw/dt = -w × (J w),   dq/dt = -1/2 (0, w) ⊗ q   (w: body rate, body axes),
//               RK4 at a fixed internal step from the epoch, renormalised each step, so a
//               given time always gives the same bits regardless of the query pattern.
#pragma once

#include <cstdint>
#include <string>

#include <Eigen/Core>

#include "pipeline/orbit.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {

enum class AttitudeMode { nadir, inertial, spin, tumbling };

struct AttitudeProfileOptions {
  AttitudeMode mode = AttitudeMode::nadir;
  QuaternionWxyz q0_body_from_eci = QuaternionWxyz(1.0, 0.0, 0.0, 0.0);  // inertial/spin/tumbling
  Eigen::Vector3d spin_axis_body = Eigen::Vector3d::UnitZ();             // spin
  double spin_rate_rad_s = 0.0;                                          // spin
  Eigen::Vector3d inertia_kg_m2 = Eigen::Vector3d(10.0, 12.0, 8.0);      // tumbling, principal
  Eigen::Vector3d omega0_body_rad_s = Eigen::Vector3d::Zero();           // tumbling
  double integration_step_s = 0.1;                                       // tumbling RK4 step

  // "" if valid, else names the bad key.
  std::string validate() const;
};

class AttitudeProfile {
 public:
  // epoch_utime: t = 0 of spin/tumbling. options must validate.
  AttitudeProfile(const AttitudeProfileOptions& options, int64_t epoch_utime);

  // eci: the true orbit state at utime (used by nadir only). Times before the epoch are
  // allowed for nadir/inertial/spin; tumbling requires utime >= epoch.
  QuaternionWxyz q_body_from_eci(int64_t utime, const OrbitState& eci);

  // Body rate of the tumbling integrator at its last grid point (diagnostics/tests).
  const Eigen::Vector3d& tumbling_rate_body_rad_s() const { return omega_; }

 private:
  void rk4_step(double h, QuaternionWxyz& q, Eigen::Vector3d& w) const;

  AttitudeProfileOptions options_;
  int64_t epoch_utime_;
  // Tumbling integrator state on the grid t = k * step.
  int64_t grid_index_ = 0;
  QuaternionWxyz q_;
  Eigen::Vector3d omega_;
};

}  // namespace magcal
