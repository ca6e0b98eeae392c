// Bias temperature model in the batch refit (issue 20): on 12 h paper-scenario sets with an
// orbit-synchronous +-15 degC temperature, the coefficient is fitted jointly with b and D, its
// sigma and the bias sigma at the reference temperature cover the real error, and the model stays
// off on a sensor without the effect and on samples without a temperature. Truth: the
// simulator's, which the estimator never sees (the bias at the fit's reference temperature is
// b0 + k (T0 - T_ref,truth)).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <tuple>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/crlb.hpp"

#include "pipeline/batch_calibration.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/sensor_model.hpp"
#include "pipeline/simulator.hpp"
#include "pipeline/temperature_model.hpp"

using namespace magcal;

namespace {

struct ThermalSet {
  SampleSet samples;
  TruthParameters truth;
};

// The paper scenario (or another preset) with an orbit-synchronous temperature (+-amplitude_C
// about 20 degC) and the given bias temperature coefficient.
ThermalSet simulate_thermal(const char* preset, uint64_t seed, const Eigen::Vector3d& k_nT_per_C,
                            double hours = 12.0, double phase_deg = 0.0,
                            double amplitude_C = 15.0) {
  Scenario sc = *scenario_preset(preset);
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  sc.sensor.temperature_coefficient_nT_per_C = k_nT_per_C;
  sc.sensor.temperature_mean_C = 20.0;
  sc.sensor.temperature_amplitude_C = amplitude_C;
  sc.sensor.temperature_period_s = 0.0;  // orbital
  sc.sensor.temperature_phase_deg = phase_deg;
  REQUIRE(sc.validate().empty());
  Simulator sim(sc);
  ThermalSet out;
  out.truth = sim.truth();
  SimulatedSample s;
  while (sim.next(&s)) out.samples.push_back(s.calibration_sample());
  return out;
}

// The true bias at the fit's reference temperature.
Eigen::Vector3d true_bias_at(const TruthParameters& t, double temperature_C) {
  return t.bias_nT +
         t.temperature_coefficient_nT_per_C * (temperature_C - t.reference_temperature_C);
}

// Counts of |error| <= 3 sigma over axes and results.
struct Coverage {
  int within = 0, total = 0;
  double sum_z2 = 0.0;
  void add(const Eigen::Vector3d& err, const Eigen::Vector3d& sigma) {
    for (int i = 0; i < 3; ++i) {
      const double z = err(i) / sigma(i);
      within += std::abs(z) <= 3.0 ? 1 : 0;
      sum_z2 += z * z;
      ++total;
    }
  }
  double fraction() const { return total > 0 ? static_cast<double>(within) / total : 0.0; }
  double rms_z() const { return total > 0 ? std::sqrt(sum_z2 / total) : 0.0; }
};

}  // namespace

TEST_CASE("thermal paper 12 h, k_T 0.5-2 nT/degC: k_T and b(T0) within their sigmas") {
  const int runs = 24;
  std::mt19937_64 rng(20);
  std::uniform_real_distribution<double> magnitude(0.5, 2.0), phase(0.0, 360.0);
  std::bernoulli_distribution sign(0.5);
  Coverage bias, coefficient;
  int modelled = 0, accepted = 0;
  Eigen::Vector3d sum_bias_sigma = Eigen::Vector3d::Zero(),
                  worst_bias_sigma = Eigen::Vector3d::Zero();
  Eigen::Vector3d worst_cost = Eigen::Vector3d::Zero();
  double fit_ms = 0.0;
  int bar_below_crlb = 0;  // axis checks where 1 nT is below the Cramer-Rao bound
  double largest_crlb_over_bar = 0.0;
  for (int run = 0; run < runs; ++run) {
    Eigen::Vector3d k;
    for (int i = 0; i < 3; ++i) k(i) = (sign(rng) ? 1.0 : -1.0) * magnitude(rng);
    const ThermalSet set = simulate_thermal("paper", 3000 + run, k, 12.0, phase(rng));
    const auto t0 = std::chrono::steady_clock::now();
    const CalibrationResult r = calibrate_batch(set.samples, BatchCalibrationOptions{});
    fit_ms +=
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    // The same orbit and noise seed at a constant temperature: the sigma the geometry allows
    // without the effect.
    const ThermalSet constant = simulate_thermal("paper", 3000 + run, k, 12.0, 0.0, 0.0);
    const CalibrationResult rc = calibrate_batch(constant.samples, BatchCalibrationOptions{});
    INFO("run " << run << ": " << r.message << ", k " << k.transpose());
    REQUIRE(r.status == CalibrationStatus::kOk);
    REQUIRE(rc.status == CalibrationStatus::kOk);
    CHECK_FALSE(rc.has_temperature_model);
    CHECK(r.has_temperature_model);
    if (!r.has_temperature_model) continue;
    ++modelled;
    accepted += r.accepted ? 1 : 0;
    const Eigen::Vector3d b_sigma = r.bias_sigma_nT();
    sum_bias_sigma += b_sigma;
    worst_bias_sigma = worst_bias_sigma.cwiseMax(b_sigma);
    const Eigen::Vector3d cost = b_sigma.cwiseQuotient(rc.bias_sigma_nT());
    worst_cost = worst_cost.cwiseMax(cost);
    // The bar is 1 nT per axis where the geometry allows it: where even the Cramer-Rao bound of
    // the constant-temperature set, white noise alone and no k_T to estimate, is above 1 nT (y,
    // the orbit normal of a nadir spacecraft), no estimator meets it, and what the temperature
    // term costs there is bounded instead.
    CalibrationParameters truth_p;
    truth_p.bias_nT = constant.truth.bias_nT;
    truth_p.D = constant.truth.D;
    const CrlbResult bound = compute_crlb(constant.samples, truth_p, constant.truth.noise_sigma_nT);
    REQUIRE(bound.ok);
    for (int i = 0; i < 3; ++i) {
      INFO("axis " << i << ": CRLB " << bound.sigma(i) << " nT, sigma " << b_sigma(i) << " nT");
      if (bound.sigma(i) <= 1.0) {
        CHECK(b_sigma(i) <= 1.0);
      } else {
        ++bar_below_crlb;
        largest_crlb_over_bar = std::max(largest_crlb_over_bar, bound.sigma(i));
      }
    }
    CHECK(cost.maxCoeff() <= 1.6);
    if (!r.accepted) continue;
    bias.add(r.parameters.bias_nT - true_bias_at(set.truth, r.reference_temperature_C), b_sigma);
    coefficient.add(r.temperature_coefficient_nT_per_C - k,
                    r.temperature_coefficient_sigma_nT_per_C());
  }
  const Eigen::Vector3d mean_sigma = sum_bias_sigma / std::max(modelled, 1);
  std::printf(
      "thermal paper 12 h x %d: temperature model in %d, accepted %d; bias sigma mean (%.3f, "
      "%.3f, %.3f) nT, worst (%.3f, %.3f, %.3f) nT, worst ratio to the constant-temperature fit "
      "(%.2f, %.2f, %.2f); within 3 sigma: b(T0) %d / %d (RMS z %.2f), k_T %d / %d (RMS z %.2f); "
      "%.1f ms per fit\n",
      runs, modelled, accepted, mean_sigma(0), mean_sigma(1), mean_sigma(2), worst_bias_sigma(0),
      worst_bias_sigma(1), worst_bias_sigma(2), worst_cost(0), worst_cost(1), worst_cost(2),
      bias.within, bias.total, bias.rms_z(), coefficient.within, coefficient.total,
      coefficient.rms_z(), fit_ms / runs);
  std::printf(
      "  1 nT bar below the constant-temperature Cramer-Rao bound in %d axis checks (largest "
      "bound %.3f nT): there the ratio to the constant-temperature fit is the bar\n",
      bar_below_crlb, largest_crlb_over_bar);
  CHECK(modelled == runs);
  CHECK(accepted >= runs - 1);
  // 99 % within 3 sigma: over 2 x 3 x 24 = 144 checks, at most one miss (a sigma that is right
  // misses 3 sigma in 0.27 % of draws: 0.4 expected).
  CHECK(bias.within + coefficient.within >= bias.total + coefficient.total - 1);
  CHECK(bias.rms_z() <= 1.5);
  CHECK(coefficient.rms_z() <= 1.5);
}

TEST_CASE("thermal paper 12 h without a temperature coefficient: the model stays off") {
  const int runs = 24;
  int modelled = 0, accepted = 0;
  Coverage bias, coefficient;
  for (int run = 0; run < runs; ++run) {
    const ThermalSet set =
        simulate_thermal("paper", 4000 + run, Eigen::Vector3d::Zero(), 12.0, 37.0 * run);
    const CalibrationResult r = calibrate_batch(set.samples, BatchCalibrationOptions{});
    INFO("run " << run << ": " << r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    accepted += r.accepted ? 1 : 0;
    if (!r.has_temperature_model) continue;
    ++modelled;  // a BIC false positive: still within its sigmas
    bias.add(r.parameters.bias_nT - set.truth.bias_nT, r.bias_sigma_nT());
    coefficient.add(r.temperature_coefficient_nT_per_C, r.temperature_coefficient_sigma_nT_per_C());
  }
  std::printf(
      "paper 12 h +-15 degC, k_T = 0, x %d: temperature model in %d (false positives), accepted "
      "%d; their b and k_T within 3 sigma: %d / %d, %d / %d\n",
      runs, modelled, accepted, bias.within, bias.total, coefficient.within, coefficient.total);
  CHECK(modelled <= 1);
  CHECK(accepted == runs);
  CHECK(bias.within == bias.total);
  CHECK(coefficient.within == coefficient.total);
}

TEST_CASE("no temperature on any sample: the fit is the one without the temperature model") {
  const ThermalSet set = simulate_thermal("paper", 5000, Eigen::Vector3d(1.5, -1.0, 2.0), 6.0);
  SampleSet unknown = set.samples;
  for (CalibrationSample& s : unknown) s.temperature_C = std::numeric_limits<double>::quiet_NaN();
  for (auto method :
       {BatchCalibrationOptions::Method::kTwoStep, BatchCalibrationOptions::Method::kCentered}) {
    BatchCalibrationOptions o;
    o.method = method;
    const CalibrationResult r = calibrate_batch(unknown, o);
    BatchCalibrationOptions off = o;
    off.temperature_model = false;
    const CalibrationResult r_off = calibrate_batch(set.samples, off);
    INFO(to_string(method) << ": " << r.message);
    CHECK_FALSE(r.has_temperature_model);
    CHECK(std::isnan(r.reference_temperature_C));
    CHECK(r.status == r_off.status);
    CHECK(r.parameters.packed() == r_off.parameters.packed());
    // Without a temperature channel the bias may swing with the orbit unseen
    // (orbit_synchronous_bias_test): twostep's bias variance grows by that term alone.
    Matrix9d swing = Matrix9d::Zero();
    swing.diagonal().head<3>() = r.bias_variability_nT2 - r_off.bias_variability_nT2;
    CHECK((r.covariance - swing).isApprox(r_off.covariance, 1e-12));
    CHECK((swing.diagonal().array() >= 0.0).all());
    if (method == BatchCalibrationOptions::Method::kCentered) CHECK(swing.isZero());
    CHECK(r.n_samples == r_off.n_samples);
  }
}

TEST_CASE("partial temperature: the samples that carry one are fitted, too few leave it off") {
  const Eigen::Vector3d k(1.5, -1.0, 2.0);
  const ThermalSet set = simulate_thermal("paper", 5100, k, 12.0);
  const int n = static_cast<int>(set.samples.size());
  SECTION("the first quarter without a temperature: modelled on the other 75 %") {
    SampleSet partial = set.samples;
    for (int i = 0; i < n / 4; ++i) partial[i].temperature_C = std::nan("");
    const CalibrationResult r = calibrate_batch(partial, BatchCalibrationOptions{});
    INFO(r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    REQUIRE(r.has_temperature_model);
    CHECK(r.n_samples == n - n / 4);
    const Eigen::Vector3d bias_z =
        (r.parameters.bias_nT - true_bias_at(set.truth, r.reference_temperature_C))
            .cwiseQuotient(r.bias_sigma_nT());
    const Eigen::Vector3d k_z = (r.temperature_coefficient_nT_per_C - k)
                                    .cwiseQuotient(r.temperature_coefficient_sigma_nT_per_C());
    CHECK(bias_z.cwiseAbs().maxCoeff() <= 3.0);
    CHECK(k_z.cwiseAbs().maxCoeff() <= 3.0);
  }
  SECTION("60 % without a temperature: no temperature model, every sample fitted") {
    SampleSet partial = set.samples;
    for (int i = 0; i < n * 6 / 10; ++i) partial[i].temperature_C = std::nan("");
    const CalibrationResult r = calibrate_batch(partial, BatchCalibrationOptions{});
    INFO(r.message);
    CHECK_FALSE(r.has_temperature_model);
    CHECK(r.n_samples == n);
  }
}

TEST_CASE("centered solution with the temperature columns: k_T within its sigmas") {
  // The pure model (tumbling, white noise) with a temperature coefficient: the centered
  // solution's own gates refuse the paper sensor's unmodelled effects.
  const Eigen::Vector3d k(-0.8, 1.7, 1.1);
  Coverage bias, coefficient;
  for (int run = 0; run < 6; ++run) {
    const ThermalSet set = simulate_thermal("pure", 5200 + run, k, 6.0, 60.0 * run);
    BatchCalibrationOptions o;
    o.method = BatchCalibrationOptions::Method::kCentered;
    const CalibrationResult r = calibrate_batch(set.samples, o);
    INFO("run " << run << ": " << r.message);
    REQUIRE(r.status == CalibrationStatus::kOk);
    REQUIRE(r.has_temperature_model);
    bias.add(r.parameters.bias_nT - true_bias_at(set.truth, r.reference_temperature_C),
             r.bias_sigma_nT());
    coefficient.add(r.temperature_coefficient_nT_per_C - k,
                    r.temperature_coefficient_sigma_nT_per_C());
  }
  std::printf("pure 6 h x 6, centered: b(T0) within 3 sigma %d / %d, k_T %d / %d\n", bias.within,
              bias.total, coefficient.within, coefficient.total);
  CHECK(bias.within == bias.total);
  CHECK(coefficient.within == coefficient.total);
}

namespace {

struct DriftSet {
  SampleSet samples;
  Eigen::Vector3d bias_at_end_nT;  // the true bias at the last sample
};

// The paper scenario with a linear bias drift (nT/h per axis), no temperature effect.
DriftSet simulate_drift(uint64_t seed, const Eigen::Vector3d& drift_nT_per_h, double hours) {
  Scenario sc = *scenario_preset("paper");
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  sc.sensor.drift_nT_per_day = 24.0 * drift_nT_per_h;
  REQUIRE(sc.validate().empty());
  Simulator sim(sc);
  DriftSet out;
  SimulatedSample s;
  while (sim.next(&s)) out.samples.push_back(s.calibration_sample());
  const CalibrationSample& last = out.samples.back();
  out.bias_at_end_nT = SensorModel(sc.sensor).bias_nT(
      static_cast<double>(last.utime - sc.epoch_utime) * 1e-6, last.temperature_C);
  return out;
}

}  // namespace

// The bias rate model (time as the covariate of the temperature model's columns): a drift of
// 0.3-3 nT/h per axis (log-uniform, random signs) over a 12 h paper window is fitted, its rate and
// the bias at the window's end within 3 sigma of the truth; on a constant bias the model stays off.
TEST_CASE("bias drift, paper 12 h: the rate and the bias at the window's end within 3 sigma") {
  const int runs = 12;
  std::mt19937_64 rng(21);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  Coverage bias, rate;
  int with_rate = 0, accepted = 0;
  for (int run = 0; run < runs; ++run) {
    Eigen::Vector3d r;
    for (int i = 0; i < 3; ++i)
      r(i) = (unit(rng) < 0.5 ? -1.0 : 1.0) * 0.3 * std::pow(10.0, unit(rng));
    const DriftSet set = simulate_drift(6000 + run, r, 12.0);
    const CalibrationResult fit = calibrate_batch(set.samples, BatchCalibrationOptions{});
    INFO("run " << run << ": " << fit.message << ", drift " << r.transpose() << " nT/h");
    REQUIRE(fit.status == CalibrationStatus::kOk);
    CHECK(fit.has_bias_rate);
    CHECK_FALSE(fit.has_temperature_model);
    if (!fit.has_bias_rate) continue;
    ++with_rate;
    accepted += fit.accepted ? 1 : 0;
    bias.add(fit.parameters.bias_nT - set.bias_at_end_nT, fit.bias_sigma_nT());
    rate.add(fit.bias_rate_nT_per_h - r, fit.bias_rate_sigma_nT_per_h());
  }
  std::printf(
      "paper 12 h, drift 0.3-3 nT/h, x %d: rate model in %d, accepted %d; bias at the end and "
      "rate within 3 sigma: %d / %d, %d / %d (RMS z %.2f, %.2f)\n",
      runs, with_rate, accepted, bias.within, bias.total, rate.within, rate.total, bias.rms_z(),
      rate.rms_z());
  // Measured over 80 runs: 240 / 240 and 239 / 240 within 3 sigma (RMS z 0.88, 1.06). A miss is
  // allowed here as in the temperature case (0.27 % of draws).
  CHECK(bias.within + rate.within >= bias.total + rate.total - 1);
  CHECK(bias.rms_z() <= 1.5);
  CHECK(rate.rms_z() <= 1.5);
}

// A sensor that both cycles thermally and drifts (the shipped deploy/scenarios/tumbling.toml's
// kind: +-15 degC, a few nT/day): the temperature model and, beside it, the bias rate of the
// samples moved to T0. Before, the temperature model alone published the bias at a 24 h window's
// end up to 18 sigma off (sigma 0.14 nT; a fresh-user trial). Control: the thermal sensor without
// drift takes no rate.
TEST_CASE("thermal and drifting, 24 h: the bias rate beside the temperature model") {
  const Eigen::Vector3d k(1.0, -0.8, 1.2);
  Coverage bias, rate, coefficient;
  int false_rates = 0;
  for (const char* preset : {"tumbling", "paper"}) {
    for (uint64_t seed = 1; seed <= 5; ++seed) {
      for (const bool drifting : {true, false}) {
        Scenario sc = *scenario_preset(preset);
        sc.seed = seed;
        sc.duration_s = 24.0 * 3600.0;
        sc.sensor.temperature_coefficient_nT_per_C = k;
        sc.sensor.temperature_mean_C = 20.0;
        sc.sensor.temperature_amplitude_C = 15.0;
        sc.sensor.temperature_period_s = 0.0;
        const Eigen::Vector3d drift_nT_per_day(5.0, -4.0, 3.0);
        sc.sensor.drift_nT_per_day = drifting ? drift_nT_per_day : Eigen::Vector3d::Zero();
        Simulator sim(sc);
        const TruthParameters truth = sim.truth();
        SampleSet samples;
        SimulatedSample x;
        while (sim.next(&x)) samples.push_back(x.calibration_sample());
        const CalibrationResult fit = calibrate_batch(samples, BatchCalibrationOptions{});
        INFO(preset << " seed " << seed << (drifting ? " drifting" : " no drift") << ": "
                    << fit.message);
        REQUIRE(fit.status == CalibrationStatus::kOk);
        REQUIRE(fit.has_temperature_model);
        coefficient.add(fit.temperature_coefficient_nT_per_C - k,
                        fit.temperature_coefficient_sigma_nT_per_C());
        if (!drifting) {
          false_rates += fit.has_bias_rate;
          continue;
        }
        CHECK(fit.has_bias_rate);
        const double end_h = static_cast<double>(samples.back().utime - samples.front().utime) /
                             3.6e9;  // the simulator's drift runs from the first sample
        const Eigen::Vector3d at_end =
            true_bias_at(truth, fit.reference_temperature_C) + drift_nT_per_day * (end_h / 24.0);
        bias.add(fit.parameters.bias_nT - at_end, fit.bias_sigma_nT());
        if (fit.has_bias_rate) {
          rate.add(fit.bias_rate_nT_per_h - drift_nT_per_day / 24.0,
                   fit.bias_rate_sigma_nT_per_h());
        }
      }
    }
  }
  std::printf(
      "thermal + drift, 24 h, tumbling and paper x 5: bias at the end (T0) within 3 sigma %d / %d "
      "(RMS z %.2f), rate %d / %d (%.2f), k_T %d / %d (%.2f); rates on the thermal sensor without "
      "drift: %d of 10\n",
      bias.within, bias.total, bias.rms_z(), rate.within, rate.total, rate.rms_z(),
      coefficient.within, coefficient.total, coefficient.rms_z(), false_rates);
  // Measured over 10 seeds each: bias 60 / 60 within 3 sigma (RMS z 1.11), rate 60 / 60 (0.98),
  // k_T 120 / 120 (0.95), no rate without drift; here (5 seeds) 30 / 30 (1.21), 30 / 30 (1.02),
  // 60 / 60 (0.98). With k_T fitted once beside the unmodelled drift (before the coordinate
  // descent in with_bias_rate_beside_temperature()): k_T 115 / 120 (RMS z 1.39), the paper
  // sensor's k_z 2.7-3.6 sigma off in 5 of 5 drifting seeds.
  CHECK(bias.within >= bias.total - 1);
  CHECK(bias.rms_z() <= 1.5);
  CHECK(rate.within == rate.total);
  CHECK(coefficient.within >= coefficient.total - 1);
  CHECK(coefficient.rms_z() <= 1.25);
  CHECK(false_rates == 0);
}

// Measured: 0 of 300 (6, 12 and 24 h x 100 seeds).
TEST_CASE("constant bias, paper 12 h and 24 h: the bias rate model stays off") {
  int with_rate = 0, fits = 0;
  for (double hours : {12.0, 24.0}) {
    for (int run = 0; run < 12; ++run) {
      const DriftSet set = simulate_drift(7000 + run, Eigen::Vector3d::Zero(), hours);
      const CalibrationResult fit = calibrate_batch(set.samples, BatchCalibrationOptions{});
      INFO(hours << " h, run " << run << ": " << fit.message);
      REQUIRE(fit.status == CalibrationStatus::kOk);
      ++fits;
      with_rate += fit.has_bias_rate ? 1 : 0;
    }
  }
  std::printf("paper constant bias, 12 h and 24 h, x %d: bias rate model in %d\n", fits, with_rate);
  CHECK(with_rate == 0);
}

namespace {

// Every number a batch result publishes (b, D and their covariances, the estimator-bias
// correction, the model extension and its doubt, residual evidence, alignment), in a fixed order.
std::vector<double> published_numbers(const CalibrationResult& r) {
  std::vector<double> v;
  auto add = [&v](const auto& m) { v.insert(v.end(), m.data(), m.data() + m.size()); };
  add(r.parameters.packed());
  add(r.covariance);
  add(r.covariance_white_noise);
  add(r.estimator_bias);
  add(r.model_error);
  add(r.nonlinearity_k3);
  add(r.hysteresis_nT);
  add(r.extension_covariance);
  add(r.alignment.R_sensor_from_body);
  add(r.alignment.angle_covariance_rad2);
  v.insert(v.end(),
           {r.noise_scale, r.residual_autocorrelation, r.residual_rms_nT, r.fisher_condition_number,
            static_cast<double>(r.covariance_lag_window), static_cast<double>(r.iterations)});
  return v;
}

}  // namespace

// The bias rate is a candidate within one fit (stage 1's model choice, which makes the choice
// without it from the same 9-parameter fit): where the rate is not kept, the result is exactly
// the fit without the rate model, every field. Sets: the paper sensor with a constant bias (BIC
// prefers the rate to the 9-parameter fit, not on top of the model extension), the same with a
// small drift and ten times the paper's nonlinearity and hysteresis (strongly autocorrelated
// residuals: BIC takes the rate, the significance test refuses it; the gates reject the fit), and a
// tumbling spacecraft with a constant bias (BIC does not prefer the rate even to the 9-parameter
// fit).
TEST_CASE("a window whose bias rate is not kept: the fit without the rate model, bit for bit") {
  struct Case {
    const char* preset;
    double misfit_fraction_fs;  // nonlinearity and hysteresis, fraction of full scale
    Eigen::Vector3d drift_nT_per_h;
  };
  for (const Case& c : {Case{"paper", 1e-4, Eigen::Vector3d::Zero()},
                        Case{"paper", 1e-3, Eigen::Vector3d(0.25, 0.0, -0.25)},
                        Case{"tumbling", 0.0, Eigen::Vector3d::Zero()}}) {
    Scenario sc = *scenario_preset(c.preset);
    sc.seed = 7300;
    sc.duration_s = 12.0 * 3600.0;
    sc.sensor.nonlinearity_fraction_fs = sc.sensor.hysteresis_fraction_fs = c.misfit_fraction_fs;
    sc.sensor.drift_nT_per_day = 24.0 * c.drift_nT_per_h;
    REQUIRE(sc.validate().empty());
    Simulator sim(sc);
    SampleSet samples;
    SimulatedSample s;
    while (sim.next(&s)) samples.push_back(s.calibration_sample());

    BatchCalibrationOptions without_rate_model;
    without_rate_model.bias_rate_model = false;
    const CalibrationResult a = calibrate_batch(samples, BatchCalibrationOptions{});
    const CalibrationResult b = calibrate_batch(samples, without_rate_model);
    INFO(c.preset << ", misfit " << c.misfit_fraction_fs << ": " << a.message);
    REQUIRE((a.status == CalibrationStatus::kOk || a.status == CalibrationStatus::kRejected));
    REQUIRE_FALSE(a.has_bias_rate);
    CHECK(published_numbers(a) == published_numbers(b));
    CHECK(std::tie(a.status, a.accepted, a.has_nonlinearity, a.has_alignment, a.message,
                   a.rejection_reasons) == std::tie(b.status, b.accepted, b.has_nonlinearity,
                                                    b.has_alignment, b.message,
                                                    b.rejection_reasons));
  }
}
