// Consistency of the online filters (estimation.md 3a): normalised estimation errors ~ chi2,
// the NIS monitor, cold starts in weakly observed (nadir-like) geometry, and where the EKF fails
// and the UKF does not. Truth: simulated from the estimation model with known parameters.
#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Cholesky>
#include <catch2/catch.hpp>

#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "tests/pipeline/filter_test_support.hpp"

using namespace magcal;
using namespace magcal::test;

namespace {

constexpr double kSigma_nT = 3.0;
constexpr int kMonteCarloRuns = 60;
// Mean of 60 chi2(9) draws: 9 +- 0.55 (1 sigma); the bounds are ~3.5 sigma.
constexpr double kMeanNeesLow = 7.0;
constexpr double kMeanNeesHigh = 11.0;
constexpr double kMaxErrorOverSigma = 5.0;  // "a wrong estimate must not claim a small sigma"
constexpr int kCheckEvery = 30;             // samples between checks of the claimed sigma

struct RunSummary {
  Vector9d error = Vector9d::Zero();
  double nees = 0.0;
  double final_bias_error_over_sigma = 0.0;  // max over axes at the end
  double worst_claimed_ok = 0.0;  // max |bias error| / sigma over checks where converged()
  double converged_after_s = -1.0;
};

template <class Filter>
RunSummary run(Filter& f, const std::vector<SimSample>& data, const Vector9d& p_true) {
  RunSummary s;
  for (size_t k = 0; k < data.size(); ++k) {
    f.update(data[k].b_sensor_nT, data[k].h_norm_nT, data[k].utime);
    if (k % kCheckEvery == 0 && f.converged()) {
      const Eigen::Vector3d r =
          (f.x() - p_true).template head<3>().cwiseQuotient(f.bias_sigma_nT());
      s.worst_claimed_ok = std::max(s.worst_claimed_ok, r.cwiseAbs().maxCoeff());
    }
  }
  s.error = f.x() - p_true;
  s.nees = s.error.dot(f.P().ldlt().solve(s.error));
  s.final_bias_error_over_sigma =
      s.error.head<3>().cwiseQuotient(f.bias_sigma_nT()).cwiseAbs().maxCoeff();
  if (f.state().converged_since_utime >= 0)
    s.converged_after_s = (f.state().converged_since_utime - data.front().utime) * 1e-6;
  return s;
}

template <class Filter>
double monte_carlo_mean_nees(Geometry g, double hours) {
  const Vector9d p_true = paper_parameters();
  double sum = 0.0;
  for (int r = 0; r < kMonteCarloRuns; ++r) {
    const auto data = simulate(g, p_true, hours, kSigma_nT, 1000 + r);
    std::mt19937_64 rng(2000 + r);
    Filter f;
    f.initialize(draw_prior(p_true, warm_covariance(), rng), warm_covariance());
    sum += run(f, data, p_true).nees;
  }
  return sum / kMonteCarloRuns;
}

}  // namespace

TEST_CASE("Warm start, 3 nT noise: normalised estimation errors are chi-square(9)") {
  const double ekf = monte_carlo_mean_nees<MagnetometerEkf>(Geometry::kTumbling, 3.0);
  const double ukf = monte_carlo_mean_nees<MagnetometerUkf>(Geometry::kTumbling, 3.0);
  WARN("mean NEES over " << kMonteCarloRuns << " runs: EKF " << ekf << ", UKF " << ukf);
  CHECK(ekf > kMeanNeesLow);
  CHECK(ekf < kMeanNeesHigh);
  CHECK(ukf > kMeanNeesLow);
  CHECK(ukf < kMeanNeesHigh);
}

TEST_CASE("Consistent data: the NIS monitor stays quiet") {
  const Vector9d p_true = paper_parameters();
  const auto data = simulate(Geometry::kTumbling, p_true, 6.0, kSigma_nT, 21);
  MagnetometerUkf f;
  f.initialize(p_true, warm_covariance());
  run(f, data, p_true);
  CHECK(f.state().n_inconsistency_events == 0);
  CHECK(f.consistent());
  CHECK(f.state().last_window_mean_nis == Approx(1.0).margin(0.5));
}

TEST_CASE("Mis-stated noise (15 nT data, 3 nT assumed): inconsistency flagged, no ok status") {
  const Vector9d p_true = paper_parameters();
  const auto data = simulate(Geometry::kTumbling, p_true, 6.0, 5.0 * kSigma_nT, 22);
  MagnetometerUkf f;
  f.initialize(p_true, warm_covariance());
  run(f, data, p_true);
  CHECK(f.state().n_inconsistency_events > 0);
  CHECK_FALSE(f.consistent());
  CHECK(f.snapshot().status == CalibrationStatus::kNotConverged);
}

TEST_CASE("Overconfident wrong prior: gated samples trip the monitor, which re-opens P") {
  // Every sample is outside the gate of a filter sure of a wrong answer; without the monitor it
  // would ignore the data forever.
  const Vector9d p_true = paper_parameters();
  const auto data = simulate(Geometry::kTumbling, p_true, 12.0, kSigma_nT, 23);
  Vector9d wrong = p_true;
  wrong.head<3>() += Eigen::Vector3d(300.0, -200.0, 250.0);
  Matrix9d tiny = warm_covariance() * 1e-4;  // claims 0.2 nT
  for (int which = 0; which < 2; ++which) {
    RunSummary s;
    int64_t events = 0;
    if (which == 0) {
      MagnetometerEkf f;
      f.initialize(wrong, tiny);
      s = run(f, data, p_true);
      events = f.state().n_inconsistency_events;
    } else {
      MagnetometerUkf f;
      f.initialize(wrong, tiny);
      s = run(f, data, p_true);
      events = f.state().n_inconsistency_events;
    }
    CHECK(events > 0);
    CHECK(s.error.head<3>().cwiseAbs().maxCoeff() < 1.0);
    CHECK(s.final_bias_error_over_sigma < kMaxErrorOverSigma);
  }
}

TEST_CASE("Cold start on nadir-like geometry: no small sigma while wrong after a day") {
  // Measured (paper parameters, seeds 1-10, 24 h, defaults): final |error| / sigma UKF <= 4.4,
  // EKF <= 5.4; with 0.3 nT/sqrt(h) process noise the UKF ends <= 1.3 (early linearisation
  // errors are forgotten instead of locked in).
  // Known limitation (estimation.md 3a, reproduced): during the first hours of a cold start the
  // filters can claim convergence while the weakly observed orbit-normal bias is still wrong
  // (seen: 378 nT off with 6.7 nT sigma at 6 h, seed 3); the innovations are consistent there,
  // so the NIS monitor cannot see it. The remedy is the daemon's re-anchoring on a batch refit:
  // from a warm start the claimed sigma holds throughout (next test).
  const Vector9d p_true = paper_parameters();
  for (uint64_t seed : {1, 2, 3}) {
    const auto data = simulate(Geometry::kNadir, p_true, 24.0, kSigma_nT, seed);
    MagnetometerUkf f;
    const RunSummary s = run(f, data, p_true);
    CHECK(s.final_bias_error_over_sigma < kMaxErrorOverSigma);
    CHECK(s.converged_after_s > 0.0);  // converges within the day
    CHECK(f.snapshot().status == CalibrationStatus::kOk);

    MagnetometerUkf::Options o;
    o.process_noise_per_sqrt_hour << 0.3, 0.3, 0.3, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6;
    MagnetometerUkf fq(o);
    const RunSummary sq = run(fq, data, p_true);
    CHECK(sq.final_bias_error_over_sigma < 2.5);
  }
}

TEST_CASE("Warm start (re-anchored) on nadir-like geometry: the claimed sigma holds throughout") {
  // Measured over seeds 1-10, 24 h, paper and harsh parameters: worst |error| / sigma at any
  // check while converged <= 3.8 for both filters.
  for (const Vector9d& p_true : {paper_parameters(), harsh_parameters()}) {
    for (uint64_t seed : {1, 2}) {
      const auto data = simulate(Geometry::kNadir, p_true, 24.0, kSigma_nT, seed);
      std::mt19937_64 rng(100 + seed);
      const Vector9d x0 = draw_prior(p_true, warm_covariance(), rng);
      MagnetometerEkf ekf;
      MagnetometerUkf ukf;
      ekf.initialize(x0, warm_covariance());
      ukf.initialize(x0, warm_covariance());
      const RunSummary se = run(ekf, data, p_true);
      const RunSummary su = run(ukf, data, p_true);
      CHECK(se.worst_claimed_ok < kMaxErrorOverSigma);
      CHECK(su.worst_claimed_ok < kMaxErrorOverSigma);
      CHECK(se.final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(su.final_bias_error_over_sigma < kMaxErrorOverSigma);
    }
  }
}

TEST_CASE("Harsh parameters (3000 nT, D 0.05): the EKF fails where the UKF converges") {
  // estimation.md 3a. Whatever the EKF does, it must not end claiming convergence while wrong.
  const Vector9d p_true = harsh_parameters();
  int ekf_failures = 0;
  int runs = 0;
  for (uint64_t seed : {1, 2, 3, 4, 5}) {
    const auto data = simulate(Geometry::kTumbling, p_true, 24.0, kSigma_nT, seed);
    for (bool from_2p8 : {false, true}) {
      MagnetometerEkf ekf;
      MagnetometerUkf ukf;
      if (from_2p8) {
        ekf.initialize(2.8 * p_true, ekf.options().initial_covariance());
        ukf.initialize(2.8 * p_true, ukf.options().initial_covariance());
      }
      const RunSummary se = run(ekf, data, p_true);
      const RunSummary su = run(ukf, data, p_true);
      ++runs;
      const bool ekf_failed = se.error.head<3>().cwiseAbs().maxCoeff() > 100.0;
      if (ekf_failed) {
        ++ekf_failures;
        CHECK_FALSE(ekf.converged());  // failed, and says so
      }
      CHECK(su.error.head<3>().cwiseAbs().maxCoeff() < 1.0);  // UKF: converged, every run
      CHECK(su.final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(ukf.converged());
    }
  }
  WARN("EKF failed (bias error > 100 nT after 24 h) in " << ekf_failures << " of " << runs
                                                         << " harsh tumbling runs");
  CHECK(ekf_failures >= 3);
}
