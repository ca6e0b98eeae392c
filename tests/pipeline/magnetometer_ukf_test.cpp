// MagnetometerUkf: unscented-transform moments against the exact Gaussian moments of the
// quadratic measurement, the square-root downdate against the covariance form, recovery of known
// parameters, the covariance guard, input validation, save/restore, no allocation per update.
// Consistency studies: filter_consistency_test.cpp.
#include "pipeline/magnetometer_ukf.hpp"

#include <cmath>
#include <limits>
#include <variant>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <catch2/catch.hpp>

#include "tests/test_skip.hpp"

#include "pipeline/scalar_measurement.hpp"
#include "tests/pipeline/filter_test_support.hpp"

using namespace magcal;
using namespace magcal::test;

namespace {

constexpr double kSigma_nT = 3.0;
constexpr double kNoiseFreeSigma_nT = 1e-3;
constexpr double kNoiseFreeBiasTol_nT = 1e-3;
constexpr double kNoiseFreeDTol = 1e-7;
constexpr double kMomentRelTol = 1e-9;

// M = dy/dp of y(p) = (I + D) B - b, by central differences (y is linear in p, so exact).
Eigen::Matrix<double, 3, 9> dy_dp(const Eigen::Vector3d& B) {
  Eigen::Matrix<double, 3, 9> M;
  for (int i = 0; i < 9; ++i) {
    Vector9d e = Vector9d::Zero();
    e(i) = 1.0;
    M.col(i) = 0.5 * (CalibrationParameters::from_packed(e).apply(B) -
                      CalibrationParameters::from_packed(-e).apply(B));
  }
  return M;
}

}  // namespace

TEST_CASE("UKF predicted measurement and cross-covariance equal the exact Gaussian moments") {
  // h(x + d) = |B|^2 - |y0 + M d|^2 is quadratic in d ~ N(0, P), so exactly
  //   E[h] = h(x) - tr(M P M^T),  Cov(d, h) = -2 P M^T y0.
  // The scaled UT with the symmetric 2n+1 points reproduces both (it is exact to 2nd order).
  const Vector9d x = paper_parameters();
  Matrix9d P = warm_covariance();
  P(0, 4) = P(4, 0) = 0.3 * std::sqrt(P(0, 0) * P(4, 4));  // some correlation
  const Eigen::Vector3d B(21000.0, -17000.0, 30000.0);
  const double h_norm = 40000.0;
  MagnetometerUkf::Options o;
  o.gate_nis = 0.0;
  for (double kappa : {-6.0, 0.0}) {  // W0c = 0 (default) and W0c = 2
    o.kappa = kappa;
    MagnetometerUkf f(o);
    f.initialize(x, P);
    const FilterUpdate u = f.update(B, h_norm, kSimStartUtime);
    REQUIRE(u.status == FilterUpdateStatus::kAccepted);
    const double y = scalar_measurement(B, h_norm) - scalar_noise_mean(o.sigma_nT);
    const double y_hat = y - u.innovation_nT2;
    const Eigen::Matrix<double, 3, 9> M = dy_dp(B);
    const Eigen::Vector3d y0 = CalibrationParameters::from_packed(x).apply(B);
    const double expected_mean =
        predicted_scalar_measurement(x, B) - (M * P * M.transpose()).trace();
    CHECK(y_hat == Approx(expected_mean).epsilon(kMomentRelTol));
    // K = Pxz / S and x_new = x + K nu  =>  Pxz = (x_new - x) S / nu.
    const Vector9d Pxz = (f.x() - x) * u.innovation_variance_nT4 / u.innovation_nT2;
    const Vector9d expected_Pxz = -2.0 * P * M.transpose() * y0;
    CHECK((Pxz - expected_Pxz).norm() < 1e-7 * expected_Pxz.norm());
    // S >= R + the linear part 4 y0^T M P M^T y0 (the quadratic part only adds).
    const double R = scalar_noise_variance(y0, o.sigma_nT);
    CHECK(u.innovation_variance_nT4 >= R + 4.0 * y0.dot(M * P * M.transpose() * y0));
  }
}

TEST_CASE("UKF recovers known parameters from a warm start on noise-free data") {
  const Vector9d p_true = paper_parameters();
  for (Geometry g : {Geometry::kRandom, Geometry::kTumbling, Geometry::kNadir}) {
    const auto data = simulate(g, p_true, g == Geometry::kNadir ? 24.0 : 6.0, 0.0, 11);
    MagnetometerUkf::Options o;
    o.sigma_nT = kNoiseFreeSigma_nT;
    o.gate_nis = 0.0;  // see the EKF test: this is about the fixed point
    o.bias_floor_rate_sigmas = 0.0;
    MagnetometerUkf f(o);
    std::mt19937_64 rng(5);
    f.initialize(draw_prior(p_true, warm_covariance(), rng), warm_covariance());
    run_pure_model(f, data);
    const Vector9d e = f.x() - p_true;
    CHECK(e.head<3>().cwiseAbs().maxCoeff() < kNoiseFreeBiasTol_nT);
    CHECK(e.tail<6>().cwiseAbs().maxCoeff() < kNoiseFreeDTol);
    CHECK(f.state().n_accepted == static_cast<int64_t>(data.size()));
  }
}

TEST_CASE("UKF options: defaults are the spec's weights, bad spreads are refused") {
  const MagnetometerUkf::Options o;
  CHECK(o.validate().empty());
  CHECK(o.alpha == 1.0);
  CHECK(o.beta == 2.0);
  CHECK(o.kappa == -6.0);  // 3 - n: lambda = -6, W0m = -2, W0c = 0, Wi = 1/6
  MagnetometerUkf::Options bad;
  bad.kappa = -9.0;  // n + lambda = 0
  CHECK_FALSE(bad.validate().empty());
  bad = {};
  bad.alpha = 0.0;
  CHECK_FALSE(bad.validate().empty());
  bad = {};
  bad.alpha = 0.5;  // W0c = -8.25 < 0: the square-root downdate is no longer guaranteed PD
  CHECK_FALSE(bad.validate().empty());
  bad = {};
  bad.sigma_nT = -1.0;  // base options are validated too
  CHECK_FALSE(bad.validate().empty());
}

TEST_CASE("Covariance guard keeps P symmetric positive definite") {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> n(0.0, 1.0);
  Matrix9d A;
  for (int i = 0; i < 81; ++i) A(i) = n(rng);
  const Matrix9d scale = Vector9d(warm_covariance().diagonal().cwiseSqrt()).asDiagonal();

  SECTION("positive definite: unchanged, L L^T = P") {
    Matrix9d P = scale * (A * A.transpose() + Matrix9d::Identity()) * scale;
    P = (0.5 * (P + P.transpose())).eval();
    const Matrix9d P_in = P;
    Matrix9d L;
    CHECK(guard_covariance(P, L) == CovarianceGuard::kOk);
    CHECK(P == P_in);
    CHECK((L * L.transpose() - P).norm() < 1e-12 * P.norm());
  }
  SECTION("indefinite (a negative eigenvalue): repaired to positive definite") {
    Eigen::SelfAdjointEigenSolver<Matrix9d> eig(A * A.transpose());
    Vector9d lambda = eig.eigenvalues();
    lambda(0) = -0.5;
    Matrix9d P =
        scale * eig.eigenvectors() * lambda.asDiagonal() * eig.eigenvectors().transpose() * scale;
    Matrix9d L;
    CHECK(guard_covariance(P, L) == CovarianceGuard::kRepaired);
    CHECK(Eigen::LLT<Matrix9d>(P).info() == Eigen::Success);
    CHECK((L * L.transpose() - P).norm() < 1e-10 * P.norm());
    CHECK(P.isApprox(P.transpose()));
  }
  SECTION("asymmetric round-off is symmetrised") {
    Matrix9d P = scale * (A * A.transpose() + Matrix9d::Identity()) * scale;
    P(0, 3) *= 1.0 + 1e-12;
    Matrix9d L;
    guard_covariance(P, L);
    CHECK(P == P.transpose());
  }
  SECTION("NaN: refused, P untouched") {
    Matrix9d P = Matrix9d::Identity();
    P(2, 2) = std::numeric_limits<double>::quiet_NaN();
    Matrix9d L;
    CHECK(guard_covariance(P, L) == CovarianceGuard::kNonFinite);
    CHECK(std::isnan(P(2, 2)));
  }
}

TEST_CASE("UKF rejects NaN input without touching the state") {
  const auto data = simulate(Geometry::kRandom, paper_parameters(), 0.5, kSigma_nT, 2);
  MagnetometerUkf f;
  run_pure_model(f, data);
  const FilterState before = f.state();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const int64_t t = data.back().utime + 10'000'000;
  CHECK(f.update({nan, 1.0, 2.0}, 40000.0, t).status == FilterUpdateStatus::kRejectedInvalid);
  CHECK(f.update({1e4, 2e4, 3e4}, nan, t).status == FilterUpdateStatus::kRejectedInvalid);
  FilterState expected = before;
  expected.n_rejected_invalid += 2;
  CHECK(f.state() == expected);
}

TEST_CASE("UKF state save/restore is a bit-exact continuation, reanchor keeps counters") {
  const auto data = simulate(Geometry::kNadir, paper_parameters(), 4.0, kSigma_nT, 4);
  MagnetometerUkf::Options o;
  o.process_noise_per_sqrt_hour.setConstant(1e-3);
  MagnetometerUkf a(o);
  run_pure_model(a, data, 0, data.size() / 2);
  MagnetometerUkf b(o);
  b.restore(a.state());
  run_pure_model(a, data, data.size() / 2);
  run_pure_model(b, data, data.size() / 2);
  CHECK(b.state() == a.state());

  const FilterState s = a.state();
  a.reanchor(paper_parameters(), warm_covariance());
  CHECK(a.x() == paper_parameters());
  CHECK(a.P().isApprox(warm_covariance(), 1e-14));
  CHECK(a.state().n_accepted == s.n_accepted);
  CHECK(a.state().last_utime == s.last_utime);
  CHECK(a.state().nis_window_count == 0);
  CHECK(a.consistent());
}

TEST_CASE(
    "UKF saved while collecting for its start resumes bit for bit, started it drops the "
    "start's lag-1 products") {
  const auto data = simulate(Geometry::kNadir, paper_parameters(), 4.0, kSigma_nT, 4);
  const size_t collecting = 40;  // below start.min_samples
  MagnetometerUkf a;
  run_pure_model(a, data, 0, collecting);
  REQUIRE_FALSE(a.initialized());
  const auto* lag1 = std::get_if<ScalarLag1Moments>(&a.state().lag1_or_block);
  REQUIRE(lag1 != nullptr);
  CHECK(lag1->m.norm() > 0.0);
  MagnetometerUkf b;
  b.restore(a.state());
  run_pure_model(a, data, collecting);
  run_pure_model(b, data, collecting);
  REQUIRE(a.initialized());
  CHECK(b.state() == a.state());
  // The bias-motion block start holds the place of the lag-1 products.
  const auto* block = std::get_if<BiasBlockStart>(&a.state().lag1_or_block);
  REQUIRE(block != nullptr);
  CHECK(block->utime >= data[collecting].utime);
}

TEST_CASE("UKF update does not allocate") {
  const auto data = simulate(Geometry::kTumbling, paper_parameters(), 1.0, kSigma_nT, 5);
  MagnetometerUkf f;
  f.update(data[0].b_sensor_nT, data[0].h_norm_nT, data[0].utime);
  if (!kCountingAllocations) {
    magcal::test::skip("allocation counting is off under AddressSanitizer");
    return;
  }
  const long before = g_allocations.load();
  run_pure_model(f, data, 1);
  CHECK(g_allocations.load() == before);
  CHECK(f.state().n_accepted > 0);
}

TEST_CASE("UKF converges from 2.8x the paper's parameters") {
  // Measured (seeds 1-10, 24 h): tumbling |error| / sigma <= 2.3, bias error <= 0.2 nT;
  // nadir |error| / sigma <= 4.7, bias error <= 3 nT (the orbit-normal axis).
  const Vector9d p_true = paper_parameters();
  for (Geometry g : {Geometry::kTumbling, Geometry::kNadir}) {
    const auto data = simulate(g, p_true, 24.0, kSigma_nT, 3);
    MagnetometerUkf f;
    f.initialize(2.8 * p_true, f.options().initial_covariance());
    run_pure_model(f, data);
    const Vector9d e = f.x() - p_true;
    CHECK(e.head<3>().cwiseAbs().maxCoeff() < (g == Geometry::kNadir ? 5.0 : 1.0));
    CHECK(e.head<3>().cwiseQuotient(f.bias_sigma_nT()).cwiseAbs().maxCoeff() < 5.0);
    CHECK(f.snapshot().method == "ukf");
    CHECK(f.snapshot().status == CalibrationStatus::kOk);
  }
}
