// HAC (Newey–West) building blocks against independent computations: the moving-sum meat equals
// the textbook double sum, the lag-window rule, the "never below white" guard; and the ellipsoid
// start recovers exact parameters from noise-free constant-field data.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/ellipsoid_fit.hpp"
#include "pipeline/hac_covariance.hpp"
#include "pipeline/parameter_recovery.hpp"

using namespace magcal;

TEST_CASE("Newey-West meat equals the textbook Bartlett double sum") {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> g(0.0, 1.0);
  std::vector<Vector9d> u(200);
  for (auto& v : u) {
    for (int i = 0; i < 9; ++i) v(i) = g(rng) * (i + 1);
  }
  for (const int L : {0, 1, 7, 40}) {
    Matrix9d direct = Matrix9d::Zero();
    for (int l = -L; l <= L; ++l) {
      const double k = 1.0 - std::abs(l) / (L + 1.0);
      for (int t = 0; t < 200; ++t) {
        const int s = t + l;
        if (s < 0 || s >= 200) continue;
        direct += k * u[static_cast<std::size_t>(t)] * u[static_cast<std::size_t>(s)].transpose();
      }
    }
    const Matrix9d fast = newey_west_meat<9>(u, L);
    INFO("L = " << L);
    CHECK((fast - direct).norm() <= 1e-10 * direct.norm());
  }
}

TEST_CASE("lag window: none for white residuals, Andrews' rule for correlated ones") {
  CHECK(bartlett_lag_window(0.01, 4320) == 0);  // below 3 / sqrt(n) = 0.046
  const int L8 = bartlett_lag_window(0.8, 4320);
  // alpha = 4 0.64 / (0.04 3.24) = 19.75; 1.1447 (19.75 4320)^(1/3) = 50.3 -> 51
  CHECK(L8 == 51);
  CHECK(bartlett_lag_window(0.3, 4320) < L8);
  CHECK(bartlett_lag_window(0.999, 100) == 25);  // capped at n / 4
  CHECK(bartlett_lag_window(std::nan(""), 100) == 0);
  std::vector<double> e(1000);
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 1.0);
  double prev = 0.0;
  for (double& x : e) x = prev = 0.8 * prev + g(rng);
  CHECK(lag1_autocorrelation(e) == Approx(0.8).margin(0.05));
}

TEST_CASE("reported covariance is never below the white-noise one, and is the HAC above it") {
  Matrix9d A = Matrix9d::Random();
  const Matrix9d white = A * A.transpose() + Matrix9d::Identity();
  // HAC larger in every direction: returned unchanged.
  const Matrix9d larger = 2.5 * white;
  CHECK((covariance_not_below(white, larger) - larger).norm() < 1e-9 * larger.norm());
  // HAC smaller in some directions: the result dominates both (C - white and C - hac PSD).
  Matrix9d mixed = white;
  mixed.row(0) *= 0.2;
  mixed.col(0) *= 0.2;
  const Matrix9d C = covariance_not_below(white, mixed);
  const Eigen::SelfAdjointEigenSolver<Matrix9d> e1(C - white), e2(C - mixed);
  CHECK(e1.eigenvalues().minCoeff() > -1e-9 * C.norm());
  CHECK(e2.eigenvalues().minCoeff() > -1e-9 * C.norm());
}

TEST_CASE("ellipsoid start: exact on noise-free constant-field data with a large offset") {
  CalibrationParameters p;
  p.bias_nT << -33516.0, -3655.0, -90315.0;
  p.D << 0.03, 0.01, -0.02, 0.01, 0.05, 0.004, -0.02, 0.004, -0.02;
  std::mt19937_64 rng(9);
  std::normal_distribution<double> g(0.0, 1.0);
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + p.D).inverse();
  SampleSet s(300);
  for (auto& c : s) {
    c.h_body_nT = Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized() * 48000.0;
    c.b_sensor_nT = inv * (c.h_body_nT + p.bias_nT);
  }
  Vector9d theta;
  REQUIRE(ellipsoid_fit_start(s, &theta));
  const RecoveryResult rec = recover_parameters(theta);
  REQUIRE(rec.ok());
  CHECK((rec.parameters.bias_nT - p.bias_nT).norm() < 1e-3);
  CHECK((rec.parameters.D - p.D).norm() < 1e-8);
  // Samples in a plane do not determine an ellipsoid.
  for (auto& c : s) c.b_sensor_nT.z() = 100.0;
  CHECK_FALSE(ellipsoid_fit_start(s, &theta));
}
