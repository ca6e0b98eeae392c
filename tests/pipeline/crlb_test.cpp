// CRLB (estimation.md 2d): Fisher information against finite differences of the measurement
// model, agreement with the LM covariance, scaled condition numbers for good and degenerate
// geometry.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/crlb.hpp"
#include "pipeline/scalar_measurement.hpp"

using namespace magcal;

namespace {
CalibrationParameters truth_parameters() {
  CalibrationParameters p;
  p.bias_nT << 1000, 800, 900;
  p.D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  return p;
}

SampleSet model_data(const CalibrationParameters& p, int n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> mag(20000.0, 50000.0);
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + p.D).inverse();
  SampleSet s(n);
  for (int k = 0; k < n; ++k) {
    s[k].h_body_nT = Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized() * mag(rng);
    s[k].b_sensor_nT = inv * (s[k].h_body_nT + p.bias_nT);
  }
  return s;
}
}  // namespace

TEST_CASE("Fisher information equals the finite-difference construction") {
  const CalibrationParameters p = truth_parameters();
  const SampleSet s = model_data(p, 50, 3);
  const double sigma = 3.0;
  const CrlbResult r = compute_crlb(s, p, sigma);
  REQUIRE(r.ok);
  CHECK(r.n_samples == 50);
  // Independent: numerical dz/dp of predicted_scalar_measurement, variance from the true y.
  Matrix9d F = Matrix9d::Zero();
  const Vector9d p0 = p.packed();
  for (const auto& x : s) {
    RowVector9d H;
    for (int j = 0; j < 9; ++j) {
      const double h = j < 3 ? 1e-2 : 1e-7;
      Vector9d pp = p0, pm = p0;
      pp(j) += h;
      pm(j) -= h;
      H(j) = (predicted_scalar_measurement(pp, x.b_sensor_nT) -
              predicted_scalar_measurement(pm, x.b_sensor_nT)) /
             (2 * h);
    }
    const Eigen::Vector3d y = p.apply(x.b_sensor_nT);
    F += H.transpose() * H / (4 * sigma * sigma * y.squaredNorm() + 6 * std::pow(sigma, 4));
  }
  for (int i = 0; i < 9; ++i)
    for (int j = 0; j < 9; ++j)
      CHECK(r.fisher(i, j) ==
            Approx(F(i, j)).epsilon(1e-5).margin(1e-12 * F.diagonal().maxCoeff()));
  CHECK((r.covariance * r.fisher - Matrix9d::Identity()).norm() < 1e-6);
  CHECK(r.sigma(0) == Approx(std::sqrt(r.covariance(0, 0))));
}

TEST_CASE("scaled condition number: isotropic geometry is well conditioned, one direction is not") {
  const CalibrationParameters p = truth_parameters();
  const CrlbResult good = compute_crlb(model_data(p, 500, 4), p, 3.0);
  REQUIRE(good.ok);
  CHECK(good.condition_number < 100.0);
  CHECK(good.min_eigenvalue > 0.01);

  SampleSet s = model_data(p, 500, 5);
  for (auto& x : s) {
    x.h_body_nT = Eigen::Vector3d(0.3, -0.5, 0.8).normalized() * x.h_body_nT.norm();
    x.b_sensor_nT = (Eigen::Matrix3d::Identity() + p.D).inverse() * (x.h_body_nT + p.bias_nT);
  }
  const CrlbResult bad = compute_crlb(s, p, 3.0);
  CHECK_FALSE(bad.ok);
  CHECK(bad.condition_number > 1e10);
  CHECK_FALSE(bad.message.empty());
}

TEST_CASE("CRLB scales with the noise: sigma doubles -> bound roughly doubles") {
  const CalibrationParameters p = truth_parameters();
  const SampleSet s = model_data(p, 300, 6);
  const CrlbResult a = compute_crlb(s, p, 3.0), b = compute_crlb(s, p, 6.0);
  REQUIRE(a.ok);
  REQUIRE(b.ok);
  for (int i = 0; i < 9; ++i) CHECK(b.sigma(i) / a.sigma(i) == Approx(2.0).epsilon(1e-3));
}
