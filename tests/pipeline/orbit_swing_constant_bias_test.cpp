// Constant-bias windows without a temperature channel: the refit tests whether the bias swings with
// the orbit (pipeline/orbit_synchronous_bias.hpp) instead of always adding the swing it cannot
// rule out, so its bias sigma says what the data know. Bars, per set of windows: every window's
// bias sigma within 3 times the Cramer-Rao bound at the truth, RMS(error / sigma) at least 0.5 on
// every axis (not uselessly wide), a swing reported `detected` (posterior probability above 0.99)
// on at most 5 % of the windows (measured: 0 of 140 with the "Measure" case's 20 seeds a set).
// The paper sensor (nadir and tumbling, 12 h) and the pure model (nadir, tumbling; 6 and 24 h).
// Before, with the whole swing always added: on the paper's nadir 12 h windows a bias sigma of
// 2.1-2.3 / 3.7-4.1 / 1.1-1.2 nT against 0.38 / 1.46 / 0.26 nT with a temperature channel.
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <tuple>

#include <catch2/catch.hpp>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"

using namespace magcal;

namespace {

constexpr double kMaxSigmaOverCrlb = 3.0;
constexpr double kMinRmsErrorOverSigma = 0.5;

// preset's sensor and noise in attitude_preset's attitude, temperature unknown on every sample.
Scenario constant_bias_scenario(const char* preset, const char* attitude_preset, uint64_t seed,
                                double hours) {
  Scenario sc = *scenario_preset(preset);
  sc.attitude = scenario_preset(attitude_preset)->attitude;
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  return sc;
}

struct SetOutcome {
  Eigen::Vector3d sum_z2 = Eigen::Vector3d::Zero();  // (error / sigma)^2
  Eigen::Vector3d worst_sigma_over_crlb = Eigen::Vector3d::Zero();
  int windows = 0, detected = 0;

  Eigen::Vector3d rms_z() const { return (sum_z2 / windows).cwiseSqrt(); }
};

SetOutcome run_set(const char* preset, const char* attitude_preset, double hours,
                   uint64_t first_seed, int n_seeds) {
  SetOutcome out;
  for (int i = 0; i < n_seeds; ++i) {
    Simulator sim(constant_bias_scenario(preset, attitude_preset,
                                         first_seed + static_cast<uint64_t>(i), hours));
    SampleSet samples;
    SimulatedSample s;
    while (sim.next(&s)) {
      CalibrationSample c = s.calibration_sample();
      c.temperature_C = std::numeric_limits<double>::quiet_NaN();
      samples.push_back(c);
    }
    const CalibrationResult r = calibrate_batch(samples, BatchCalibrationOptions{});
    REQUIRE(r.status == CalibrationStatus::kOk);
    REQUIRE(r.orbit_swing.periods_tried > 0);  // the swing was considered
    CalibrationParameters truth;
    truth.bias_nT = sim.truth().bias_nT;
    truth.D = sim.truth().D;
    const CrlbResult crlb = compute_crlb(samples, truth, sim.truth().noise_sigma_nT);
    REQUIRE(crlb.ok);
    const Eigen::Vector3d err = r.parameters.bias_nT - truth.bias_nT;
    out.sum_z2 += err.cwiseQuotient(r.bias_sigma_nT()).cwiseAbs2();
    out.worst_sigma_over_crlb =
        out.worst_sigma_over_crlb.cwiseMax(r.bias_sigma_nT().cwiseQuotient(crlb.sigma.head<3>()));
    out.detected += r.orbit_swing.detected();
    ++out.windows;
  }
  return out;
}

void check_set(const std::string& name, const SetOutcome& o) {
  INFO(name << ": " << o.windows << " windows, worst sigma / CRLB "
            << o.worst_sigma_over_crlb.transpose() << ", RMS(error / sigma) "
            << o.rms_z().transpose() << ", swing detected on " << o.detected);
  CHECK((o.worst_sigma_over_crlb.array() <= kMaxSigmaOverCrlb).all());
  CHECK((o.rms_z().array() >= kMinRmsErrorOverSigma).all());
  CHECK(o.detected * 20 <= o.windows);  // at most 5 %
}

}  // namespace

// 12 windows a set: a sigma 5 times too wide (the bound the swing test replaces) fails the first
// bar on any window and the second on the set (RMS(error / sigma) near 0.2).
TEST_CASE("Constant bias without a temperature channel, paper 12 h: sigma at the bound") {
  check_set("paper nadir 12 h", run_set("paper", "paper", 12.0, 100, 12));
  check_set("paper tumbling 12 h", run_set("paper", "tumbling", 12.0, 200, 12));
}

TEST_CASE("Constant bias without a temperature channel, pure model: sigma at the bound") {
  check_set("pure nadir 6 h", run_set("pure", "paper", 6.0, 300, 12));
  check_set("pure nadir 24 h", run_set("pure", "paper", 24.0, 400, 12));
  check_set("pure tumbling 24 h", run_set("pure", "pure", 24.0, 500, 12));
}

// Measurement, not a bar (hidden: run it by name): 20 seeds of each set.
TEST_CASE("Measure: constant bias without a temperature channel", "[.measure]") {
  for (const auto& [preset, attitude, hours] :
       {std::tuple{"paper", "paper", 12.0}, std::tuple{"paper", "tumbling", 12.0},
        std::tuple{"pure", "paper", 6.0}, std::tuple{"pure", "paper", 12.0},
        std::tuple{"pure", "paper", 24.0}, std::tuple{"pure", "pure", 6.0},
        std::tuple{"pure", "pure", 24.0}}) {
    const SetOutcome o = run_set(preset, attitude, hours, 1000, 20);
    WARN(preset << " sensor, " << attitude << " attitude, " << hours << " h: worst sigma / CRLB "
                << o.worst_sigma_over_crlb.transpose() << ", RMS(error / sigma) "
                << o.rms_z().transpose() << ", detected " << o.detected << " of " << o.windows);
  }
}
