// Centered solution (estimation.md 2a): exact on noise-free model data, covariance consistent
// with Monte Carlo, clean statuses for too few samples, NaN and degenerate geometry.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/centered_solution.hpp"
#include "pipeline/parameter_recovery.hpp"
#include "pipeline/rotation.hpp"

using namespace magcal;

namespace {
constexpr double kNoiseFreeRelTol = 1e-6;

CalibrationParameters truth_parameters() {
  CalibrationParameters p;
  p.bias_nT << 1000, -800, 900;
  p.D << 0.01, 0.01, -0.01, 0.01, 0.02, 0.005, -0.01, 0.005, -0.015;
  return p;
}

// Estimation-model data: random directions, |h| in [20 000, 50 000] nT.
SampleSet model_data(const CalibrationParameters& p, int n, double sigma, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> mag(20000.0, 50000.0);
  const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({0.017, 0.035, 0.017});
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + p.D).inverse();
  SampleSet s(n);
  for (int k = 0; k < n; ++k) {
    const Eigen::Vector3d dir = Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized();
    s[k].utime = k * 10'000'000LL;
    s[k].h_body_nT = dir * mag(rng);
    const Eigen::Vector3d eps(g(rng), g(rng), g(rng));
    s[k].b_sensor_nT = inv * (R * s[k].h_body_nT + p.bias_nT + sigma * eps);
  }
  return s;
}
}  // namespace

TEST_CASE("centered solution is exact on noise-free model data") {
  const CalibrationParameters p = truth_parameters();
  const SampleSet s = model_data(p, 300, 0.0, 1);
  const CenteredResult r = centered_solution(s);
  REQUIRE(r.status == CenteredStatus::kOk);
  const Vector9d theta = theta_from_parameters(p);
  CHECK((r.theta.head<3>() - theta.head<3>()).norm() <= kNoiseFreeRelTol * theta.head<3>().norm());
  CHECK((r.theta.tail<6>() - theta.tail<6>()).norm() <= kNoiseFreeRelTol * theta.tail<6>().norm());
  const RecoveryResult rec = recover_parameters(r.theta);
  REQUIRE(rec.ok());
  CHECK((rec.parameters.bias_nT - p.bias_nT).norm() <= kNoiseFreeRelTol * p.bias_nT.norm());
}

TEST_CASE("centered covariance is consistent with Monte Carlo (NEES ~ chi-square 9)") {
  const CalibrationParameters p = truth_parameters();
  const Vector9d theta = theta_from_parameters(p);
  const int runs = 40;
  double nees_sum = 0.0;
  for (int run = 0; run < runs; ++run) {
    const SampleSet s = model_data(p, 400, 3.0, 1000 + run);
    const CenteredResult r = centered_solution(s);
    REQUIRE(r.status == CenteredStatus::kOk);
    const Vector9d e = r.theta - theta;
    nees_sum += e.dot(r.theta_covariance.ldlt().solve(e));
  }
  // Sum of 40 chi2(9) = chi2(360): 99.9 % interval ~ [276, 451].
  CHECK(nees_sum > 276.0);
  CHECK(nees_sum < 451.0);
}

TEST_CASE("centered solution: too few samples, NaN, degenerate geometry") {
  const CalibrationParameters p = truth_parameters();
  SampleSet s = model_data(p, 9, 3.0, 2);
  CHECK(centered_solution(s).status == CenteredStatus::kTooFewSamples);

  s = model_data(p, 100, 3.0, 3);
  s[17].b_sensor_nT(1) = std::nan("");
  const CenteredResult nan_r = centered_solution(s);
  CHECK(nan_r.status == CenteredStatus::kInvalidInput);
  CHECK(nan_r.message.find("17") != std::string::npos);

  s = model_data(p, 100, 3.0, 4);
  s[5].h_body_nT.setZero();
  CHECK(centered_solution(s).status == CenteredStatus::kInvalidInput);

  // All samples along one direction (only the magnitude varies): singular.
  s = model_data(p, 100, 0.0, 5);
  for (auto& x : s) {
    const double m = x.h_body_nT.norm();
    x.h_body_nT = Eigen::Vector3d(1, 2, 3).normalized() * m;
    x.b_sensor_nT = (Eigen::Matrix3d::Identity() + p.D).inverse() * (x.h_body_nT + p.bias_nT);
  }
  const CenteredResult deg = centered_solution(s);
  CHECK(deg.status == CenteredStatus::kSingular);
  CHECK_FALSE(deg.message.empty());

  CenteredOptions bad;
  bad.sigma_nT = -1;
  CHECK_FALSE(bad.validate().empty());
  CHECK(centered_solution(model_data(p, 100, 3.0, 6), bad).status == CenteredStatus::kInvalidInput);
}
