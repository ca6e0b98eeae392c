// unresolved_orbit_synchronous_bias_swing() against the simulator's truth (issue 20 item 3): a
// sensor whose bias swings with an orbit-synchronous temperature that no sample reports.
#include <cmath>
#include <cstdlib>
#include <limits>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/orbit_synchronous_bias.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
#include "tests/pipeline/orbit_swing_scenario.hpp"

using namespace magcal;

namespace {

// hours of preset with a +-amplitude_nT orbit-synchronous swing (k_T = 1 nT/degC), temperature
// unknown.
struct SwingWindow {
  SampleSet samples;                     // temperature unknown
  double period_s = 0.0;                 // the swing's (the orbit's)
  std::vector<Eigen::Vector3d> bias_nT;  // the true current bias of each sample
  std::vector<double> temperature_C;     // the true temperature of each sample
};

SwingWindow simulate_swing(const char* preset, uint64_t seed, double amplitude_nT, double hours) {
  const Scenario sc = test::orbit_swing_scenario(preset, seed, amplitude_nT, hours);
  Simulator sim(sc);
  SwingWindow out;
  out.period_s = sim.truth().temperature_period_s;
  SimulatedSample s;
  while (sim.next(&s)) {
    CalibrationSample c = s.calibration_sample();
    c.temperature_C = std::numeric_limits<double>::quiet_NaN();
    out.samples.push_back(c);
    out.temperature_C.push_back(s.temperature_C);
    out.bias_nT.push_back(
        sc.sensor.bias_nT +
        Eigen::Vector3d::Constant(s.temperature_C - sc.sensor.reference_temperature_C));
  }
  return out;
}

// Per axis, the rms over the window of (bias - current bias) / sigma.
Eigen::Vector3d rms_error_over_sigma(const SwingWindow& w, const CalibrationResult& r) {
  Eigen::Vector3d err2 = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& b : w.bias_nT) err2 += (r.parameters.bias_nT - b).cwiseAbs2();
  return (err2 / static_cast<double>(w.bias_nT.size()))
      .cwiseSqrt()
      .cwiseQuotient(r.bias_sigma_nT());
}

}  // namespace

// Tumbling: the swing is separable at any period; its size is estimated, its period found, and
// the published bias sigma covers the current bias as its rms distance from the mean (~7.1 nT).
// Eight draws (each about 20 ms): an estimator whose amplitude sigma is 2x too small misses 3
// sigma on some axis of some draw in nearly every such set (24 checks, each then missing in 13 %).
TEST_CASE("Tumbling, +-10 nT orbit swing without temperature: estimated, in the refit's sigma") {
  for (uint64_t seed = 1; seed <= 8; ++seed) {
    const SwingWindow w = simulate_swing("tumbling", seed, 10.0, 12.0);
    BatchCalibrationOptions options;
    const CalibrationResult refit = calibrate_batch(w.samples, options);
    REQUIRE(refit.status == CalibrationStatus::kOk);
    const UnresolvedBiasSwing u =
        unresolved_orbit_synchronous_bias_swing(w.samples, refit, options.sigma_nT);
    INFO("seed " << seed << ": amplitude " << u.amplitude_nT.transpose() << " +- "
                 << u.amplitude_sigma_nT.transpose() << " nT at " << u.period_s / 60.0
                 << " min (true " << w.period_s / 60.0 << "), p " << u.period_probability);
    CHECK(std::abs(u.period_s - w.period_s) < 0.01 * w.period_s);
    CHECK(u.period_probability > 0.5);
    CHECK(refit.orbit_swing.detected());
    CHECK(((u.amplitude_nT.array() - 10.0).abs() < 3.0 * u.amplitude_sigma_nT.array()).all());
    // In the published covariance and the filters' model error.
    CHECK((refit.bias_variability_nT2.array() >= u.variance_nT2.array() - 1e-9).all());
    const Eigen::Vector3d rms_z = rms_error_over_sigma(w, refit);
    INFO("rms (bias - current bias) / sigma " << rms_z.transpose());
    CHECK((rms_z.array() > 0.8).all());  // not much wider than the swing
    CHECK((rms_z.array() < 1.2).all());
  }
}

// Nadir (the paper scenario): a first-harmonic swing is nearly a change of D; what the day's
// geometry separates is estimated, the rest is the prior's. Before, the refit's sigma was 13-35
// times too small on x and z (the rms of bias - current bias over the window).
// Eight draws per window length: the bar is per draw, so that one window whose sigma does not
// cover its error fails it.
TEST_CASE("Nadir, +-10 nT orbit swing without temperature: rms error within the sigma") {
  for (double hours : {12.0, 24.0}) {
    for (uint64_t seed = 1; seed <= 8; ++seed) {
      const SwingWindow w = simulate_swing("paper", seed, 10.0, hours);
      const CalibrationResult refit = calibrate_batch(w.samples, BatchCalibrationOptions{});
      REQUIRE(refit.status == CalibrationStatus::kOk);
      const Eigen::Vector3d rms_z = rms_error_over_sigma(w, refit);
      INFO(hours << " h, seed " << seed << ": rms (bias - current bias) / sigma "
                 << rms_z.transpose() << ", sigma " << refit.bias_sigma_nT().transpose());
      // The swing's peak is sqrt(2) times its rms: within 3 sigma where the rms is within 2.
      CHECK((rms_z.array() < 2.0).all());
    }
  }
}

// A temperature on every 6th sample (a 60 s housekeeping rate): too few for the temperature
// model, and too few to rule the swing out (a trial found such refits accepted with the current
// bias 14 sigma off on 40 % and 17 %).
TEST_CASE("Sparse temperatures (every 6th sample): the swing term as without any") {
  SwingWindow w = simulate_swing("tumbling", 1, 10.0, 12.0);
  for (std::size_t k = 0; k < w.samples.size(); k += 6)
    w.samples[k].temperature_C = w.temperature_C[k];
  const CalibrationResult refit = calibrate_batch(w.samples, BatchCalibrationOptions{});
  REQUIRE(refit.status == CalibrationStatus::kOk);
  CHECK_FALSE(refit.has_temperature_model);
  CHECK(refit.orbit_swing.periods_tried > 0);
  const Eigen::Vector3d rms_z = rms_error_over_sigma(w, refit);
  INFO("rms (bias - current bias) / sigma " << rms_z.transpose());
  CHECK((rms_z.array() < 1.5).all());
}

// Only without a temperature channel: a constant temperature (the paper sensor's) says the bias
// does not swing with it, and a window shorter than an orbit is not tested.
TEST_CASE("Constant bias: no swing term with a temperature channel, nor on a short window") {
  const SwingWindow w = simulate_swing("paper", 3, 0.0, 12.0);
  SampleSet with_temperature = w.samples;
  for (CalibrationSample& s : with_temperature) s.temperature_C = 20.0;
  const CalibrationResult known = calibrate_batch(with_temperature, BatchCalibrationOptions{});
  const CalibrationResult unknown = calibrate_batch(w.samples, BatchCalibrationOptions{});
  CHECK(known.bias_variability_nT2.isZero());
  CHECK((unknown.bias_variability_nT2.array() > 0.0).all());
  CHECK_FALSE(unknown.orbit_swing.detected());
  CHECK(known.parameters.packed() == unknown.parameters.packed());
  // Nadir without temperature: wider, and honest (the rms error well inside).
  CHECK((unknown.bias_sigma_nT().array() > known.bias_sigma_nT().array()).all());

  const SampleSet short_window(w.samples.begin(), w.samples.begin() + 700);  // 1.9 h
  const CalibrationResult fit = calibrate_batch(short_window, BatchCalibrationOptions{});
  const UnresolvedBiasSwing u = unresolved_orbit_synchronous_bias_swing(short_window, fit, 3.0);
  CHECK(u.periods_tried == 0);
  CHECK(u.variance_nT2.isZero());
}

TEST_CASE("Measure: unresolved orbit-synchronous swing", "[.measure]") {
  for (const char* preset : {"paper", "tumbling"}) {
    for (double amplitude_nT : {0.0, 10.0}) {
      for (double hours : {2.8, 6.0, 12.0, 24.0}) {
        for (uint64_t seed : {1, 2, 3}) {
          const SwingWindow w = simulate_swing(preset, seed, amplitude_nT, hours);
          BatchCalibrationOptions options;
          options.bias_variability = false;
          const CalibrationResult refit = calibrate_batch(w.samples, options);
          const CalibrationResult published = calibrate_batch(w.samples, BatchCalibrationOptions{});
          const UnresolvedBiasSwing u =
              unresolved_orbit_synchronous_bias_swing(w.samples, refit, options.sigma_nT);
          Eigen::Vector3d err2 = Eigen::Vector3d::Zero();
          for (const Eigen::Vector3d& b : w.bias_nT) {
            err2 += (refit.parameters.bias_nT - b).cwiseAbs2();
          }
          const Eigen::Vector3d rms = (err2 / w.bias_nT.size()).cwiseSqrt();
          const Eigen::Vector3d sigma = refit.bias_sigma_nT();
          const Eigen::Vector3d with = published.bias_sigma_nT();
          OrbitSynchronousBiasOptions at_truth;
          at_truth.min_period_s = at_truth.max_period_s = w.period_s;
          const UnresolvedBiasSwing t =
              unresolved_orbit_synchronous_bias_swing(w.samples, refit, options.sigma_nT, at_truth);
          WARN("true period " << w.period_s / 60.0 << " min: amplitude "
                              << t.amplitude_nT.transpose() << " +- "
                              << t.amplitude_sigma_nT.transpose() << ", sd "
                              << t.variance_nT2.cwiseSqrt().transpose());
          WARN(preset << " +-" << amplitude_nT << " " << hours << " h s" << seed
                      << ": rms err/sigma " << rms.cwiseQuotient(sigma).transpose() << " -> "
                      << rms.cwiseQuotient(with).transpose() << "; sigma " << sigma.transpose()
                      << " -> " << with.transpose() << "; amplitude " << u.amplitude_nT.transpose()
                      << " +- " << u.amplitude_sigma_nT.transpose() << " at " << u.period_s / 60.0
                      << " min p " << u.period_probability);
        }
      }
    }
  }
}
