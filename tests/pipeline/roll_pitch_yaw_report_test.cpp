// Roll, pitch, yaw near gimbal lock (issue 20), Monte-Carlo over noise draws of the Procrustes
// alignment against the rotation it did not see: at and near pitch +-90 deg the reported angles
// are the canonical split (stable), the determined combination and pitch are within their sigmas
// (RMS of error / sigma ~ 1); far from the pole the angles are section 0's extraction, each
// within its sigma.
#include "pipeline/roll_pitch_yaw_report.hpp"

#include <cmath>
#include <limits>
#include <numbers>
#include <random>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/alignment.hpp"

using namespace magcal;

namespace {

constexpr double kNoise_nT = 3.0;
constexpr double kField_nT = 30000.0;
constexpr int kPairs = 300;
constexpr int kDraws = 400;
// RMS of error / sigma over kDraws: standard error ~ 1 / sqrt(2 kDraws) = 3.5 %.
constexpr double kRmsLow = 0.85, kRmsHigh = 1.15;

double wrapped(double a) {
  return std::remainder(a, 2.0 * std::numbers::pi);
}

// Field directions spread unevenly (z squeezed), so the rotation covariance is anisotropic and
// a wrong gradient direction would show.
std::vector<AlignmentPair> simulate(const Eigen::Matrix3d& R, std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  std::vector<AlignmentPair> pairs;
  for (int k = 0; k < kPairs; ++k) {
    const Eigen::Vector3d h =
        kField_nT * Eigen::Vector3d(n(rng), n(rng), 0.3 * n(rng)).normalized();
    const Eigen::Vector3d noise = kNoise_nT * Eigen::Vector3d(n(rng), n(rng), n(rng));
    pairs.push_back({R * h + noise, h});
  }
  return pairs;
}

struct Rms {
  double sum = 0.0;
  int n = 0;
  void add(double err, double sigma) {
    sum += (err / sigma) * (err / sigma);
    ++n;
  }
  double value() const { return std::sqrt(sum / n); }
};

}  // namespace

TEST_CASE("gimbal lock: canonical roll/yaw split near pitch +-90 deg, honest combination sigma",
          "[roll_pitch_yaw_report][monte_carlo]") {
  const double margin = kDefaultGimbalLockMargin_deg * kDegToRad;
  const double roll_true = 30.0 * kDegToRad, yaw_true = -50.0 * kDegToRad;
  for (const double pitch_deg : {90.0, -90.0, 89.5, -89.9, 88.5}) {
    INFO("pitch " << pitch_deg << " deg");
    const Eigen::Matrix3d R_true =
        dcm_from_roll_pitch_yaw({roll_true, pitch_deg * kDegToRad, yaw_true});
    const RollPitchYawReport truth = roll_pitch_yaw_report(R_true, Eigen::Matrix3d::Zero(), margin);
    REQUIRE(truth.singular);
    // The roll-0 angles reproduce R only at the pole; off it they are off by about
    // |roll| cos(pitch), which the report states (the quaternion is exact).
    const double moved_roll_rad = roll_true * std::cos(pitch_deg * kDegToRad);
    WARN("pitch " << pitch_deg << ": the canonical angles differ from R by "
                  << truth.canonical_rotation_error_rad * kRadToDeg << " deg (|roll| cos(pitch) "
                  << std::abs(moved_roll_rad) * kRadToDeg << " deg)");
    CHECK(truth.canonical_rotation_error_rad ==
          Approx(std::abs(moved_roll_rad)).epsilon(0.05).margin(1e-9));
    std::mt19937 rng(static_cast<uint32_t>(1000 + 10 * pitch_deg));
    Rms combination, pitch;
    double spread_rad = 0.0, raw_roll_min = 10.0, raw_roll_max = -10.0;
    for (int k = 0; k < kDraws; ++k) {
      const AlignmentResult a = align_procrustes(simulate(R_true, rng), {.sigma_nT = kNoise_nT});
      REQUIRE(a.ok());
      const Eigen::Matrix3d& R = a.estimate.R_sensor_from_body;
      const RollPitchYawReport r =
          roll_pitch_yaw_report(R, a.estimate.angle_covariance_rad2, margin);
      REQUIRE(r.singular);
      CHECK(r.rpy.roll_rad == 0.0);
      CHECK(std::isnan(r.sigma_rad(0)));
      CHECK(std::isnan(r.sigma_rad(2)));
      CHECK(r.rpy.yaw_rad == r.combination_rad);
      CHECK(std::string(r.combination_name) ==
            (pitch_deg > 0 ? "yaw_minus_roll" : "yaw_plus_roll"));
      const double err = wrapped(r.combination_rad - truth.combination_rad);
      combination.add(err, r.combination_sigma_rad);
      pitch.add(r.rpy.pitch_rad - truth.rpy.pitch_rad, r.sigma_rad(1));
      spread_rad = std::max(spread_rad, std::abs(err));
      const double raw_roll = roll_pitch_yaw_from_dcm(R).roll_rad;
      raw_roll_min = std::min(raw_roll_min, raw_roll);
      raw_roll_max = std::max(raw_roll_max, raw_roll);
    }
    WARN("pitch " << pitch_deg << ": RMS err/sigma " << truth.combination_name << " "
                  << combination.value() << ", pitch " << pitch.value()
                  << "; largest combination error " << spread_rad * kRadToDeg
                  << " deg; section 0's raw roll spans "
                  << (raw_roll_max - raw_roll_min) * kRadToDeg << " deg over the draws");
    CHECK(combination.value() > kRmsLow);
    CHECK(combination.value() < kRmsHigh);
    CHECK(pitch.value() > kRmsLow);
    CHECK(pitch.value() < kRmsHigh);
    // Stable: every draw within a few sigmas of the truth (sigma ~2e-4 deg here).
    CHECK(spread_rad * kRadToDeg < 0.01);
  }
}

TEST_CASE("roll/pitch/yaw away from the pole: section 0's angles, each within its sigma",
          "[roll_pitch_yaw_report][monte_carlo]") {
  const double margin = kDefaultGimbalLockMargin_deg * kDegToRad;
  struct Case {
    double roll_deg, pitch_deg, yaw_deg;
  };
  // The paper's small misalignment, large mounting angles, and just outside the margin.
  for (const Case c : {Case{1.0, 2.0, 1.0}, Case{30.0, 45.0, -50.0}, Case{-120.0, -70.0, 160.0},
                       Case{30.0, 87.0, -50.0}}) {
    INFO("roll " << c.roll_deg << " pitch " << c.pitch_deg << " yaw " << c.yaw_deg);
    const RollPitchYaw rpy_true{c.roll_deg * kDegToRad, c.pitch_deg * kDegToRad,
                                c.yaw_deg * kDegToRad};
    const Eigen::Matrix3d R_true = dcm_from_roll_pitch_yaw(rpy_true);
    std::mt19937 rng(static_cast<uint32_t>(7 + c.pitch_deg));
    Rms rms[3], rms_rotation_diag[3];
    double worst_sigma_change = 0.0;
    for (int k = 0; k < kDraws; ++k) {
      const AlignmentResult a = align_procrustes(simulate(R_true, rng), {.sigma_nT = kNoise_nT});
      REQUIRE(a.ok());
      const Eigen::Matrix3d& R = a.estimate.R_sensor_from_body;
      const Eigen::Matrix3d& P = a.estimate.angle_covariance_rad2;
      const RollPitchYawReport r = roll_pitch_yaw_report(R, P, margin);
      REQUIRE_FALSE(r.singular);
      // The angles themselves are section 0's extraction, unchanged.
      const RollPitchYaw raw = roll_pitch_yaw_from_dcm(R);
      CHECK(r.rpy.roll_rad == raw.roll_rad);
      CHECK(r.rpy.pitch_rad == raw.pitch_rad);
      CHECK(r.rpy.yaw_rad == raw.yaw_rad);
      const double err[3] = {wrapped(raw.roll_rad - rpy_true.roll_rad),
                             raw.pitch_rad - rpy_true.pitch_rad,
                             wrapped(raw.yaw_rad - rpy_true.yaw_rad)};
      for (int i = 0; i < 3; ++i) {
        rms[i].add(err[i], r.sigma_rad(i));
        rms_rotation_diag[i].add(err[i], std::sqrt(P(i, i)));
        worst_sigma_change =
            std::max(worst_sigma_change, std::abs(r.sigma_rad(i) / std::sqrt(P(i, i)) - 1.0));
      }
    }
    WARN("RMS err/sigma roll " << rms[0].value() << " pitch " << rms[1].value() << " yaw "
                               << rms[2].value() << "; with sqrt(diag) of the rotation covariance "
                               << rms_rotation_diag[0].value() << " "
                               << rms_rotation_diag[1].value() << " "
                               << rms_rotation_diag[2].value() << "; largest sigma change "
                               << worst_sigma_change);
    for (int i = 0; i < 3; ++i) {
      CHECK(rms[i].value() > kRmsLow);
      CHECK(rms[i].value() < kRmsHigh);
    }
    // At the paper's small angles the sigmas are those of the rotation covariance (to first order
    // in the angles: a few percent at 2 deg).
    if (std::abs(c.pitch_deg) < 5.0) CHECK(worst_sigma_change < 0.06);
  }
}

TEST_CASE("gimbal lock margin: configurable, 0 flags only the pole itself",
          "[roll_pitch_yaw_report]") {
  const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() * 1e-10;
  const Eigen::Matrix3d R88 = dcm_from_roll_pitch_yaw({0.3, 88.0 * kDegToRad, -0.2});
  CHECK(roll_pitch_yaw_report(R88, P, 2.5 * kDegToRad).singular);
  CHECK_FALSE(roll_pitch_yaw_report(R88, P, 1.5 * kDegToRad).singular);
  const Eigen::Matrix3d R90 = dcm_from_roll_pitch_yaw({0.3, 90.0 * kDegToRad, -0.2});
  const RollPitchYawReport at_pole = roll_pitch_yaw_report(R90, P, 0.0);
  CHECK(at_pole.singular);
  // yaw - roll = -0.5 rad, whatever the rounding noise in roll and yaw alone.
  CHECK(at_pole.combination_rad == Approx(-0.5).margin(1e-12));
  CHECK(at_pole.rpy.yaw_rad == at_pole.combination_rad);
  const Eigen::Matrix3d Rm90 = dcm_from_roll_pitch_yaw({0.3, -90.0 * kDegToRad, -0.2});
  CHECK(roll_pitch_yaw_report(Rm90, P, 0.0).combination_rad == Approx(0.1).margin(1e-12));
  // The canonical angles rebuild the rotation at the pole.
  CHECK((dcm_from_roll_pitch_yaw(at_pole.rpy) - R90).norm() < 1e-9);
}

TEST_CASE("an unknown rotation covariance (NaN) gives unknown sigmas, never 0",
          "[roll_pitch_yaw_report]") {
  const Eigen::Matrix3d unknown =
      Eigen::Matrix3d::Constant(std::numeric_limits<double>::quiet_NaN());
  for (const double pitch_deg : {2.0, 90.0}) {
    INFO("pitch " << pitch_deg << " deg");
    const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({0.3, pitch_deg * kDegToRad, -0.2});
    const RollPitchYawReport r =
        roll_pitch_yaw_report(R, unknown, kDefaultGimbalLockMargin_deg * kDegToRad);
    CHECK(r.singular == (pitch_deg == 90.0));
    for (int i = 0; i < 3; ++i) CHECK(std::isnan(r.sigma_rad(i)));
    CHECK(std::isnan(r.combination_sigma_rad));
    // The angles come from R alone.
    CHECK(r.rpy.pitch_rad == Approx(pitch_deg * kDegToRad));
  }
}
