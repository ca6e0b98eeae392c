// Monte-Carlo coverage of the batch refit over noise and attitude coverage (issue 20, item 1):
// bench-style captures (a sensor turned through all yaw, tilted at most +-20..60 deg, with or
// without being turned upside down; constant or varying |h|; 30-300 nT white noise). An accepted
// result must lie within 3 of its sigmas, per parameter, in at least 99 % of the accepted
// results, and nothing may be accepted that the fit without the bias correction (today's
// estimator through the same gates) refuses. Truth: the generator's parameters.
#include <cmath>
#include <cstdio>
#include <random>

#include <catch2/catch.hpp>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/rotation.hpp"

using namespace magcal;

namespace {

struct BenchCase {
  double noise_nT = 150.0;
  double tilt_deg = 45.0;
  bool inversion = false;  // every other sample turned upside down
  bool varying_h = false;  // |h| uniform in 30 000..50 000 nT, else 48 000 nT
};

constexpr int kSamples = 1500;

// Samples of the estimation model (estimation.md section 1) for a sensor on a bench: the lab
// field at 60 deg inclination seen at yaw uniform in 360 deg and roll, pitch uniform in
// +-tilt_deg (plus 180 deg of roll for the inverted half). b within +-1500 nT, D within +-0.03
// (diagonal) and +-0.01, a (1, 2, 1) deg installation rotation; *p_true = [b; D].
SampleSet bench_capture(const BenchCase& c, uint64_t seed, Vector9d* p_true) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const Eigen::Vector3d b(1500.0 * u(rng), 1500.0 * u(rng), 1500.0 * u(rng));
  Vector6d d;
  d << 0.03 * u(rng), 0.03 * u(rng), 0.03 * u(rng), 0.01 * u(rng), 0.01 * u(rng), 0.01 * u(rng);
  *p_true << b, d;
  const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({0.017, 0.035, 0.017});
  const Eigen::Matrix3d to_sensor = (Eigen::Matrix3d::Identity() + unpack_symmetric(d)).inverse();
  const double inclination = 60.0 * kDegToRad;
  const Eigen::Vector3d lab_direction(std::cos(inclination), 0.0, std::sin(inclination));
  const double tilt = c.tilt_deg * kDegToRad;
  SampleSet s(kSamples);
  for (int k = 0; k < kSamples; ++k) {
    const double yaw = M_PI * u(rng), pitch = tilt * u(rng);
    const double roll = tilt * u(rng) + (c.inversion && k % 2 == 1 ? M_PI : 0.0);
    const double magnitude_nT = c.varying_h ? 40000.0 + 10000.0 * u(rng) : 48000.0;
    const Eigen::Vector3d h =
        dcm_from_roll_pitch_yaw({roll, pitch, yaw}) * (magnitude_nT * lab_direction);
    const Eigen::Vector3d eps(normal(rng), normal(rng), normal(rng));
    s[k].utime = 1'600'000'000'000'000LL + k * 1'000'000LL;
    s[k].h_body_nT = h;
    s[k].b_sensor_nT = to_sensor * (R * h + b + c.noise_nT * eps);
  }
  return s;
}

BatchCalibrationOptions bench_options(double noise_nT, bool bias_correction) {
  BatchCalibrationOptions o;
  o.sigma_nT = noise_nT;
  // As magcal fit sets it: the residual a sensor of this noise leaves.
  o.gate_options.expected_residual_nT = std::max(o.gate_options.expected_residual_nT, noise_nT);
  o.bias_correction = bias_correction;
  return o;
}

// Per parameter: accepted results whose |error| <= 3 reported sigmas.
struct Coverage {
  int accepted = 0;
  Eigen::Matrix<int, 9, 1> within = Eigen::Matrix<int, 9, 1>::Zero();
  void add(const CalibrationResult& r, const Vector9d& p_true) {
    ++accepted;
    const Vector9d err = r.parameters.packed() - p_true;
    const Vector9d sigma = r.covariance.diagonal().cwiseSqrt();
    for (int i = 0; i < 9; ++i) within(i) += std::abs(err(i)) <= 3.0 * sigma(i) ? 1 : 0;
  }
  // 0 when nothing was accepted: no result, no coverage shown.
  double worst_fraction() const {
    return accepted == 0 ? 0.0 : static_cast<double>(within.minCoeff()) / accepted;
  }
  void print(const char* label) const {
    std::printf(
        "%-14s accepted %4d, within 3 sigma per parameter (b1 b2 b3 D11 D22 D33 D12 D13 "
        "D23):",
        label, accepted);
    for (int i = 0; i < 9; ++i) std::printf(" %d", within(i));
    std::printf("  worst %.2f %%\n", 100.0 * worst_fraction());
  }
};

}  // namespace

TEST_CASE("bench captures, 30-300 nT noise, tilt +-20..60 deg: accepted means within 3 sigma") {
  // 72 cases x 10 draws; each case's draws independent of every other's. The estimator is
  // nearly linear in the noise, so reusing draws across noise levels would repeat one outcome.
  constexpr int kDraws = 10;
  Coverage corrected, uncorrected;
  int accepted_only_with_correction = 0;
  uint64_t case_index = 0;
  for (double noise_nT : {30.0, 100.0, 300.0}) {
    for (bool varying_h : {false, true}) {
      for (double tilt_deg : {20.0, 30.0, 40.0, 45.0, 50.0, 60.0}) {
        for (bool inversion : {false, true}) {
          const BenchCase c{noise_nT, tilt_deg, inversion, varying_h};
          ++case_index;
          for (int draw = 0; draw < kDraws; ++draw) {
            Vector9d p_true;
            const SampleSet samples = bench_capture(c, 1000 * case_index + draw, &p_true);
            const CalibrationResult with = calibrate_batch(samples, bench_options(noise_nT, true));
            const CalibrationResult without =
                calibrate_batch(samples, bench_options(noise_nT, false));
            if (with.accepted) corrected.add(with, p_true);
            if (without.accepted) uncorrected.add(without, p_true);
            if (with.accepted && !without.accepted) ++accepted_only_with_correction;
          }
        }
      }
    }
  }
  corrected.print("corrected");
  uncorrected.print("uncorrected");
  CHECK(accepted_only_with_correction == 0);
  CHECK(corrected.accepted >= uncorrected.accepted * 9 / 10);  // the correction refuses little
  // Enough accepted results for a 1 % bar to resolve one miss in a hundred.
  CHECK(corrected.accepted >= 100);
  CHECK(corrected.worst_fraction() >= 0.99);
}

TEST_CASE("bench capture of issue 20 (150 nT, tilt +-45 deg, never inverted): b_z unbiased") {
  // Today's least-squares optimum puts b_z and the scale factors 2-2.5 sigma low on average
  // (5-6 sigma on single seeds); the corrected estimate's mean error over draws is a small
  // fraction of its sigma, with and without --robust.
  constexpr int kDraws = 24;
  for (bool robust : {false, true}) {
    Eigen::Vector3d mean_z = Eigen::Vector3d::Zero(), mean_z_uncorrected = Eigen::Vector3d::Zero();
    int corrected_runs = 0;
    for (int draw = 0; draw < kDraws; ++draw) {
      Vector9d p_true;
      const SampleSet samples = bench_capture({150.0, 45.0, false, false}, 77 + draw, &p_true);
      BatchCalibrationOptions o = bench_options(150.0, true);
      o.robust = robust;
      const CalibrationResult r = calibrate_batch(samples, o);
      o.bias_correction = false;
      const CalibrationResult r0 = calibrate_batch(samples, o);
      REQUIRE(r.accepted);
      REQUIRE(r0.accepted);
      if (r.estimator_bias.squaredNorm() > 0.0) ++corrected_runs;
      // b_z, D11, D33: the components the missing inversion leaves weakly determined.
      for (int j = 0; j < 3; ++j) {
        const int i = j == 0 ? 2 : j == 1 ? 3 : 5;
        mean_z(j) += (r.parameters.packed()(i) - p_true(i)) / std::sqrt(r.covariance(i, i));
        mean_z_uncorrected(j) +=
            (r0.parameters.packed()(i) - p_true(i)) / std::sqrt(r0.covariance(i, i));
      }
    }
    mean_z /= kDraws;
    mean_z_uncorrected /= kDraws;
    INFO("robust " << robust << ": mean error / sigma of b_z, D11, D33: corrected "
                   << mean_z.transpose() << ", uncorrected " << mean_z_uncorrected.transpose());
    CHECK(corrected_runs == kDraws);
    CHECK(mean_z_uncorrected.maxCoeff() < -1.5);  // the bias the correction is for
    CHECK(mean_z.cwiseAbs().maxCoeff() < 0.5);
  }
}
