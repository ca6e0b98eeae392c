// Levenberg–Marquardt refinement (estimation.md 2b): analytic Jacobian vs finite differences,
// exact recovery on noise-free data from the centered solution and from a poor start, NEES
// consistency, and the robust (Huber IRLS) option against spikes and a wrong reference.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/centered_solution.hpp"
#include "pipeline/lm_refinement.hpp"
#include "pipeline/parameter_recovery.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/scalar_measurement.hpp"

using namespace magcal;

namespace {
constexpr double kNoiseFreeRelTol = 1e-6;

CalibrationParameters truth_parameters() {
  CalibrationParameters p;
  p.bias_nT << 1000, 800, 900;
  p.D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  return p;
}

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

void check_recovers(const Vector9d& theta, const CalibrationParameters& p, double rel_tol) {
  const RecoveryResult r = recover_parameters(theta);
  REQUIRE(r.ok());
  CHECK((r.parameters.bias_nT - p.bias_nT).norm() <= rel_tol * p.bias_nT.norm());
  CHECK((r.parameters.D - p.D).norm() <= rel_tol * p.D.norm());
}
}  // namespace

TEST_CASE("analytic |b|^2 gradient and residual Jacobian equal finite differences") {
  const Vector9d theta = theta_from_parameters(truth_parameters());
  double bsq = 0.0;
  Vector9d grad;
  REQUIRE(bias_norm_squared(theta, &bsq, &grad));
  CHECK(bsq == Approx(truth_parameters().bias_nT.squaredNorm()).epsilon(1e-12));
  const Eigen::Vector3d B(21000, -15000, 30000);
  const double zm = 1.234e8;
  const RowVector9d J = lm_residual_jacobian(theta, B);
  for (int j = 0; j < 9; ++j) {
    const double h = j < 3 ? 1e-2 : 1e-7;
    Vector9d tp = theta, tm = theta;
    tp(j) += h;
    tm(j) -= h;
    double bp = 0, bm = 0;
    bias_norm_squared(tp, &bp, nullptr);
    bias_norm_squared(tm, &bm, nullptr);
    CHECK(grad(j) == Approx((bp - bm) / (2 * h)).epsilon(1e-6).margin(1e-6));
    const double fd = (lm_residual(tp, B, zm) - lm_residual(tm, B, zm)) / (2 * h);
    CHECK(J(j) == Approx(fd).epsilon(1e-6));
  }
}

TEST_CASE("LM recovers known parameters on noise-free data") {
  const CalibrationParameters p = truth_parameters();
  const SampleSet s = model_data(p, 300, 0.0, 1);
  SECTION("from the centered solution") {
    const CenteredResult c = centered_solution(s);
    REQUIRE(c.status == CenteredStatus::kOk);
    const LmResult r = refine_lm(s, c.theta);
    CHECK(r.status == LmStatus::kOk);
    CHECK(r.converged);
    check_recovers(r.theta, p, kNoiseFreeRelTol);
  }
  SECTION("from a poor start: zero bias, D = 0") {
    const LmResult r = refine_lm(s, Vector9d::Zero());
    CHECK(r.status == LmStatus::kOk);
    check_recovers(r.theta, p, kNoiseFreeRelTol);
  }
  SECTION("from a non-positive-definite start (falls back to [c; 0])") {
    Vector9d t0 = Vector9d::Zero();
    t0(3) = -3.0;
    const LmResult r = refine_lm(s, t0);
    CHECK(r.status == LmStatus::kOk);
    check_recovers(r.theta, p, kNoiseFreeRelTol);
  }
}

TEST_CASE("LM covariance is consistent with Monte Carlo (NEES ~ chi-square 9)") {
  const CalibrationParameters p = truth_parameters();
  const Vector9d theta = theta_from_parameters(p);
  const int runs = 40;
  double nees_sum = 0.0;
  for (int run = 0; run < runs; ++run) {
    const SampleSet s = model_data(p, 400, 3.0, 2000 + run);
    const LmResult r = refine_lm(s, centered_solution(s).theta);
    REQUIRE(r.status == LmStatus::kOk);
    const Vector9d e = r.theta - theta;
    nees_sum += e.dot(r.theta_covariance.ldlt().solve(e));
  }
  // chi2(360): 99.9 % interval ~ [276, 451].
  CHECK(nees_sum > 276.0);
  CHECK(nees_sum < 451.0);
}

TEST_CASE("robust LM withstands spikes and a wrong reference, plain LM does not") {
  const CalibrationParameters p = truth_parameters();
  SampleSet s = model_data(p, 600, 3.0, 77);
  const SampleSet clean = s;
  // 6 spikes of 5 000 nT on one axis, 4 samples with a wrong reference (another sample's |h|
  // scaled by 0.8).
  for (int k : {10, 50, 120, 300, 410, 555}) s[k].b_sensor_nT(k % 3) += 5000.0;
  for (int k : {33, 222, 444, 590}) s[k].h_body_nT *= 0.8;

  LmOptions robust;
  robust.robust = true;
  const LmResult clean_fit = refine_lm(clean, centered_solution(clean).theta);
  const LmResult plain = refine_lm(s, centered_solution(s).theta);
  const LmResult rob = refine_lm(s, centered_solution(s).theta, robust);
  REQUIRE(rob.status == LmStatus::kOk);
  const auto bias = [](const LmResult& r) {
    return recover_parameters(r.theta).parameters.bias_nT;
  };
  const double sigma_b =
      std::sqrt(recover_parameters(clean_fit.theta, &clean_fit.theta_covariance).covariance(0, 0));
  const double err_plain = (bias(plain) - p.bias_nT).norm();
  const double err_robust = (bias(rob) - p.bias_nT).norm();
  INFO("plain " << err_plain << " nT, robust " << err_robust << " nT, sigma " << sigma_b);
  CHECK(err_plain > 20.0 * sigma_b);  // the corruption matters...
  CHECK(err_robust < 5.0 * sigma_b);  // ...and the robust fit shrugs it off
  CHECK(rob.n_downweighted >= 10);
  CHECK(rob.n_downweighted < 30);  // clean samples keep full weight (k = 3)

  // On clean data robust = plain to well within the noise.
  const LmResult rob_clean = refine_lm(clean, centered_solution(clean).theta, robust);
  CHECK((bias(rob_clean) - bias(clean_fit)).norm() < 0.2 * sigma_b);
}

TEST_CASE("LM: too few samples, NaN input, invalid options") {
  const CalibrationParameters p = truth_parameters();
  CHECK(refine_lm(model_data(p, 5, 3.0, 1), Vector9d::Zero()).status == LmStatus::kTooFewSamples);
  SampleSet s = model_data(p, 100, 3.0, 2);
  s[3].h_body_nT(0) = INFINITY;
  CHECK(refine_lm(s, Vector9d::Zero()).status == LmStatus::kInvalidInput);
  LmOptions bad;
  bad.max_iterations = 0;
  CHECK(refine_lm(model_data(p, 100, 3.0, 2), Vector9d::Zero(), bad).status ==
        LmStatus::kInvalidInput);
}
