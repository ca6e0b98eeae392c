// measure_bias_variability() against the simulator's truth: a sensor whose bias swings with an
// orbit-synchronous temperature (k_T = 1 nT/degC on every axis) that no sample reports (issue 20
// item 3), refitted by twostep over 12 h. The truth to compare with is the spread of the true
// bias's means over the same 30 min blocks (what the measurement can see of the swing).
#include <cmath>
#include <cstdlib>
#include <limits>

#include <catch2/catch.hpp>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/batch_calibration.hpp"
#include "pipeline/bias_variability.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
#include "tests/pipeline/orbit_swing_scenario.hpp"

using namespace magcal;

namespace {

struct SwingWindow {
  SampleSet samples;              // temperature unknown
  double block_mean_sd_nT = 0.0;  // sd of the true bias's 30 min block means (every axis alike)
};

SwingWindow simulate_swing(const char* preset, uint64_t seed, double amplitude_nT,
                           double hours = 12.0) {
  Simulator sim(test::orbit_swing_scenario(preset, seed, amplitude_nT, hours));
  SwingWindow w;
  SimulatedSample s;
  const BiasVariabilityOptions blocks;
  double block_sum = 0.0, sum = 0.0, sum2 = 0.0;
  int block_n = 0, n_blocks = 0;
  int64_t block_start = -1;
  const auto close_block = [&] {
    if (block_n < blocks.min_block_samples) return;
    const double mean = block_sum / block_n;
    sum += mean;
    sum2 += mean * mean;
    ++n_blocks;
  };
  while (sim.next(&s)) {
    CalibrationSample c = s.calibration_sample();
    c.temperature_C = std::numeric_limits<double>::quiet_NaN();
    w.samples.push_back(c);
    if (block_start < 0 || s.utime - block_start >= static_cast<int64_t>(blocks.block_s * 1e6)) {
      if (block_start >= 0) close_block();
      block_start = s.utime;
      block_sum = 0.0;
      block_n = 0;
    }
    block_sum += s.temperature_C;  // the bias's swing in nT at 1 nT/degC
    ++block_n;
  }
  close_block();
  w.block_mean_sd_nT = std::sqrt((sum2 - sum * sum / n_blocks) / (n_blocks - 1));
  return w;
}

}  // namespace

// A tumbling spacecraft sees the field from every direction within each block: the block biases
// are well determined, and the swing is measured at its size.
TEST_CASE("Tumbling, bias swing without temperature: its block means' spread is measured") {
  for (uint64_t seed : {1, 2, 3}) {
    const SwingWindow w = simulate_swing("tumbling", seed, 10.0);
    BatchCalibrationOptions blocks_alone;  // the swing's own estimate: orbit_synchronous_bias_test
    blocks_alone.orbit_synchronous_swing = false;
    const CalibrationResult refit = calibrate_batch(w.samples, blocks_alone);
    REQUIRE(refit.status == CalibrationStatus::kOk);
    const BiasVariability v = measure_bias_variability(w.samples, refit, 3.0);
    const Eigen::Vector3d excess_sd = v.excess_nT2().cwiseSqrt();
    INFO("seed " << seed << ": excess sd " << excess_sd.transpose() << " nT, true block means' sd "
                 << w.block_mean_sd_nT << " nT, " << v.blocks << " blocks");
    CHECK(v.significant);
    CHECK((excess_sd.array() > 0.75 * w.block_mean_sd_nT).all());
    CHECK((excess_sd.array() < 1.25 * w.block_mean_sd_nT).all());
    // In the refit's covariance and the filters' model error.
    CHECK(refit.bias_variability_nT2.isApprox(v.excess_nT2(), 1e-9));
    CHECK((refit.model_error_covariance().diagonal().head<3>().array() >=
           v.excess_nT2().array() - 1e-9)
              .all());
    CHECK((refit.bias_sigma_nT().array() >= excess_sd.array()).all());
  }
}

// The same sensors with a constant bias: nothing beyond the noise, the refit as before.
TEST_CASE("Constant bias, tumbling and nadir: no bias variability") {
  for (const char* preset : {"tumbling", "paper"}) {
    int alarms = 0;
    for (uint64_t seed : {1, 2, 3, 4, 5, 6}) {
      const SwingWindow w = simulate_swing(preset, seed, 0.0);
      BatchCalibrationOptions blocks_alone;  // the orbit swing's term: orbit_synchronous_bias_test
      blocks_alone.orbit_synchronous_swing = false;
      const CalibrationResult refit = calibrate_batch(w.samples, blocks_alone);
      alarms += refit.bias_variability_nT2.any();
      BatchCalibrationOptions without = blocks_alone;
      without.bias_variability = false;
      const CalibrationResult plain = calibrate_batch(w.samples, without);
      CHECK(plain.parameters.bias_nT == refit.parameters.bias_nT);
      CHECK((refit.covariance - plain.covariance).topLeftCorner<3, 3>().diagonal() ==
            refit.bias_variability_nT2);
    }
    INFO(preset);
    CHECK(alarms == 0);
  }
}

// Measurement behind the test's threshold (hidden: run it by name): per refit, the chi2 of each
// axis against the quantiles at 1e-3, 1e-4 and 1e-5, and the excess sd against the truth.
// MAGCAL_WINDOW_HOURS sets the window (default 12).
TEST_CASE("Measure: block-bias scatter of twostep refits, tumbling and nadir", "[.measure]") {
  const char* hours_text = std::getenv("MAGCAL_WINDOW_HOURS");
  const double hours = hours_text ? std::atof(hours_text) : 12.0;
  for (const char* preset : {"paper", "tumbling"}) {
    for (double amplitude_nT : {0.0, 5.0, 10.0}) {
      for (uint64_t seed = 1; seed <= (amplitude_nT > 0.0 ? 4u : 12u); ++seed) {
        const SwingWindow w = simulate_swing(preset, seed, amplitude_nT, hours);
        BatchCalibrationOptions options;
        options.bias_variability = false;
        const CalibrationResult refit = calibrate_batch(w.samples, options);
        const BiasVariability v = measure_bias_variability(w.samples, refit, 3.0);
        const double dof = v.blocks - 1;
        WARN(preset << ", swing +-" << amplitude_nT << " nT, seed " << seed << ": chi2 "
                    << (dof * v.scatter_nT2.cwiseQuotient(v.noise_nT2)).transpose() << " (0.1 % "
                    << chi_square_upper_quantile(dof, 1e-3) << ", 0.01 % "
                    << chi_square_upper_quantile(dof, 1e-4) << ", 0.001 % "
                    << chi_square_upper_quantile(dof, 1e-5) << "), excess sd "
                    << (v.scatter_nT2 - v.noise_nT2).cwiseMax(0.0).cwiseSqrt().transpose()
                    << " nT, true block means' sd " << w.block_mean_sd_nT << " nT");
      }
    }
  }
}
