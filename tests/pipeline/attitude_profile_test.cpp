#include "pipeline/attitude_profile.hpp"

#include <catch2/catch.hpp>

#include <cmath>

using namespace magcal;

namespace {
constexpr double kDeg = 3.141592653589793 / 180.0;
constexpr int64_t kEpoch = 1577836800LL * 1'000'000;
int64_t at(double t_s) {
  return kEpoch + static_cast<int64_t>(std::llround(t_s * 1e6));
}

Orbit test_orbit() {
  KeplerianElements el;
  el.inclination_rad = 97.6 * kDeg;
  el.raan_rad = 20.0 * kDeg;
  el.epoch_utime = kEpoch;
  return Orbit(el, {});
}

// Body rate from dA/dt = -[w x] A (central differences), for checking kinematics.
Eigen::Vector3d rate_from_attitude(AttitudeProfile& p, const Orbit& o, double t, double dt) {
  const Eigen::Matrix3d A0 =
      dcm_from_quaternion(p.q_body_from_eci(at(t - dt), o.state_eci(at(t - dt))));
  const Eigen::Matrix3d A1 =
      dcm_from_quaternion(p.q_body_from_eci(at(t + dt), o.state_eci(at(t + dt))));
  const Eigen::Matrix3d A = dcm_from_quaternion(p.q_body_from_eci(at(t), o.state_eci(at(t))));
  const Eigen::Matrix3d W = -((A1 - A0) / (2.0 * dt)) * A.transpose();  // = [w x]
  return Eigen::Vector3d(W(2, 1), W(0, 2), W(1, 0));
}
}  // namespace

TEST_CASE("nadir: body z points to the Earth's centre, y opposite the orbit normal") {
  const Orbit orbit = test_orbit();
  AttitudeProfile p({}, kEpoch);
  for (double t : {0.0, 1234.0, 4000.0}) {
    const OrbitState s = orbit.state_eci(at(t));
    const Eigen::Matrix3d A = dcm_from_quaternion(p.q_body_from_eci(at(t), s));
    const Eigen::Vector3d r_body = A * s.r_m.normalized();
    CHECK((r_body - Eigen::Vector3d(0, 0, -1)).norm() < 1e-12);
    const Eigen::Vector3d h_body = A * s.r_m.cross(s.v_m_s).normalized();
    CHECK((h_body - Eigen::Vector3d(0, -1, 0)).norm() < 1e-12);
  }
  // The orbit frame turns at -n about body y (one revolution per orbit).
  const Eigen::Vector3d w = rate_from_attitude(p, orbit, 2000.0, 0.5);
  CHECK(w.y() == Approx(-orbit.mean_motion_rad_s()).epsilon(1e-6));
  CHECK(std::abs(w.x()) + std::abs(w.z()) < 1e-9);
}

TEST_CASE("inertial and spin profiles") {
  const Orbit orbit = test_orbit();
  AttitudeProfileOptions opt;
  opt.mode = AttitudeMode::inertial;
  opt.q0_body_from_eci = QuaternionWxyz(0.5, 0.5, -0.5, 0.5);
  AttitudeProfile inertial(opt, kEpoch);
  CHECK((inertial.q_body_from_eci(at(999.0), orbit.state_eci(at(999.0))) - opt.q0_body_from_eci)
            .norm() == 0.0);

  opt.mode = AttitudeMode::spin;
  opt.spin_axis_body = Eigen::Vector3d(1.0, 2.0, 2.0);  // normalised inside
  opt.spin_rate_rad_s = 3.0 * kDeg;
  AttitudeProfile spin(opt, kEpoch);
  const Eigen::Vector3d w = rate_from_attitude(spin, orbit, 50.0, 0.01);
  // Central-difference truncation error ~ |w|^3 dt^2 / 6 ~ 2e-9 rad/s here.
  CHECK((w - opt.spin_rate_rad_s * Eigen::Vector3d(1.0, 2.0, 2.0) / 3.0).norm() < 1e-7);
  // Angle turned after 40 s relative to q0 is 120 deg.
  const Eigen::Matrix3d A = dcm_from_quaternion(spin.q_body_from_eci(at(40.0), {}));
  CHECK(rotation_angle(A * dcm_from_quaternion(opt.q0_body_from_eci).transpose()) / kDeg ==
        Approx(120.0).epsilon(1e-12));
}

TEST_CASE("tumbling: torque-free invariants, kinematics and determinism") {
  const Orbit orbit = test_orbit();
  AttitudeProfileOptions opt;
  opt.mode = AttitudeMode::tumbling;
  opt.inertia_kg_m2 = Eigen::Vector3d(10.0, 14.0, 8.0);
  opt.omega0_body_rad_s = Eigen::Vector3d(2.0, -1.0, 3.0) * kDeg;
  opt.q0_body_from_eci = QuaternionWxyz(0.9, 0.1, 0.3, -0.2).normalized();
  opt.integration_step_s = 0.125;  // exact in binary: every test time is a grid point
  AttitudeProfile p(opt, kEpoch);
  const Eigen::Vector3d J = opt.inertia_kg_m2;
  const Eigen::Vector3d w0 = opt.omega0_body_rad_s;
  const double energy0 = 0.5 * w0.dot(J.cwiseProduct(w0));
  // Inertial angular momentum H = A^T J w is constant.
  const Eigen::Vector3d H0 =
      dcm_from_quaternion(opt.q0_body_from_eci).transpose() * J.cwiseProduct(w0);
  constexpr double kInvariantTol = 1e-9;  // relative, RK4 at 0.1 s over hours
  for (double t : {100.0, 1000.0, 7200.0}) {
    const QuaternionWxyz q = p.q_body_from_eci(at(t), {});
    const Eigen::Vector3d w = p.tumbling_rate_body_rad_s();  // at the grid point == t here
    CHECK(0.5 * w.dot(J.cwiseProduct(w)) == Approx(energy0).epsilon(kInvariantTol));
    const Eigen::Vector3d H = dcm_from_quaternion(q).transpose() * J.cwiseProduct(w);
    CHECK((H - H0).norm() < 1e-6 * H0.norm());
  }
  // The body rate is genuinely time-varying (not a trivial spin).
  CHECK((p.tumbling_rate_body_rad_s() - w0).norm() > 0.1 * w0.norm());
  // Kinematics: the attitude derivative matches the integrated body rate.
  AttitudeProfile k(opt, kEpoch);
  const Eigen::Vector3d w_fd = rate_from_attitude(k, orbit, 500.0, 0.05);
  k.q_body_from_eci(at(500.0), {});
  CHECK((w_fd - k.tumbling_rate_body_rad_s()).norm() <
        1e-5 * w0.norm());  // FD error ~ |w|^3 dt^2 / 6
  // Determinism: stepping vs. jumping, and going back in time, give identical bits.
  AttitudeProfile a(opt, kEpoch), b(opt, kEpoch);
  QuaternionWxyz qa;
  for (int i = 0; i <= 3000; i += 10) qa = a.q_body_from_eci(at(i + 0.05), {});
  const QuaternionWxyz qb = b.q_body_from_eci(at(3000.05), {});
  CHECK(qa == qb);
  b.q_body_from_eci(at(100.0), {});
  CHECK(b.q_body_from_eci(at(3000.05), {}) == qb);
}

TEST_CASE("attitude options are validated") {
  AttitudeProfileOptions opt;
  CHECK(opt.validate().empty());
  opt.q0_body_from_eci = QuaternionWxyz(1, 1, 0, 0);
  CHECK(opt.validate().find("q0_body_from_eci") != std::string::npos);
  opt = {};
  opt.mode = AttitudeMode::tumbling;
  opt.inertia_kg_m2 = Eigen::Vector3d(1.0, 1.0, 3.0);
  CHECK(opt.validate().find("inertia") != std::string::npos);
  opt.inertia_kg_m2 = Eigen::Vector3d(1.0, 1.0, -1.0);
  CHECK(opt.validate().find("inertia") != std::string::npos);
  opt = {};
  opt.mode = AttitudeMode::spin;
  opt.spin_axis_body.setZero();
  CHECK(opt.validate().find("spin_axis_body") != std::string::npos);
  opt = {};
  opt.mode = AttitudeMode::tumbling;
  opt.omega0_body_rad_s = Eigen::Vector3d(NAN, 0, 0);
  CHECK(opt.validate().find("omega0") != std::string::npos);
}
