// Rotation conventions of estimation.md section 0, checked against independent forms:
// the explicit quaternion product q ⊗ (0, v) ⊗ q*, Eigen's AngleAxis (active rotations) and
// ERFA's eraRx/eraRy/eraRz (frame rotations, IAU SOFA).
#include "pipeline/rotation.hpp"

#include <cmath>
#include <numbers>
#include <random>

#include <erfa.h>
#include <catch2/catch.hpp>

using namespace magcal;

namespace {
constexpr double kTol = 1e-12;

QuaternionWxyz random_unit_quaternion(std::mt19937_64& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  QuaternionWxyz q(n(rng), n(rng), n(rng), n(rng));
  return q.normalized();
}

Eigen::Matrix3d from_erfa(double r[3][3]) {
  Eigen::Matrix3d m;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) m(i, j) = r[i][j];
  return m;
}
}  // namespace

TEST_CASE("Hamilton product: ij = k and v_b = q v q*", "[rotation]") {
  const QuaternionWxyz i(0, 1, 0, 0), j(0, 0, 1, 0), k(0, 0, 0, 1);
  CHECK((quaternion_multiply(i, j) - k).norm() < kTol);
  CHECK((quaternion_multiply(j, i) + k).norm() < kTol);

  std::mt19937_64 rng(11);
  std::normal_distribution<double> n(0.0, 1.0);
  for (int t = 0; t < 200; ++t) {
    const QuaternionWxyz q = random_unit_quaternion(rng);
    const Eigen::Vector3d v(n(rng), n(rng), n(rng));
    QuaternionWxyz vq(0.0, v.x(), v.y(), v.z());
    const QuaternionWxyz r =
        quaternion_multiply(quaternion_multiply(q, vq), quaternion_conjugate(q));
    REQUIRE(std::abs(r(0)) < kTol);
    REQUIRE((r.tail<3>() - rotate_vector(q, v)).norm() < kTol);
    REQUIRE((dcm_from_quaternion(q) * v - rotate_vector(q, v)).norm() < kTol);
  }
}

TEST_CASE("quaternion about +z is the active rotation (AngleAxis), not the frame rotation",
          "[rotation]") {
  const double a = 0.7;
  const QuaternionWxyz q(std::cos(a / 2), 0, 0, std::sin(a / 2));
  const Eigen::Matrix3d active = Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  CHECK((dcm_from_quaternion(q) - active).norm() < kTol);
  CHECK((frame_rotation_z(a) - active.transpose()).norm() < kTol);
}

TEST_CASE("q -> DCM -> q round trip, including 180-degree rotations", "[rotation]") {
  std::mt19937_64 rng(12);
  std::vector<QuaternionWxyz> qs;
  for (int t = 0; t < 500; ++t) qs.push_back(random_unit_quaternion(rng));
  // w = 0 (half turns) about each axis and a skew axis exercise every Shepperd branch.
  qs.push_back(QuaternionWxyz(0, 1, 0, 0));
  qs.push_back(QuaternionWxyz(0, 0, 1, 0));
  qs.push_back(QuaternionWxyz(0, 0, 0, 1));
  qs.push_back(QuaternionWxyz(0, 1, 1, 1).normalized());
  qs.push_back(QuaternionWxyz(1, 0, 0, 0));
  for (QuaternionWxyz q : qs) {
    if (q(0) < 0) q = -q;
    const QuaternionWxyz back = quaternion_from_dcm(dcm_from_quaternion(q));
    // q and -q are the same rotation; with w = 0 either sign is valid.
    const double err = std::min((back - q).norm(), (back + q).norm());
    REQUIRE(err < 1e-12);
    REQUIRE(back(0) >= 0.0);
  }
}

TEST_CASE("composition: A(q_cb ⊗ q_ba) = A_cb A_ba", "[rotation]") {
  std::mt19937_64 rng(13);
  for (int t = 0; t < 200; ++t) {
    const QuaternionWxyz q_cb = random_unit_quaternion(rng);
    const QuaternionWxyz q_ba = random_unit_quaternion(rng);
    const Eigen::Matrix3d lhs = dcm_from_quaternion(quaternion_multiply(q_cb, q_ba));
    const Eigen::Matrix3d rhs = dcm_from_quaternion(q_cb) * dcm_from_quaternion(q_ba);
    REQUIRE((lhs - rhs).norm() < kTol);
  }
  // Section 0's matrix entries, spelled out for one quaternion.
  const QuaternionWxyz q = QuaternionWxyz(0.9, 0.1, -0.3, 0.2).normalized();
  const double w = q(0), x = q(1), y = q(2), z = q(3);
  const Eigen::Matrix3d A = dcm_from_quaternion(q);
  CHECK(std::abs(A(0, 1) - 2 * (x * y - w * z)) < kTol);
  CHECK(std::abs(A(1, 2) - 2 * (y * z - w * x)) < kTol);
  CHECK(std::abs(A(2, 0) - 2 * (x * z - w * y)) < kTol);
}

TEST_CASE("frame rotations equal ERFA's eraRx/eraRy/eraRz", "[rotation]") {
  for (double a : {-2.5, -0.3, 0.0, 0.1, 1.2, 3.0}) {
    double r[3][3];
    eraIr(r);
    eraRx(a, r);
    CHECK((frame_rotation_x(a) - from_erfa(r)).norm() < kTol);
    eraIr(r);
    eraRy(a, r);
    CHECK((frame_rotation_y(a) - from_erfa(r)).norm() < kTol);
    eraIr(r);
    eraRz(a, r);
    CHECK((frame_rotation_z(a) - from_erfa(r)).norm() < kTol);
  }
}

TEST_CASE("roll/pitch/yaw: 3-2-1 order, small-angle form and round trip", "[rotation]") {
  const RollPitchYaw rpy{0.3, -0.2, 1.1};
  const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw(rpy);
  CHECK((R - frame_rotation_x(0.3) * frame_rotation_y(-0.2) * frame_rotation_z(1.1)).norm() < kTol);

  // R ≈ I - [theta x]: the error is second order in theta.
  const Eigen::Vector3d theta(1e-4, 2e-4, -3e-4);
  const Eigen::Matrix3d Rs = dcm_from_roll_pitch_yaw({theta.x(), theta.y(), theta.z()});
  const double second_order = theta.squaredNorm();
  CHECK((Rs - (Eigen::Matrix3d::Identity() - cross_matrix(theta))).norm() < 2 * second_order);
  // ... and the sign matters: I + [theta x] is off by first order.
  CHECK((Rs - (Eigen::Matrix3d::Identity() + cross_matrix(theta))).norm() > 1e-4);

  std::mt19937_64 rng(14);
  std::uniform_real_distribution<double> ang(-3.1, 3.1), pitch(-1.5, 1.5);
  for (int t = 0; t < 500; ++t) {
    const RollPitchYaw in{ang(rng), pitch(rng), ang(rng)};
    const RollPitchYaw out = roll_pitch_yaw_from_dcm(dcm_from_roll_pitch_yaw(in));
    REQUIRE(std::abs(out.roll_rad - in.roll_rad) < 1e-9);
    REQUIRE(std::abs(out.pitch_rad - in.pitch_rad) < 1e-9);
    REQUIRE(std::abs(out.yaw_rad - in.yaw_rad) < 1e-9);
  }
}

TEST_CASE("rotation angle near 0 and pi", "[rotation]") {
  for (double a : {0.0, 1e-9, 1e-4, 0.5, 2.0, std::numbers::pi - 1e-7, std::numbers::pi}) {
    const Eigen::Matrix3d R =
        Eigen::AngleAxisd(a, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
    INFO(a);
    CHECK(std::abs(rotation_angle(R) - a) < 1e-9);
  }
}

TEST_CASE("orbit frame: z to Earth, y opposite angular momentum", "[rotation]") {
  const Eigen::Vector3d r(7000e3, 100e3, -200e3), v(-100.0, 7500.0, 300.0);
  const Eigen::Matrix3d A = orbit_from_inertial(r, v);
  CHECK((A * A.transpose() - Eigen::Matrix3d::Identity()).norm() < kTol);
  CHECK(std::abs(A.determinant() - 1.0) < kTol);
  CHECK((A * (-r.normalized()) - Eigen::Vector3d::UnitZ()).norm() < kTol);
  CHECK((A * (-r.cross(v).normalized()) - Eigen::Vector3d::UnitY()).norm() < kTol);
  CHECK((A * v.normalized()).x() > 0.99);  // x ≈ velocity on a near-circular orbit
}

TEST_CASE("q_sensor_from_body: section 0's quaternion of R, canonical sign", "[rotation]") {
  std::mt19937_64 rng(2026);
  std::uniform_real_distribution<double> angle(-std::numbers::pi, std::numbers::pi);
  std::uniform_real_distribution<double> pitch(-std::numbers::pi / 2, std::numbers::pi / 2);
  for (int t = 0; t < 300; ++t) {
    const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({angle(rng), pitch(rng), angle(rng)});
    const QuaternionWxyz q = quaternion_from_dcm(R);
    REQUIRE(q.norm() == Approx(1.0).margin(1e-15));
    REQUIRE(q(0) >= 0.0);
    // v_sensor = q v_body q* = R v_body (estimation.md section 0).
    const Eigen::Vector3d v(0.3, -1.2, 2.0);
    REQUIRE((rotate_vector(q, v) - R * v).norm() < 1e-12);
    REQUIRE((dcm_from_quaternion(q) - R).norm() < 1e-12);
  }
  // Section 0's frame rotation by a small roll is the active rotation by -roll about x.
  const double a = 0.01;
  const QuaternionWxyz q_roll = quaternion_from_dcm(frame_rotation_x(a));
  CHECK(q_roll(0) == Approx(std::cos(a / 2)));
  CHECK(q_roll(1) == Approx(-std::sin(a / 2)));
  CHECK(q_roll(2) == Approx(0.0).margin(1e-15));
  CHECK(q_roll(3) == Approx(0.0).margin(1e-15));
  // Half turns (w = 0): the sign is fixed by the first component that is not zero, so an
  // upside-down mounting reads the same whatever rounding left in w.
  struct HalfTurn {
    Eigen::Vector3d axis, expected;
  };
  for (const HalfTurn& h : {HalfTurn{{1, 0, 0}, {1, 0, 0}}, HalfTurn{{0, -1, 0}, {0, 1, 0}},
                            HalfTurn{{0, 1, -1}, {0, 1, -1}}, HalfTurn{{0, -1, 1}, {0, 1, -1}},
                            HalfTurn{{-1, 2, 2}, {1, -2, -2}}}) {
    for (const double tilt : {0.0, 1e-16, -1e-16}) {
      // A half turn about the axis, nudged by rounding-level amounts either way.
      const Eigen::Matrix3d R =
          Eigen::AngleAxisd(std::numbers::pi + tilt, h.axis.normalized()).toRotationMatrix();
      const QuaternionWxyz q = quaternion_from_dcm(R);
      INFO("axis " << h.axis.transpose() << ", tilt " << tilt << ": q " << q.transpose());
      CHECK(q(0) == 0.0);
      CHECK((q.tail<3>() - h.expected.normalized()).norm() < 1e-12);
    }
  }
}
