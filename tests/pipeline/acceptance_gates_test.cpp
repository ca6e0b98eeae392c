// Acceptance gates (issue 7): each gate fires when its condition is violated and only then.
// A healthy result is built on simulated data (the paper and tumbling presets): parameters at
// the truth, covariance = inverse Fisher information, residual rms of |B_cal| - |h|.
#include "pipeline/acceptance_gates.hpp"

#include <cmath>
#include <random>
#include <string>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/scalar_measurement.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"

using namespace magcal;

namespace {

constexpr double kSigmaNT = 3.0;  // paper scenario white noise

struct SimulatedSet {
  SampleSet samples;
  TruthParameters truth;
};

SimulatedSet simulate_preset(const char* preset, double hours) {
  auto scenario = scenario_preset(preset);
  REQUIRE(scenario.has_value());
  scenario->duration_s = hours * 3600.0;
  REQUIRE(scenario->validate().empty());
  Simulator sim(*scenario);
  SimulatedSet out;
  for (const auto& s : sim.run()) out.samples.push_back(s.calibration_sample());
  out.truth = sim.truth();
  return out;
}

// Scaled Fisher information (estimation.md 2d) at p: condition number and smallest eigenvalue.
std::pair<double, double> scaled_fisher(const SampleSet& samples, const Vector9d& p) {
  Matrix9d F = Matrix9d::Zero();
  for (const auto& s : samples) {
    const RowVector9d J = scalar_measurement_jacobian(p, s.b_sensor_nT);
    const Eigen::Vector3d y = CalibrationParameters::from_packed(p).apply(s.b_sensor_nT);
    F += J.transpose() * J / scalar_noise_variance(y, kSigmaNT);
  }
  const Vector9d d = F.diagonal().cwiseSqrt().cwiseInverse();
  const Matrix9d Fs = d.asDiagonal() * F * d.asDiagonal();
  const Vector9d eig = Eigen::SelfAdjointEigenSolver<Matrix9d>(Fs).eigenvalues();
  return {eig(8) / eig(0), eig(0)};
}

Matrix9d inverse_fisher(const SampleSet& samples, const Vector9d& p) {
  Matrix9d F = Matrix9d::Zero();
  for (const auto& s : samples) {
    const RowVector9d J = scalar_measurement_jacobian(p, s.b_sensor_nT);
    const Eigen::Vector3d y = CalibrationParameters::from_packed(p).apply(s.b_sensor_nT);
    F += J.transpose() * J / scalar_noise_variance(y, kSigmaNT);
  }
  return F.inverse();
}

double residual_rms(const SampleSet& samples, const CalibrationParameters& params) {
  double ss = 0.0;
  for (const auto& s : samples) {
    const double r = params.apply(s.b_sensor_nT).norm() - s.h_body_nT.norm();
    ss += r * r;
  }
  return std::sqrt(ss / static_cast<double>(samples.size()));
}

struct Healthy {
  CalibrationResult result;
  GateInputs inputs;
  double coverage_min = 0.0;
};

// A result as a good refit would report it, with its gate inputs.
Healthy healthy_result(const SimulatedSet& set) {
  Healthy h;
  CalibrationResult& r = h.result;
  r.method = "twostep";
  r.status = CalibrationStatus::kOk;
  r.n_samples = static_cast<int>(set.samples.size());
  r.parameters = {set.truth.bias_nT, set.truth.D};
  r.covariance = inverse_fisher(set.samples, r.parameters.packed());
  r.residual_rms_nT = residual_rms(set.samples, r.parameters);
  const auto [cond, min_eig] = scaled_fisher(set.samples, r.parameters.packed());
  r.fisher_condition_number = cond;
  h.inputs.fisher_min_eigenvalue = min_eig;
  h.coverage_min = direction_coverage_eigenvalues(set.samples)(0);
  h.inputs.min_coverage_eigenvalue = h.coverage_min;
  return h;
}

bool has_reason(const GateVerdict& v, const std::string& key) {
  for (const auto& r : v.reasons)
    if (r.rfind(key, 0) == 0) return true;
  return false;
}

std::string joined(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& x : v) s += x + "; ";
  return s;
}

}  // namespace

TEST_CASE("healthy simulated results pass every default gate (the measurements behind them)",
          "[gates]") {
  for (const char* preset : {"paper", "tumbling", "pure"}) {
    const SimulatedSet set = simulate_preset(preset, 12.0);
    const Healthy h = healthy_result(set);
    const Eigen::Vector3d cov = direction_coverage_eigenvalues(set.samples);
    // Previous accepted refit: the same data, a different noise realisation would move b by
    // ~1 sigma; use the same result shifted by 1 sigma per axis.
    CalibrationResult previous = h.result;
    previous.parameters.bias_nT += h.result.bias_sigma_nT();
    GateInputs in = h.inputs;
    in.previous_accepted = &previous;
    const GateVerdict v = evaluate_gates(h.result, in);
    WARN(preset << ": residual_rms " << h.result.residual_rms_nT << " nT, fisher cond "
                << h.result.fisher_condition_number << ", fisher min eig "
                << h.inputs.fisher_min_eigenvalue << ", coverage eigenvalues " << cov.transpose()
                << ", bias sigma " << h.result.bias_sigma_nT().transpose() << " nT");
    INFO(joined(v.reasons));
    CHECK(v.accepted);
    CHECK(v.reasons.empty());
    CHECK(v.skipped.empty());
    CHECK(std::abs(cov.sum() - 1.0) < 1e-12);

    // The real batch refit (centered + LM + alignment + these gates) on the same data passes.
    const CalibrationResult fit = calibrate_batch(set.samples, BatchCalibrationOptions{});
    WARN(preset << " batch refit: status " << to_string(fit.status) << ", residual_rms "
                << fit.residual_rms_nT << " nT, fisher cond " << fit.fisher_condition_number << "; "
                << joined(fit.rejection_reasons));
    CHECK(fit.status == CalibrationStatus::kOk);
    CHECK(fit.accepted);
  }
}

TEST_CASE("each gate fires when its condition is violated, and only that gate", "[gates]") {
  const SimulatedSet set = simulate_preset("paper", 12.0);
  const Healthy h = healthy_result(set);
  CalibrationResult previous = h.result;
  GateInputs in = h.inputs;
  in.previous_accepted = &previous;
  REQUIRE(evaluate_gates(h.result, in).accepted);
  const GateOptions opt;

  auto expect_only = [&](const CalibrationResult& r, const GateInputs& gi, const char* key) {
    const GateVerdict v = evaluate_gates(r, gi, opt);
    INFO(key << ": " << joined(v.reasons));
    CHECK_FALSE(v.accepted);
    CHECK(has_reason(v, key));
    for (const auto& reason : v.reasons) CHECK(reason.rfind(key, 0) == 0);
  };

  SECTION("residual: a wrong reference (time-tag offset) inflates the residual") {
    // Shift the reference by 480 s: |h| no longer matches the measurement time.
    SampleSet shifted = set.samples;
    const std::size_t lag = 48;  // 480 s at 10 s
    for (std::size_t k = 0; k + lag < shifted.size(); ++k)
      shifted[k].h_body_nT = set.samples[k + lag].h_body_nT;
    shifted.resize(shifted.size() - lag);
    CalibrationResult r = h.result;
    r.residual_rms_nT = residual_rms(shifted, r.parameters);
    expect_only(r, in, "residual_rms");
    // Just below / above the threshold.
    r.residual_rms_nT = 0.99 * opt.residual_factor * opt.expected_residual_nT;
    CHECK(evaluate_gates(r, in, opt).accepted);
    r.residual_rms_nT = 1.01 * opt.residual_factor * opt.expected_residual_nT;
    CHECK_FALSE(evaluate_gates(r, in, opt).accepted);
  }
  SECTION("residual, chi-square mode") {
    GateOptions chi = opt;
    chi.residual_test = GateOptions::ResidualTest::kChiSquare;
    chi.expected_residual_nT = h.result.residual_rms_nT;  // exactly as expected: passes
    CHECK(evaluate_gates(h.result, in, chi).accepted);
    CalibrationResult r = h.result;
    // chi-square(N) has relative std sqrt(2/N): 1.5x the variance is ~20 sigma at N = 4320.
    r.residual_rms_nT = std::sqrt(1.5) * h.result.residual_rms_nT;
    const GateVerdict v = evaluate_gates(r, in, chi);
    CHECK_FALSE(v.accepted);
    CHECK(has_reason(v, "residual_chi2"));
  }
  SECTION("outliers: a least-squares fit resting on far residuals, named; disabled: passes") {
    GateInputs gi = in;
    gi.outliers.count = 1;
    gi.outliers.robust_sigmas = 10.0;
    gi.outliers.largest_sample = 1234;
    gi.outliers.largest_utime = 1600000123500000;
    gi.outliers.largest_residual_nT = 5012.0;
    expect_only(h.result, gi, "outliers");
    const GateVerdict v = evaluate_gates(h.result, gi, opt);
    CHECK(joined(v.reasons).find("sample 1234 (t_s 1600000123.500), 5012 nT") != std::string::npos);
    GateOptions off = opt;
    off.outliers_enabled = false;
    CHECK(evaluate_gates(h.result, gi, off).accepted);
  }
  SECTION("unmodelled: effects the fitted model cannot take; disabled: passes") {
    GateInputs gi = in;
    gi.unmodelled_effects = true;
    expect_only(h.result, gi, "centered solution");
    GateOptions off = opt;
    off.unmodelled_enabled = false;
    CHECK(evaluate_gates(h.result, gi, off).accepted);
  }
  SECTION("observability: a field direction that barely changes") {
    // Keep only a short arc (5 min): the direction turns by ~2 deg.
    SimulatedSet arc = set;
    arc.samples.resize(30);
    const Healthy bad = healthy_result(arc);
    CalibrationResult r = h.result;
    r.fisher_condition_number = bad.result.fisher_condition_number;
    INFO("short-arc fisher cond " << r.fisher_condition_number << ", coverage "
                                  << bad.coverage_min);
    expect_only(r, in, "fisher_condition");
    GateOptions with_min = opt;
    with_min.min_fisher_eigenvalue = 1e-6;
    GateInputs gi = in;
    gi.fisher_min_eigenvalue = 1e-9;
    const GateVerdict v = evaluate_gates(h.result, gi, with_min);
    CHECK(has_reason(v, "fisher_min_eigenvalue"));
    CHECK(v.reasons.size() == 1);
  }
  SECTION("coverage: directions confined to a narrow cone") {
    SimulatedSet arc = set;
    arc.samples.resize(30);
    GateInputs gi = in;
    gi.min_coverage_eigenvalue = direction_coverage_eigenvalues(arc.samples)(0);
    expect_only(h.result, gi, "coverage_min_eigenvalue");
  }
  SECTION("bounds: bias, scale, non-orthogonality") {
    CalibrationResult r = h.result;
    r.parameters.bias_nT.y() = -1.5 * opt.max_bias_nT;
    GateInputs no_previous = h.inputs;  // (the change gate would fire too)
    expect_only(r, no_previous, "bias_bound");
  }
  SECTION("bounds, each parameter class") {
    GateOptions no_change = opt;
    no_change.change_enabled = false;
    CalibrationResult r = h.result;
    r.parameters.D(1, 1) = 0.5;
    GateVerdict v = evaluate_gates(r, in, no_change);
    CHECK(has_reason(v, "scale_bound D22"));
    CHECK(v.reasons.size() == 1);
    r = h.result;
    r.parameters.D(0, 2) = r.parameters.D(2, 0) = -0.2;
    v = evaluate_gates(r, in, no_change);
    CHECK(has_reason(v, "nonorthogonality_bound D13"));
    CHECK(v.reasons.size() == 1);
    r = h.result;
    r.parameters.bias_nT.x() = NAN;
    CHECK(has_reason(evaluate_gates(r, in, no_change), "bias_bound x"));
  }
  SECTION("change since the last accepted result") {
    CalibrationResult r = h.result;
    // A change along z alone: chi2 = dz^2 [(P + P)^-1]_zz against the chi2(3) quantile.
    const Eigen::Matrix3d P_sum = 2.0 * h.result.covariance.topLeftCorner<3, 3>();
    const double info_zz = P_sum.inverse()(2, 2);
    const double q = chi_square_upper_quantile(3.0, opt.change_tail_probability);
    const double limit = std::max(std::sqrt(q / info_zz), opt.bias_change_floor_nT);
    r.parameters.bias_nT.z() += 1.1 * limit;
    expect_only(r, in, "bias_change chi2");
    r.parameters.bias_nT.z() = h.result.parameters.bias_nT.z() + 0.9 * limit;
    CHECK(evaluate_gates(r, in, opt).accepted);
    r = h.result;
    r.parameters.D(0, 0) += 0.01;
    expect_only(r, in, "D_change chi2");
    // No previous result: the gate is skipped, and says so.
    GateInputs none = h.inputs;
    const GateVerdict v = evaluate_gates(r, none, opt);
    CHECK(v.accepted);
    CHECK(v.skipped == std::vector<std::string>{"change"});
  }
  SECTION("disabled gates never fire") {
    GateOptions off = opt;
    off.residual_enabled = off.observability_enabled = off.coverage_enabled = off.bounds_enabled =
        off.change_enabled = false;
    CalibrationResult r = h.result;
    r.residual_rms_nT = 1e6;
    r.fisher_condition_number = 1e20;
    r.parameters.bias_nT.x() = 1e9;
    GateInputs gi = in;
    gi.min_coverage_eigenvalue = 0.0;
    const GateVerdict v = evaluate_gates(r, gi, off);
    CHECK(v.accepted);
    CHECK(v.skipped.empty());
  }
}

TEST_CASE("reason strings are short and stable", "[gates]") {
  CalibrationResult r;
  r.status = CalibrationStatus::kOk;
  r.residual_rms_nT = 812.3;
  r.fisher_condition_number = 10.0;
  const GateVerdict v = evaluate_gates(r, {});
  REQUIRE(v.reasons.size() == 1);
  CHECK(v.reasons[0] == "residual_rms 812.3 nT > 3 x expected 7.5 nT");
  CHECK(v.skipped == std::vector<std::string>{"coverage", "change"});
}

TEST_CASE("apply_verdict: rejected status, lowest non-zero status wins", "[gates]") {
  GateVerdict rejected;
  rejected.accepted = false;
  rejected.reasons = {"residual_rms 812.3 nT > 3 x expected 7.5 nT"};
  CalibrationResult r;
  r.status = CalibrationStatus::kOk;
  apply_verdict(r, rejected);
  CHECK_FALSE(r.accepted);
  CHECK(r.status == CalibrationStatus::kRejected);
  CHECK(r.rejection_reasons == rejected.reasons);

  r.status = CalibrationStatus::kNotConverged;
  apply_verdict(r, rejected);
  CHECK(r.status == CalibrationStatus::kNotConverged);  // 1 < 4 stays
  r.status = CalibrationStatus::kFailed;
  apply_verdict(r, rejected);
  CHECK(r.status == CalibrationStatus::kFailed);

  CalibrationResult ok;
  ok.status = CalibrationStatus::kOk;
  apply_verdict(ok, GateVerdict{});
  CHECK(ok.accepted);
  CHECK(ok.status == CalibrationStatus::kOk);
  CHECK(ok.rejection_reasons.empty());
}

TEST_CASE("gate helpers: coverage eigenvalues, chi-square quantile, option validation", "[gates]") {
  // Isotropic directions: eigenvalues ~1/3; a plane: smallest 0; empty: NaN.
  std::mt19937 rng(4);
  std::normal_distribution<double> n(0.0, 1.0);
  SampleSet iso(20000), plane(100), empty;
  for (auto& s : iso) s.b_sensor_nT = Eigen::Vector3d(n(rng), n(rng), n(rng)) * 30000.0;
  for (auto& s : plane) s.b_sensor_nT = Eigen::Vector3d(n(rng), n(rng), 0.0);
  const Eigen::Vector3d e = direction_coverage_eigenvalues(iso);
  CHECK((e.array() - 1.0 / 3.0).abs().maxCoeff() < 0.02);
  CHECK(direction_coverage_eigenvalues(plane)(0) < 1e-15);
  CHECK(std::isnan(direction_coverage_eigenvalues(empty)(0)));
  plane[0].b_sensor_nT.x() = NAN;  // skipped, not propagated
  CHECK(std::isfinite(direction_coverage_eigenvalues(plane)(0)));

  // Published chi-square table values (upper 5 % / 0.1 %): chi2(10) 18.307 / 29.588,
  // chi2(100) 124.342 / 149.449. Wilson–Hilferty is good to ~0.5 % at these dof.
  CHECK(chi_square_upper_quantile(10, 0.05) == Approx(18.307).epsilon(0.005));
  CHECK(chi_square_upper_quantile(10, 0.001) == Approx(29.588).epsilon(0.01));
  CHECK(chi_square_upper_quantile(100, 0.05) == Approx(124.342).epsilon(0.002));
  CHECK(chi_square_upper_quantile(100, 0.001) == Approx(149.449).epsilon(0.002));
  CHECK(std::isnan(chi_square_upper_quantile(-1, 0.05)));

  CHECK(GateOptions{}.validate().empty());
  GateOptions bad;
  bad.expected_residual_nT = 0.0;
  CHECK_FALSE(bad.validate().empty());
  bad = GateOptions{};
  bad.min_coverage_eigenvalue = 0.5;
  CHECK_FALSE(bad.validate().empty());
}
