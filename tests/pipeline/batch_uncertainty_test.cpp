// Monte-Carlo acceptance of the batch uncertainty (issue 10, estimation.md section 7): on the
// paper scenario (unmodelled nonlinearity, hysteresis, quantisation) the reported sigma covers
// the real error without being uselessly wide, and the bias MSE beats the bar; on
// pure-model data the HAC covariance and the model extension change nothing (CRLB-tight).
// Truth: the simulator's parameters, which the estimator never sees; the CRLB at the truth.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include <catch2/catch.hpp>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"

using namespace magcal;

namespace {

// The lower bar on RMS(err/sigma) per axis: a sigma at most 2x too wide. With 10 draws it flags a
// sigma 3x too wide in 99 % of sets (chi-square, 10 degrees of freedom), with 15 or more in
// 99.6 %, and an honest sigma in under 1 %.
constexpr double kNotUselesslyWide = 0.5;

struct SimulatedSet {
  SampleSet samples;
  TruthParameters truth;
};

SimulatedSet simulate(const Scenario& sc) {
  Simulator sim(sc);
  SimulatedSet out;
  out.truth = sim.truth();
  SimulatedSample s;
  out.samples.reserve(static_cast<std::size_t>(sim.sample_count()));
  while (sim.next(&s)) out.samples.push_back(s.calibration_sample());
  return out;
}

SimulatedSet simulate(const char* preset, uint64_t seed, double hours = 12.0) {
  Scenario sc = *scenario_preset(preset);
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  return simulate(sc);
}

// Per-axis statistics over runs.
struct AxisStats {
  Eigen::Vector3d sum_z2 = Eigen::Vector3d::Zero();           // (err / reported sigma)^2
  Eigen::Vector3d sum_err2 = Eigen::Vector3d::Zero();         // err^2 (nT^2)
  Eigen::Vector3d sum_crlb_z2 = Eigen::Vector3d::Zero();      // (err / CRLB sigma)^2
  Eigen::Vector3d sum_sigma_ratio = Eigen::Vector3d::Zero();  // reported / CRLB sigma
  int runs = 0;
  int extended = 0;  // fits that enabled the nonlinearity extension

  void add(const CalibrationResult& r, const TruthParameters& t, const CrlbResult* crlb) {
    const Eigen::Vector3d err = r.parameters.bias_nT - t.bias_nT;
    const Eigen::Vector3d sigma = r.bias_sigma_nT();
    sum_z2 += err.cwiseQuotient(sigma).cwiseAbs2();
    sum_err2 += err.cwiseAbs2();
    if (crlb) {
      const Eigen::Vector3d s_crlb = crlb->sigma.head<3>();
      sum_crlb_z2 += err.cwiseQuotient(s_crlb).cwiseAbs2();
      sum_sigma_ratio += sigma.cwiseQuotient(s_crlb);
    }
    if (r.has_nonlinearity) ++extended;
    ++runs;
  }
  // Alignment (stage 2): error angles (sensor frame, R_true = (I - [d x]) R_hat) per sigma.
  Eigen::Vector3d sum_align_z2 = Eigen::Vector3d::Zero();
  Eigen::Vector3d sum_align_err2_arcsec2 = Eigen::Vector3d::Zero();
  int aligned = 0;
  void add_alignment(const CalibrationResult& r, const TruthParameters& t) {
    if (!r.has_alignment) return;
    const Eigen::Matrix3d M = t.R_sensor_from_body * r.alignment.R_sensor_from_body.transpose();
    const Eigen::Vector3d d =
        -0.5 * Eigen::Vector3d(M(2, 1) - M(1, 2), M(0, 2) - M(2, 0), M(1, 0) - M(0, 1));
    const Eigen::Vector3d sigma = r.alignment.angle_covariance_rad2.diagonal().cwiseSqrt();
    sum_align_z2 += d.cwiseQuotient(sigma).cwiseAbs2();
    sum_align_err2_arcsec2 += (d * kRadToDeg * 3600.0).cwiseAbs2();
    ++aligned;
  }
  Eigen::Vector3d align_rms_z() const { return (sum_align_z2 / aligned).cwiseSqrt(); }
  Eigen::Vector3d align_rms_arcsec() const {
    return (sum_align_err2_arcsec2 / aligned).cwiseSqrt();
  }
  Eigen::Vector3d rms_z() const { return (sum_z2 / runs).cwiseSqrt(); }
  double bias_mse() const { return sum_err2.sum() / (3.0 * runs); }
  double crlb_ratio() const { return std::sqrt(sum_crlb_z2.sum() / (3.0 * runs)); }
  Eigen::Vector3d sigma_over_crlb() const { return sum_sigma_ratio / runs; }
};

}  // namespace

TEST_CASE("paper scenario, 50 x 12 h: err/sigma RMS per axis within 0.5..1.5, bias MSE <= 5 nT^2") {
  AxisStats stats, stats_9;  // with the default model extension / 9-parameter model + HAC only
  const int runs = 50;
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("paper", 1000 + static_cast<uint64_t>(run));
    BatchCalibrationOptions o9;
    o9.model_extension = false;
    const CalibrationResult r9 = calibrate_batch(set.samples, o9);
    REQUIRE(r9.status == CalibrationStatus::kOk);
    stats_9.add(r9, set.truth, nullptr);
    BatchCalibrationOptions o;  // the defaults `magcal fit --method twostep` uses
    const CalibrationResult r = calibrate_batch(set.samples, o);
    INFO("run " << run << ": " << r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    CHECK(r.accepted);
    CHECK(r.has_nonlinearity);  // BIC: the data support the sensor-model extension
    CHECK(std::isfinite(r.noise_scale));
    CHECK(std::isfinite(r.residual_autocorrelation));
    CHECK(r.has_alignment);
    stats.add(r, set.truth, nullptr);
    stats.add_alignment(r, set.truth);
  }
  const Eigen::Vector3d z9 = stats_9.rms_z();
  std::printf(
      "paper 12 h x %d, 9 parameters + HAC: RMS(err/sigma) = (%.3f, %.3f, %.3f), bias "
      "MSE %.3f nT^2\n",
      runs, z9(0), z9(1), z9(2), stats_9.bias_mse());
  CHECK(z9.maxCoeff() <= 1.5);  // without the extension the HAC sigma still covers the error
  const Eigen::Vector3d z = stats.rms_z();
  std::printf(
      "paper 12 h x %d: RMS(err/sigma) = (%.3f, %.3f, %.3f), bias MSE %.3f nT^2, "
      "extended in %d runs\n",
      runs, z(0), z(1), z(2), stats.bias_mse(), stats.extended);
  INFO("RMS(err/sigma) " << z.transpose() << ", bias MSE " << stats.bias_mse());
  CHECK(z.maxCoeff() <= 1.5);
  CHECK(z.minCoeff() >= kNotUselesslyWide);
  CHECK(stats.bias_mse() <= 5.0);
  // Stage 2 on the same fits: the angle sigma covers the error (hysteresis, a lag much like a
  // rotation about the orbit normal, is removed with the fitted extension; the stage-1 error and
  // the residuals' structure are in the covariance).
  const Eigen::Vector3d za = stats.align_rms_z();
  const Eigen::Vector3d ea = stats.align_rms_arcsec();
  std::printf(
      "paper 12 h x %d alignment: RMS(err/sigma) = (%.3f, %.3f, %.3f), RMS error (%.2f, %.2f, "
      "%.2f) arcsec\n",
      stats.aligned, za(0), za(1), za(2), ea(0), ea(1), ea(2));
  CHECK(za.maxCoeff() <= 1.5);
  CHECK(za.minCoeff() >= 0.25);
}

TEST_CASE("paper scenario, short windows (4 h and 6 h): sigmas still cover the error") {
  // The daemon's first refits see what a spacecraft has sent so far: a few orbits. There the
  // 9-parameter fit bends b by tens of nT to absorb the unmodelled effects, so the extension
  // must still be taken (measured before: 6 h, RMS(err/sigma) 4.2 on x, accepted).
  for (const double hours : {4.0, 6.0}) {
    AxisStats stats;
    const int runs = 15;
    for (int run = 0; run < runs; ++run) {
      const SimulatedSet set = simulate("paper", 3000 + static_cast<uint64_t>(run), hours);
      const CalibrationResult r = calibrate_batch(set.samples, BatchCalibrationOptions());
      INFO(hours << " h, run " << run << ": " << r.message << " "
                 << (r.rejection_reasons.empty() ? "" : r.rejection_reasons.front()));
      REQUIRE(r.status == CalibrationStatus::kOk);
      stats.add(r, set.truth, nullptr);
      stats.add_alignment(r, set.truth);
    }
    const Eigen::Vector3d z = stats.rms_z();
    const Eigen::Vector3d za = stats.align_rms_z();
    std::printf(
        "paper %.0f h x %d: RMS(err/sigma) bias (%.3f, %.3f, %.3f), alignment (%.3f, %.3f, "
        "%.3f), extended in %d runs\n",
        hours, runs, z(0), z(1), z(2), za(0), za(1), za(2), stats.extended);
    INFO(hours << " h: bias " << z.transpose() << ", alignment " << za.transpose());
    // Measured (seeds 3000-3014): 4 h up to 1.61 (bias z), 6 h up to 1.51 (pitch); the 12 h bar
    // (1.5) is not quite met on a few orbits, where unmodelled effects the extension does not
    // describe (quantisation, its own first-order terms) weigh more. Before the extension was
    // taken on short windows: 4.2 (6 h, bias x).
    CHECK(z.maxCoeff() <= 2.0);
    CHECK(za.maxCoeff() <= 2.0);
    CHECK(z.minCoeff() >= kNotUselesslyWide);
  }
}

TEST_CASE("fast spin (3 deg/s about body z, 1 s samples), 20 x 3 h: sigmas cover the error") {
  // The paper sensor on a craft spinning about its axis of least inertia (a stable spin): the
  // spin axis sees a slow field, so its hysteresis turning points come at the spin period and
  // the sign of each sample-to-sample change flips with the noise near them, phase-locked to the
  // spin. Measured with those signs (these seeds): bias RMS(err/sigma) (2.82, 2.21, 0.91),
  // alignment (3.65, 4.24, 1.77).
  AxisStats stats;
  const int runs = 20;
  for (int run = 0; run < runs; ++run) {
    Scenario sc = *scenario_preset("tumbling");
    sc.seed = 9000 + static_cast<uint64_t>(run);
    sc.duration_s = 3.0 * 3600.0;
    sc.sample_period_s = 1.0;
    sc.attitude.omega0_body_rad_s = Eigen::Vector3d(0.0, 0.0, 3.0) * kDegToRad;
    const SimulatedSet set = simulate(sc);
    const CalibrationResult r = calibrate_batch(set.samples, BatchCalibrationOptions());
    INFO("run " << run << ": " << r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    CHECK(r.has_nonlinearity);
    stats.add(r, set.truth, nullptr);
    stats.add_alignment(r, set.truth);
  }
  const Eigen::Vector3d z = stats.rms_z();
  const Eigen::Vector3d za = stats.align_rms_z();
  std::printf(
      "fast spin 3 h x %d: RMS(err/sigma) bias (%.3f, %.3f, %.3f), alignment (%.3f, %.3f, "
      "%.3f), bias MSE %.4f nT^2\n",
      runs, z(0), z(1), z(2), za(0), za(1), za(2), stats.bias_mse());
  INFO("bias " << z.transpose() << ", alignment " << za.transpose());
  CHECK(z.maxCoeff() <= 1.5);
  CHECK(z.minCoeff() >= kNotUselesslyWide);
  CHECK(za.maxCoeff() <= 1.5);
  CHECK(za.minCoeff() >= 0.25);
}

TEST_CASE("pure model, 50 x 12 h: error <= 1.1x CRLB, sigma within 1.2x CRLB, 9 parameters") {
  AxisStats stats;
  const int runs = 50;
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("pure", 2000 + static_cast<uint64_t>(run));
    BatchCalibrationOptions o;
    o.gate_options.expected_residual_nT = 3.0;
    const CalibrationResult r = calibrate_batch(set.samples, o);
    REQUIRE(r.status == CalibrationStatus::kOk);
    CalibrationParameters p;
    p.bias_nT = set.truth.bias_nT;
    p.D = set.truth.D;
    const CrlbResult crlb = compute_crlb(set.samples, p, set.truth.noise_sigma_nT);
    REQUIRE(crlb.ok);
    stats.add(r, set.truth, &crlb);
  }
  const Eigen::Vector3d ratio = stats.sigma_over_crlb();
  std::printf(
      "pure 12 h x %d: RMS err/CRLB %.3f, sigma/CRLB (%.3f, %.3f, %.3f), "
      "extended in %d runs\n",
      runs, stats.crlb_ratio(), ratio(0), ratio(1), ratio(2), stats.extended);
  CHECK(stats.crlb_ratio() <= 1.1);
  CHECK(ratio.maxCoeff() <= 1.2);
  CHECK(ratio.minCoeff() >= 0.95);     // never over-confident (the guard keeps it >= F^-1)
  CHECK(stats.extended <= runs / 20);  // BIC keeps the 9-parameter model in >= 95 % of runs
}

TEST_CASE("robust mode, paper scenario with spikes: the clean data's fit and honest sigmas") {
  // Before, --robust skipped the model extension (BIC does not hold with outliers) and kept the
  // hysteresis in stage 2: 12 h, pitch 0.023 deg off with sigma 0.0008 deg. Now the robust pass
  // only finds the outliers; the fit is the ordinary one on the samples left.
  AxisStats stats;
  const int runs = 10;
  std::mt19937_64 rng(4242);
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("paper", 5000 + static_cast<uint64_t>(run));
    SampleSet spiked = set.samples;
    std::uniform_int_distribution<std::size_t> pick(0, spiked.size() - 1);
    std::uniform_int_distribution<int> axis(0, 2);
    std::uniform_real_distribution<double> spike(2000.0, 300000.0);
    const int n_spikes = 25;
    for (int j = 0; j < n_spikes; ++j) spiked[pick(rng)].b_sensor_nT(axis(rng)) += spike(rng);
    BatchCalibrationOptions o;
    o.robust = true;
    const CalibrationResult r = calibrate_batch(spiked, o);
    const CalibrationResult clean = calibrate_batch(set.samples, BatchCalibrationOptions());
    INFO("run " << run << ": " << r.message << " "
                << (r.rejection_reasons.empty() ? "" : r.rejection_reasons.front()));
    REQUIRE(r.status == CalibrationStatus::kOk);
    CHECK(r.accepted);
    CHECK(r.has_nonlinearity == clean.has_nonlinearity);
    CHECK(r.n_samples == static_cast<int>(spiked.size()));
    CHECK(r.n_downweighted >= n_spikes - 2);  // a pick may repeat
    CHECK(r.n_downweighted <= n_spikes + 5);
    CHECK(r.residual_rms_all_nT > 10.0 * r.residual_rms_nT);
    // The same estimate as the clean data's, to a fraction of its sigma. Not closer: the robust
    // fit is the clean data's without the spiked samples, and a sample at a hysteresis turning
    // point of the largest field moves b by up to 0.40 sigma on its own (seed 5001, every sample
    // left out in turn: 0.40 max, 0.32 at the 99.9 % point, 0.019 RMS; 0.23 / 0.15 / 0.016 with
    // the sample-to-sample hysteresis signs). Here run 1 has a spike on such a sample: 0.32.
    const Eigen::Vector3d d =
        (r.parameters.bias_nT - clean.parameters.bias_nT).cwiseQuotient(clean.bias_sigma_nT());
    CHECK(d.cwiseAbs().maxCoeff() < 0.45);
    stats.add(r, set.truth, nullptr);
    stats.add_alignment(r, set.truth);
  }
  const Eigen::Vector3d z = stats.rms_z(), za = stats.align_rms_z();
  std::printf(
      "robust, paper 12 h + spikes x %d: RMS(err/sigma) bias (%.3f, %.3f, %.3f), "
      "alignment (%.3f, %.3f, %.3f)\n",
      runs, z(0), z(1), z(2), za(0), za(1), za(2));
  CHECK(z.maxCoeff() <= 1.5);
  CHECK(za.maxCoeff() <= 1.5);
  CHECK(z.minCoeff() >= kNotUselesslyWide);
}

TEST_CASE(
    "centered solution: residual-structure sigmas, rejected when the data show effects it "
    "cannot model") {
  // Before: the white-noise covariance; 12 h paper sets accepted with z bias up to 6 sigma and
  // pitch 56 sigma off.
  AxisStats paper, pure;
  BatchCalibrationOptions o;
  o.method = BatchCalibrationOptions::Method::kCentered;
  const int runs = 10;
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("paper", 6000 + static_cast<uint64_t>(run));
    const CalibrationResult r = calibrate_batch(set.samples, o);
    INFO("paper run " << run << ": " << r.message);
    REQUIRE(r.parameters.bias_nT.allFinite());
    CHECK_FALSE(r.accepted);
    CHECK(r.status == CalibrationStatus::kRejected);
    REQUIRE_FALSE(r.rejection_reasons.empty());
    CHECK(r.rejection_reasons.back().find("use twostep") != std::string::npos);
    CHECK(std::isfinite(r.residual_autocorrelation));
    CHECK(r.covariance_lag_window > 0);
    paper.add(r, set.truth, nullptr);
  }
  // 2.2-2.6 h windows: the effects BIC finds there are larger than a sensor's (so the extension
  // fitted at the centered b, D is not `used`), and the centered D was 5-6 sigma off, accepted
  // (second trial). Any effect BIC finds now rejects it.
  for (int run = 0; run < 4; ++run) {
    const SimulatedSet set = simulate("paper", 1 + static_cast<uint64_t>(run), 2.5);
    const CalibrationResult r = calibrate_batch(set.samples, o);
    INFO("paper 2.5 h run " << run << ": " << r.message);
    CHECK_FALSE(r.accepted);
    REQUIRE_FALSE(r.rejection_reasons.empty());
    CHECK(r.rejection_reasons.back().find("use twostep") != std::string::npos);
  }
  BatchCalibrationOptions o_pure = o;
  o_pure.gate_options.expected_residual_nT = 3.0;
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("pure", 7000 + static_cast<uint64_t>(run));
    const CalibrationResult r = calibrate_batch(set.samples, o_pure);
    INFO("pure run " << run << ": " << r.message);
    CHECK(r.status == CalibrationStatus::kOk);
    CHECK(r.accepted);
    pure.add(r, set.truth, nullptr);
    pure.add_alignment(r, set.truth);
  }
  const Eigen::Vector3d zp = paper.rms_z(), z = pure.rms_z(), za = pure.align_rms_z();
  std::printf(
      "centered, paper 12 h x %d: bias RMS(err/sigma) (%.3f, %.3f, %.3f); pure: bias "
      "(%.3f, %.3f, %.3f), alignment (%.3f, %.3f, %.3f)\n",
      runs, zp(0), zp(1), zp(2), z(0), z(1), z(2), za(0), za(1), za(2));
  CHECK(zp.maxCoeff() <= 1.5);  // the bias sigma covers even where the verdict is no
  CHECK(z.maxCoeff() <= 1.5);
  CHECK(za.maxCoeff() <= 1.5);
  CHECK(z.minCoeff() >= kNotUselesslyWide);
}

TEST_CASE(
    "online filters over 24 h: the model-error term covers b and D, and the alignment of "
    "their estimate removes the hysteresis") {
  // The filters' 9-parameter model converges to the 9-parameter optimum; before, their 24 h D13
  // was 7 sigma off on the paper scenario and `magcal fit --method ukf|ekf` aligned vectors with
  // the hysteresis left in (pitch 63 sigma off at 24 h); on a tumbling spacecraft bias 12, D 19
  // and yaw 35 sigma off, all accepted. As `magcal fit --method ukf` runs it: a batch refit of
  // the same samples gives the model error and the extension the alignment removes.
  for (const char* preset : {"paper", "tumbling"}) {
    AxisStats stats;
    double worst_d_z = 0.0;
    // 40 draws: an RMS(err/sigma) above 1.5 flags a sigma 2x too small in 99 % of such sets
    // (chi-square, 40 degrees of freedom), and an honest one in 1e-5; 5 draws (before) flagged
    // only sigmas 3x too small reliably, and honest ones in 5 %.
    const int runs = 40;
    for (int run = 0; run < runs; ++run) {
      const SimulatedSet set = simulate(preset, 8000 + static_cast<uint64_t>(run), 24.0);
      BatchCalibrationOptions batch;
      batch.alignment = false;
      batch.gates = false;
      const CalibrationResult refit = calibrate_batch(set.samples, batch);
      REQUIRE(refit.has_nonlinearity);
      MagnetometerUkf ukf{MagnetometerUkf::Options{}};
      ukf.set_model_error_covariance(refit.model_error_covariance());
      for (const CalibrationSample& s : set.samples) {
        ukf.update(s.b_sensor_nT, s.h_body_nT.norm(), s.utime);
      }
      CalibrationResult r = ukf.snapshot();
      INFO(preset << " run " << run << ": " << r.message);
      REQUIRE(r.status == CalibrationStatus::kOk);
      estimate_alignment(set.samples, 3.0, 10, &r, &refit);
      REQUIRE(r.has_alignment);
      stats.add(r, set.truth, nullptr);
      stats.add_alignment(r, set.truth);
      CalibrationParameters truth_p;
      truth_p.bias_nT = set.truth.bias_nT;
      truth_p.D = set.truth.D;
      const Vector9d d_z = (r.parameters.packed() - truth_p.packed())
                               .cwiseQuotient(r.covariance.diagonal().cwiseSqrt());
      worst_d_z = std::max(worst_d_z, d_z.tail<6>().cwiseAbs().maxCoeff());
    }
    const Eigen::Vector3d z = stats.rms_z(), za = stats.align_rms_z();
    std::printf(
        "ukf %s 24 h x %d: RMS(err/sigma) bias (%.3f, %.3f, %.3f), alignment (%.3f, "
        "%.3f, %.3f), worst D entry %.2f sigma\n",
        preset, runs, z(0), z(1), z(2), za(0), za(1), za(2), worst_d_z);
    INFO(preset);
    CHECK(z.maxCoeff() <= 1.5);
    CHECK(za.maxCoeff() <= 1.5);
    CHECK(worst_d_z <= 3.0);
  }
}

TEST_CASE("3 h windows: where the extension is refused, its disagreement covers the tail") {
  // A spacecraft's first refit sees ~3 h. On some orbits the extension is refused (its effects
  // or its residual too large to publish) while BIC says the data need it; the 9-parameter fit
  // was then 3.5-4.4 sigma off on x (seeds 7, 27, 35, 36 of 1-40) with the HAC covariance alone.
  AxisStats stats;
  double worst = 0.0;
  int refused = 0;
  const int runs = 40;
  for (int run = 0; run < runs; ++run) {
    const SimulatedSet set = simulate("paper", 1 + static_cast<uint64_t>(run), 3.0);
    const CalibrationResult r = calibrate_batch(set.samples, BatchCalibrationOptions());
    INFO("run " << run << ": " << r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    stats.add(r, set.truth, nullptr);
    const Eigen::Vector3d z =
        (r.parameters.bias_nT - set.truth.bias_nT).cwiseQuotient(r.bias_sigma_nT());
    worst = std::max(worst, z.cwiseAbs().maxCoeff());
    if (!r.has_nonlinearity) ++refused;
  }
  const Eigen::Vector3d z = stats.rms_z();
  std::printf(
      "paper 3 h x %d: RMS(err/sigma) (%.3f, %.3f, %.3f), worst %.2f, extension refused "
      "in %d\n",
      runs, z(0), z(1), z(2), worst, refused);
  CHECK(refused >= 2);  // the case is exercised
  CHECK(worst <= 3.5);
  CHECK(z.maxCoeff() <= 1.5);
  CHECK(z.minCoeff() >= kNotUselesslyWide);
}

TEST_CASE("robust mode, 4 h windows with one 3 G spike: the outlier is found before the start") {
  // Found by a trial: one +-300 000 nT spike on bx dragged the (least-squares) centered start so
  // far on 4 h of paper data that the first robust refinement failed or converged elsewhere: 26
  // of 60 such fits accepted. The uncalibrated residual |B| - |h| now screens gross spikes first.
  int accepted = 0, total = 0;
  AxisStats stats;
  for (int run = 0; run < 6; ++run) {
    const SimulatedSet set = simulate("paper", 1 + static_cast<uint64_t>(run), 4.0);
    for (const std::size_t at : {std::size_t{49}, std::size_t{999}}) {
      for (const double spike_nT : {-300000.0, 300000.0}) {
        SampleSet spiked = set.samples;
        spiked[at].b_sensor_nT.x() += spike_nT;
        BatchCalibrationOptions o;
        o.robust = true;
        const CalibrationResult r = calibrate_batch(spiked, o);
        INFO("run " << run << " sample " << at << " spike " << spike_nT << ": " << r.message);
        ++total;
        if (!r.accepted) continue;
        ++accepted;
        CHECK(r.n_downweighted >= 1);
        stats.add(r, set.truth, nullptr);
      }
    }
  }
  const Eigen::Vector3d z = stats.rms_z();
  std::printf(
      "robust, paper 4 h + one 3 G spike: %d / %d accepted, RMS(err/sigma) (%.3f, %.3f, "
      "%.3f)\n",
      accepted, total, z(0), z(1), z(2));
  CHECK(accepted == total);
  CHECK(z.maxCoeff() <= 2.0);
}

TEST_CASE("least squares with one moderate spike: refused with the outliers named, robust fits") {
  // Found by a trial: one spike of 2 000-10 000 nT on by in 4 h of paper data, default twostep:
  // 19 of 57 accepted results were 4-6 sigma off (bias x 35 nT, pitch 5 sigma); the residual RMS
  // stayed within its gate.
  int refused = 0, robust_ok = 0, total = 0;
  for (int run = 0; run < 3; ++run) {
    const SimulatedSet set = simulate("paper", 1 + static_cast<uint64_t>(run), 4.0);
    for (const std::size_t at : {std::size_t{300}, std::size_t{698}}) {
      for (const double spike_nT : {2000.0, 10000.0}) {
        SampleSet spiked = set.samples;
        spiked[at].b_sensor_nT.y() += spike_nT;
        ++total;
        const CalibrationResult r = calibrate_batch(spiked, BatchCalibrationOptions());
        bool named = false;
        for (const std::string& reason : r.rejection_reasons) {
          named = named || reason.rfind("outliers:", 0) == 0;
        }
        if (!r.accepted && named) ++refused;
        BatchCalibrationOptions o;
        o.robust = true;
        const CalibrationResult rr = calibrate_batch(spiked, o);
        const Eigen::Vector3d z =
            (rr.parameters.bias_nT - set.truth.bias_nT).cwiseQuotient(rr.bias_sigma_nT());
        if (rr.accepted && z.cwiseAbs().maxCoeff() < 3.5) ++robust_ok;
      }
    }
  }
  std::printf("one spike on by, paper 4 h: %d / %d refused (outliers), robust %d / %d covered\n",
              refused, total, robust_ok, total);
  CHECK(refused == total);
  CHECK(robust_ok == total);
}
