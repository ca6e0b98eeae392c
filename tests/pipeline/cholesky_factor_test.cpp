#include "pipeline/cholesky_factor.hpp"

#include <cmath>
#include <random>

#include <Eigen/Cholesky>
#include <catch2/catch.hpp>

using namespace magcal;

TEST_CASE("Rank-1 Cholesky downdate equals the covariance-form update") {
  std::mt19937_64 rng(17);
  std::normal_distribution<double> n(0.0, 1.0);
  Matrix9d A;
  for (int i = 0; i < 81; ++i) A(i) = n(rng);
  const Matrix9d P = A * A.transpose() + Matrix9d::Identity();
  const Matrix9d S0 = Eigen::LLT<Matrix9d>(P).matrixL();
  Vector9d v;
  for (int i = 0; i < 9; ++i) v(i) = n(rng);
  // Downdate by K sqrt(S_y) with S_y = v^T P v + R, R > 0: P - P v v^T P / S_y stays PD.
  const Vector9d Pv = P * v;
  const double S_y = v.dot(Pv) + 0.01;
  const Vector9d u = Pv / std::sqrt(S_y);
  Matrix9d S = S0;
  REQUIRE(cholesky_downdate_whitened(S, S0.triangularView<Eigen::Lower>().solve(u)));
  CHECK(S.isLowerTriangular());
  const Matrix9d expected = P - Pv * Pv.transpose() / S_y;
  CHECK((S * S.transpose() - expected).norm() < 1e-9 * expected.norm());
  CHECK((S.diagonal().array() > 0.0).all());
  // A downdate that would make P indefinite is refused.
  S = S0;
  CHECK_FALSE(cholesky_downdate_whitened(
      S, S0.triangularView<Eigen::Lower>().solve(2.0 * Pv / std::sqrt(v.dot(Pv)))));
  CHECK(S == S0);
}

TEST_CASE("Lower triangular times a vector reads the lower triangle only") {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> n(0.0, 1.0);
  Matrix9d L;
  Vector9d v;
  for (int i = 0; i < 81; ++i) L(i) = n(rng);
  for (int i = 0; i < 9; ++i) v(i) = n(rng);
  const Vector9d expected = L.triangularView<Eigen::Lower>() * v;
  CHECK((lower_triangular_times(L, v) - expected).norm() < 1e-13 * expected.norm());
}
