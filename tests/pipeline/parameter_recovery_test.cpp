// Recovery of b, D from theta = [c; E] (estimation.md 2c): round trips, failure on non-PD, the
// analytic Jacobian against finite differences and the mapped covariance against Monte Carlo
// of the map itself.
#include <cmath>
#include <random>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/parameter_recovery.hpp"

using namespace magcal;

namespace {
constexpr double kRoundTripTol = 1e-12;  // relative, double-precision map

CalibrationParameters random_parameters(std::mt19937_64& rng, double d_scale) {
  std::normal_distribution<double> n(0.0, 1.0);
  CalibrationParameters p;
  p.bias_nT = Eigen::Vector3d(n(rng), n(rng), n(rng)) * 3000.0;
  Vector6d d;
  for (int i = 0; i < 6; ++i) d(i) = n(rng) * d_scale;
  p.D = unpack_symmetric(d);
  return p;
}
}  // namespace

TEST_CASE("recovery round-trips (b, D) -> theta -> (b, D)") {
  std::mt19937_64 rng(42);
  for (double d_scale : {0.0, 0.01, 0.05, 0.2}) {
    for (int i = 0; i < 50; ++i) {
      const CalibrationParameters p = random_parameters(rng, d_scale);
      const RecoveryResult r = recover_parameters(theta_from_parameters(p));
      REQUIRE(r.ok());
      CHECK((r.parameters.bias_nT - p.bias_nT).norm() <=
            kRoundTripTol * (1.0 + p.bias_nT.norm()) * 10);
      CHECK((r.parameters.D - p.D).norm() <= kRoundTripTol * 10);
      CHECK((r.parameters.D - r.parameters.D.transpose()).norm() == 0.0);
    }
  }
}

TEST_CASE("recovery reports failure, never NaN, when I + E is not positive definite") {
  Vector9d theta = Vector9d::Zero();
  theta.head<3>() << 100, 200, 300;
  theta(3) = -1.5;  // I + E has eigenvalue -0.5
  const RecoveryResult r = recover_parameters(theta);
  CHECK(r.status == RecoveryStatus::kNotPositiveDefinite);
  CHECK_FALSE(r.message.empty());
  CHECK(r.parameters.packed().allFinite());

  theta(3) = -1.0;  // exactly singular
  CHECK(recover_parameters(theta).status == RecoveryStatus::kNotPositiveDefinite);

  theta(3) = std::nan("");
  CHECK(recover_parameters(theta).status == RecoveryStatus::kInvalidInput);
}

TEST_CASE("theta_jacobian equals central finite differences") {
  std::mt19937_64 rng(7);
  const CalibrationParameters p = random_parameters(rng, 0.03);
  const Matrix9d J = theta_jacobian(p);
  const Vector9d p0 = p.packed();
  for (int j = 0; j < 9; ++j) {
    const double h = j < 3 ? 1e-3 : 1e-6;
    Vector9d pp = p0, pm = p0;
    pp(j) += h;
    pm(j) -= h;
    const Vector9d fd = (theta_from_parameters(CalibrationParameters::from_packed(pp)) -
                         theta_from_parameters(CalibrationParameters::from_packed(pm))) /
                        (2 * h);
    for (int i = 0; i < 9; ++i) {
      CHECK(J(i, j) == Approx(fd(i)).margin(1e-6).epsilon(1e-6));
    }
  }
}

TEST_CASE("mapped covariance matches Monte Carlo of the recovery map") {
  std::mt19937_64 rng(11);
  const CalibrationParameters p = random_parameters(rng, 0.02);
  const Vector9d theta = theta_from_parameters(p);
  // A small, correlated theta covariance (linear regime).
  Matrix9d A = Matrix9d::Random() * 0.1;
  Vector9d scale;
  scale << 1, 1, 1, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4;
  Matrix9d C = scale.asDiagonal() * (A * A.transpose() + Matrix9d::Identity()) * scale.asDiagonal();
  const RecoveryResult r = recover_parameters(theta, &C);
  REQUIRE(r.ok());
  const Eigen::LLT<Matrix9d> llt(C);
  std::normal_distribution<double> n(0.0, 1.0);
  const int runs = 4000;
  Matrix9d S = Matrix9d::Zero();
  for (int k = 0; k < runs; ++k) {
    Vector9d e;
    for (int i = 0; i < 9; ++i) e(i) = n(rng);
    const RecoveryResult rk = recover_parameters(theta + llt.matrixL() * e);
    REQUIRE(rk.ok());
    const Vector9d d = rk.parameters.packed() - p.packed();
    S += d * d.transpose();
  }
  S /= runs;
  // Diagonals within 3 standard errors of a variance estimate (sqrt(2/runs) ~ 2.2 %).
  constexpr double kVarianceTol = 0.07;
  for (int i = 0; i < 9; ++i) {
    CHECK(S(i, i) == Approx(r.covariance(i, i)).epsilon(kVarianceTol));
  }
}
