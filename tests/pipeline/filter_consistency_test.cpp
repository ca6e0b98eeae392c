// Consistency of the online filters (estimation.md 3a and 7): normalised estimation errors ~
// chi2, the NIS monitor, noise adaptation, the data start in weakly observed (nadir-like)
// geometry, efficiency against the CRLB, unobservable captures, the snapshot evidence.
// Truth: simulated from the estimation model with known parameters.
#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Cholesky>
#include <catch2/catch.hpp>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
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
// Checks while converged a run must have made for its worst one to say anything: an hour of
// 10 s samples (a filter that never converges passes a bound on them vacuously).
constexpr int kMinClaimedOkChecks = 12;

struct RunSummary {
  Vector9d error = Vector9d::Zero();
  double nees = 0.0;
  double final_bias_error_over_sigma = 0.0;  // max over axes at the end
  double worst_claimed_ok = 0.0;  // max |bias error| / sigma over checks where converged()
  int claimed_ok_checks = 0;      // those checks: worst_claimed_ok means something when many
  double converged_after_s = -1.0;
};

template <class Filter>
RunSummary run(Filter& f, const std::vector<SimSample>& data, const Vector9d& p_true) {
  state_pure_model(f);
  RunSummary s;
  for (size_t k = 0; k < data.size(); ++k) {
    f.update(data[k].b_sensor_nT, data[k].h_norm_nT, data[k].utime);
    if (k % kCheckEvery == 0 && f.converged()) {
      const Eigen::Vector3d r =
          (f.x() - p_true).template head<3>().cwiseQuotient(f.bias_sigma_nT());
      s.worst_claimed_ok = std::max(s.worst_claimed_ok, r.cwiseAbs().maxCoeff());
      ++s.claimed_ok_checks;
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

TEST_CASE("Mis-stated noise (15 nT data, 3 nT configured): the filter adapts and stays honest") {
  // Adaptive noise (filter_common.hpp): the effective noise is estimated from the innovations,
  // so the NIS monitor tests consistency, not a mis-set sigma.
  const Vector9d p_true = paper_parameters();
  const auto data = simulate(Geometry::kTumbling, p_true, 6.0, 5.0 * kSigma_nT, 22);
  MagnetometerUkf f;
  const RunSummary s = run(f, data, p_true);
  const CalibrationResult r = f.snapshot();
  WARN("estimated noise " << r.measurement_noise_nT << " nT (truth 15), events "
                          << f.state().n_inconsistency_events);
  CHECK(r.measurement_noise_nT == Approx(5.0 * kSigma_nT).epsilon(0.15));
  CHECK(f.consistent());
  CHECK(r.nis_mean == Approx(1.0).margin(0.3));
  CHECK(s.worst_claimed_ok < kMaxErrorOverSigma);
  CHECK(s.claimed_ok_checks >= kMinClaimedOkChecks);
  CHECK(s.final_bias_error_over_sigma < kMaxErrorOverSigma);
  CHECK(r.status == CalibrationStatus::kOk);
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

TEST_CASE("Data start on nadir-like geometry: not_converged until observed, then honest") {
  // estimation.md 7: no cold prior. Before the start the snapshot is not_converged; after it
  // no check that claims convergence is more than 5 sigma off.
  const Vector9d p_true = paper_parameters();
  for (uint64_t seed : {1, 2, 3}) {
    const auto data = simulate(Geometry::kNadir, p_true, 24.0, kSigma_nT, seed);
    MagnetometerEkf ekf;
    MagnetometerUkf ukf;
    for (size_t k = 0; k < 30; ++k)
      ukf.update(data[k].b_sensor_nT, data[k].h_norm_nT, data[k].utime);
    CHECK_FALSE(ukf.initialized());
    CHECK(ukf.snapshot().status == CalibrationStatus::kNotConverged);
    ukf.reset();
    const RunSummary se = run(ekf, data, p_true);
    const RunSummary su = run(ukf, data, p_true);
    for (const RunSummary* s : {&se, &su}) {
      CHECK(s->worst_claimed_ok < kMaxErrorOverSigma);
      CHECK(s->claimed_ok_checks >= kMinClaimedOkChecks);
      CHECK(s->final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(s->converged_after_s > 0.0);
    }
    CHECK(ekf.snapshot().status == CalibrationStatus::kOk);
    CHECK(ukf.snapshot().status == CalibrationStatus::kOk);
  }
}

TEST_CASE("Data start: efficiency against the CRLB (tumbling <= 1.5x, nadir <= 3x)") {
  // Pooled RMS over runs and axes of (b_hat - b) / sigma_CRLB (estimation.md 6), CRLB at the
  // truth on the same samples. Measured: see the closing figures in the report.
  const Vector9d p_true = paper_parameters();
  struct Case {
    Geometry g;
    double hours;
    int runs;
    double max_ratio;
  };
  for (const Case c :
       {Case{Geometry::kTumbling, 6.0, 20, 1.5}, Case{Geometry::kNadir, 24.0, 4, 3.0}}) {
    double sum_ukf = 0.0, sum_ekf = 0.0;
    for (int r = 0; r < c.runs; ++r) {
      const auto data = simulate(c.g, p_true, c.hours, kSigma_nT, 500 + r);
      SampleSet set;
      for (const SimSample& s : data)
        set.push_back({s.utime, s.b_sensor_nT, Eigen::Vector3d(s.h_norm_nT, 0.0, 0.0), false});
      const CrlbResult crlb =
          compute_crlb(set, CalibrationParameters::from_packed(p_true), kSigma_nT);
      REQUIRE(crlb.ok);
      MagnetometerUkf ukf;
      MagnetometerEkf ekf;
      const RunSummary su = run(ukf, data, p_true);
      const RunSummary se = run(ekf, data, p_true);
      sum_ukf += su.error.head<3>().cwiseQuotient(crlb.sigma.head<3>()).squaredNorm();
      sum_ekf += se.error.head<3>().cwiseQuotient(crlb.sigma.head<3>()).squaredNorm();
      CHECK(su.final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(se.final_bias_error_over_sigma < kMaxErrorOverSigma);
    }
    const double ukf_ratio = std::sqrt(sum_ukf / (3.0 * c.runs));
    const double ekf_ratio = std::sqrt(sum_ekf / (3.0 * c.runs));
    WARN((c.g == Geometry::kNadir ? "nadir" : "tumbling")
         << " RMS error / CRLB over " << c.runs << " runs: UKF " << ukf_ratio << ", EKF "
         << ekf_ratio);
    CHECK(ukf_ratio < c.max_ratio);
    CHECK(ekf_ratio < 3.0);
  }
}

TEST_CASE("Constant-field captures: yaw-only is never ok nor accepted, a 22 uT full one is") {
  // The public-report cases of issue 10: a planar (yaw-only) capture does not observe b3 (its
  // field z component never changes); a low-field capture through all orientations does.
  Vector9d p_true;
  p_true << -1500.0, 2500.0, 3200.0, 0.02, -0.01, 0.015, 0.005, -0.004, 0.003;
  GateOptions gates;
  gates.expected_residual_nT = 30.0;  // the captures' noise level (a lab setting)
  for (bool yaw_only : {true, false}) {
    const double field = yaw_only ? 48000.0 : 22000.0;
    const auto data = simulate_capture(p_true, field, yaw_only, 2000, 30.0, 31);
    MagnetometerEkf::Options o;
    o.sigma_nT = 30.0;
    MagnetometerEkf ekf(o);
    MagnetometerUkf::Options ou;
    ou.sigma_nT = 30.0;
    MagnetometerUkf ukf(ou);
    run(ekf, data, p_true);
    run(ukf, data, p_true);
    for (const CalibrationResult& r : {ekf.snapshot(), ukf.snapshot()}) {
      const GateVerdict v = evaluate_gates(r, GateInputs{}, gates);
      INFO(r.method << (yaw_only ? " yaw-only" : " 22 uT") << ": " << to_string(r.status) << " "
                    << r.message << ", condition " << r.fisher_condition_number << ", bias "
                    << r.parameters.bias_nT.transpose());
      if (yaw_only) {
        CHECK(r.status != CalibrationStatus::kOk);
        CHECK_FALSE(v.accepted);
      } else {
        CHECK(r.status == CalibrationStatus::kOk);
        CHECK(v.accepted);
        const Eigen::Vector3d e = r.parameters.bias_nT - p_true.head<3>();
        CHECK((e.cwiseQuotient(r.bias_sigma_nT()).cwiseAbs().array() < kMaxErrorOverSigma).all());
      }
    }
  }
}

TEST_CASE("Snapshot evidence: residual rms and NIS over the period, reset by the caller") {
  const Vector9d p_true = paper_parameters();
  const auto data = simulate(Geometry::kTumbling, p_true, 4.0, kSigma_nT, 41);
  MagnetometerUkf f;
  const size_t half = data.size() / 2;
  run_pure_model(f, data, 0, half);
  REQUIRE(f.initialized());
  f.snapshot_and_reset_period();
  // Independent: rms of |B_cal| - |h| with the estimate before each sample.
  double sum2 = 0.0;
  int n = 0;
  for (size_t k = half; k < data.size(); ++k) {
    const double e = f.parameters().apply(data[k].b_sensor_nT).norm() - data[k].h_norm_nT;
    sum2 += e * e;
    ++n;
    f.update(data[k].b_sensor_nT, data[k].h_norm_nT, data[k].utime);
  }
  const CalibrationResult r = f.snapshot();
  CHECK(r.residual_rms_nT == Approx(std::sqrt(sum2 / n)).epsilon(1e-9));
  CHECK(r.residual_rms_nT == Approx(kSigma_nT).epsilon(0.1));  // |B_cal| - |h| ~ N(0, sigma^2)
  CHECK(r.nis_mean == Approx(1.0).margin(0.15));
  CHECK(r.measurement_noise_nT == Approx(kSigma_nT).epsilon(0.1));
  CHECK(r.fisher_condition_number > 1.0);
  CHECK(r.fisher_condition_number < 100.0);
  CHECK(r.status == CalibrationStatus::kOk);
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
      CHECK(se.claimed_ok_checks >= kMinClaimedOkChecks);
      CHECK(su.claimed_ok_checks >= kMinClaimedOkChecks);
      CHECK(se.final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(su.final_bias_error_over_sigma < kMaxErrorOverSigma);
    }
  }
}

TEST_CASE("Harsh parameters (3000 nT, D 0.05): a data start converges for both filters") {
  // estimation.md 3a: from a cold prior the textbook EKF locks in; from a data start (the batch
  // solution of the first samples) neither filter does. From a prior at 2.8x the truth the EKF
  // may still fail, but it must not claim convergence while wrong.
  const Vector9d p_true = harsh_parameters();
  for (uint64_t seed : {1, 2, 3}) {
    const auto data = simulate(Geometry::kTumbling, p_true, 12.0, kSigma_nT, seed);
    MagnetometerEkf ekf;
    MagnetometerUkf ukf;
    const RunSummary se = run(ekf, data, p_true);
    const RunSummary su = run(ukf, data, p_true);
    for (const RunSummary* s : {&se, &su}) {
      CHECK(s->error.head<3>().cwiseAbs().maxCoeff() < 1.0);
      CHECK(s->final_bias_error_over_sigma < kMaxErrorOverSigma);
      CHECK(s->worst_claimed_ok < kMaxErrorOverSigma);
      CHECK(s->claimed_ok_checks >= kMinClaimedOkChecks);
    }
    CHECK(ekf.converged());
    CHECK(ukf.converged());

    MagnetometerEkf ekf_prior;
    ekf_prior.initialize(2.8 * p_true, ekf_prior.options().initial_covariance());
    const RunSummary sp = run(ekf_prior, data, p_true);
    if (sp.error.head<3>().cwiseAbs().maxCoeff() > 100.0) CHECK_FALSE(ekf_prior.converged());
  }
}

TEST_CASE("seed_noise: a refit's effective noise and correlation, bounded below by sigma_nT") {
  MagnetometerUkf f;
  f.seed_noise(7.5, 0.8);
  CHECK(f.measurement_noise_nT() == Approx(7.5));
  CHECK(f.innovation_autocorrelation() == Approx(0.8));
  f.seed_noise(1.0);  // below the configured 3 nT: the floor holds
  CHECK(f.measurement_noise_nT() == Approx(kSigma_nT));
  CHECK(f.innovation_autocorrelation() == Approx(0.8));
  f.seed_noise(std::numeric_limits<double>::quiet_NaN());  // ignored
  CHECK(f.measurement_noise_nT() == Approx(kSigma_nT));
}

TEST_CASE("Paper sensor, 24 h without a re-anchor: ok snapshots' sigmas cover the error") {
  // The simulator's paper sensor (nonlinearity, hysteresis, quantisation: effects the 9-parameter
  // model leaves out) and no refit all day. P alone treats the innovations as white (with the
  // lag-1 inflation) and ends 2-4x over-confident; the reported covariance (batch-means sandwich,
  // filter_common.hpp) must cover the error. Snapshots every 15 min, as the daemon takes them.
  struct Outcome {
    int ok = 0, beyond_3_sigma = 0;
    double worst = 0.0;
  };
  auto replay = [](int sandwich_block_samples) {
    Outcome o;
    for (uint64_t seed = 1; seed <= 3; ++seed) {
      Scenario sc = *scenario_preset("paper");
      sc.seed = seed;
      sc.duration_s = 24.0 * 3600.0;
      Simulator sim(sc);
      const Eigen::Vector3d bias_true = sim.truth().bias_nT;
      UkfOptions options;  // defaults, as the daemon runs it, but without a refit:
      options.ok_needs_model_error = false;  // what the filter alone claims
      options.sandwich_block_samples = sandwich_block_samples;
      MagnetometerUkf f(options);
      SimulatedSample s;
      for (int k = 1; sim.next(&s); ++k) {
        const CalibrationSample c = s.calibration_sample();
        f.update(c.b_sensor_nT, c.h_body_nT.norm(), c.utime);
        if (k % 90 != 0) continue;
        const CalibrationResult r = f.snapshot_and_reset_period();
        if (r.status != CalibrationStatus::kOk) continue;
        const double z = (r.parameters.bias_nT - bias_true)
                             .cwiseQuotient(r.bias_sigma_nT())
                             .cwiseAbs()
                             .maxCoeff();
        ++o.ok;
        o.beyond_3_sigma += z > 3.0;
        o.worst = std::max(o.worst, z);
      }
    }
    return o;
  };
  const Outcome reported = replay(UkfOptions().sandwich_block_samples);
  const Outcome p_alone = replay(0);
  INFO("reported covariance: " << reported.ok << " ok, " << reported.beyond_3_sigma
                               << " beyond 3 sigma, worst " << reported.worst
                               << "; P alone: " << p_alone.ok << " ok, " << p_alone.beyond_3_sigma
                               << " beyond 3 sigma, worst " << p_alone.worst);
  REQUIRE(p_alone.ok > 50);
  CHECK(p_alone.beyond_3_sigma > p_alone.ok / 5);  // the case P alone gets wrong
  REQUIRE(reported.ok > 50);
  CHECK(reported.beyond_3_sigma <= reported.ok / 50);
  CHECK(reported.worst < 3.5);
}
