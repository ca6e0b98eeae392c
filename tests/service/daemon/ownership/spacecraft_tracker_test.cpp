// The tracker's temperature correction: a UKF anchored on a refit with a bias
// temperature model filters B' = B - (I + D)^-1 k_T (T - T0), so it estimates the bias at T0.
// Checked on the simulator's pure sensor with an orbit-synchronous +-15 degC swing and a known
// k_T (truth the filter never sees): the ok snapshots are within their sigmas of the bias at T0,
// and the same filter without the correction is measurably worse.
#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
#include "service/daemon/ownership/spacecraft_tracker.hpp"

using namespace magcal;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

const Eigen::Vector3d kTemperatureCoefficient_nT_per_C(1.5, -1.0, 2.0);
constexpr double kReferenceTemperature_C = 20.0;  // the cycle's mean: the window's mean too

Scenario thermal_scenario(uint64_t seed) {
  Scenario sc = *scenario_preset("pure");
  sc.seed = seed;
  sc.duration_s = 12.0 * 3600.0;
  sc.sensor.temperature_mean_C = kReferenceTemperature_C;
  sc.sensor.reference_temperature_C = kReferenceTemperature_C;
  sc.sensor.temperature_amplitude_C = 15.0;  // +-22.5 .. 30 nT of bias swing
  sc.sensor.temperature_coefficient_nT_per_C = kTemperatureCoefficient_nT_per_C;
  return sc;
}

// The accepted refit the tracker is anchored on: the truth moved by about one of its sigmas
// (a real refit is that far off), with its temperature model.
CalibrationResult anchor_refit(const Scenario& sc, bool with_temperature_model) {
  CalibrationResult r;
  r.method = "twostep";
  Vector9d p;
  const SensorModelParameters& s = sc.sensor;
  p << s.bias_nT, s.D(0, 0), s.D(1, 1), s.D(2, 2), s.D(0, 1), s.D(0, 2), s.D(1, 2);
  Vector9d sigma;
  sigma << 1.0, 1.0, 1.0, 2e-5, 2e-5, 2e-5, 2e-5, 2e-5, 2e-5;
  Vector9d offset;
  offset << 0.8, -1.0, 0.6, 1.0, -0.5, 0.7, -1.0, 0.4, 0.9;
  r.parameters = CalibrationParameters::from_packed(p + sigma.cwiseProduct(offset));
  r.covariance = sigma.cwiseAbs2().asDiagonal();
  r.residual_rms_nT = s.noise_sigma_nT;
  r.status = CalibrationStatus::kOk;
  r.accepted = true;
  if (with_temperature_model) {
    r.has_temperature_model = true;
    r.reference_temperature_C = kReferenceTemperature_C;
    const Eigen::Vector3d k_sigma(0.01, 0.01, 0.01);
    r.temperature_coefficient_nT_per_C =
        kTemperatureCoefficient_nT_per_C + k_sigma.cwiseProduct(Eigen::Vector3d(1.0, -0.7, 0.5));
    r.temperature_coefficient_covariance = k_sigma.cwiseAbs2().asDiagonal();
  }
  return r;
}

struct Outcome {
  int ok = 0;
  double worst_z = 0.0;         // largest |error| / sigma of an ok snapshot
  double sum_error2_nT2 = 0.0;  // over every snapshot after the first hour
  int n_error = 0;
  int n_used = 0;  // samples the filter used
  CalibrationResult last;
  double rms_error_nT() const { return std::sqrt(sum_error2_nT2 / std::max(n_error, 1)); }
};

// Which samples carry a temperature (the others have NaN).
enum class TemperatureChannel {
  kEverySample,
  kEverySixth,          // housekeeping at 60 s, the magnetometer at 10 s: the hold covers it
  kEveryFourthMissing,  // random-looking dropouts: the hold covers them
  kLongGaps,            // 20 min without a temperature every 100 min: those samples unused
};

bool has_temperature(TemperatureChannel channel, int k) {
  switch (channel) {
    case TemperatureChannel::kEverySample:
      return true;
    case TemperatureChannel::kEverySixth:
      return k % 6 == 0;
    case TemperatureChannel::kEveryFourthMissing:
      return k % 4 != 0;
    case TemperatureChannel::kLongGaps:
      return k % 600 >= 120;
  }
  return true;
}

// Runs the tracker anchored on `refit` over the stream.
Outcome run(const Scenario& sc, const CalibrationResult& refit,
            TemperatureChannel channel = TemperatureChannel::kEverySample) {
  SpacecraftTracker t{std::make_shared<const MagnetometerUkf::Options>()};
  t.ukf.reanchor(refit.parameters.packed(), refit.covariance, refit.model_error_covariance());
  t.ukf.seed_noise(refit.residual_rms_nT);
  t.temperature.take_from(refit, 1);
  const Eigen::Vector3d bias_at_T0 = sc.sensor.bias_nT;
  Simulator sim(sc);
  SimulatedSample s;
  Outcome o;
  int k = 0;
  while (sim.next(&s)) {
    CalibrationSample c = s.calibration_sample();
    c.temperature_C = has_temperature(channel, k) ? s.temperature_C : kNaN;
    o.n_used += t.update_filter(c) ? 1 : 0;
    if (++k % 90 != 0) continue;  // every 15 min, as the daemon's snapshots
    CalibrationResult r = t.ukf.snapshot_and_reset_period();
    GateVerdict v = evaluate_gates(r, GateInputs{}, GateOptions{});
    reject_unless_ok(r, v);
    t.temperature.describe(r);
    const Eigen::Vector3d error = r.parameters.bias_nT - bias_at_T0;
    if (k > 360) {
      o.sum_error2_nT2 += error.squaredNorm() / 3.0;
      ++o.n_error;
    }
    if (r.status == CalibrationStatus::kOk) {
      ++o.ok;
      o.worst_z = std::max(o.worst_z, error.cwiseQuotient(r.bias_sigma_nT()).cwiseAbs().maxCoeff());
    }
    o.last = r;
  }
  return o;
}

}  // namespace

TEST_CASE("the correction takes the refit's model, holds a recent temperature, else skips") {
  const Scenario sc = thermal_scenario(1);
  TemperatureCorrection c;
  const CalibrationResult refit = anchor_refit(sc, true);
  c.take_from(refit, 42);
  REQUIRE(c.active);
  CHECK(c.refit_id == 42);
  CalibrationSample s;
  s.utime = sc.epoch_utime;
  s.b_sensor_nT = Eigen::Vector3d(20000.0, -3000.0, 5000.0);
  const Eigen::Matrix3d I_plus_D = Eigen::Matrix3d::Identity() + refit.parameters.D;
  Eigen::Vector3d b;
  // B' = B - (I + D)^-1 k_T (T - T0): (I + D) (B - B') = k_T (T - T0)
  s.temperature_C = 30.0;
  REQUIRE(c.correct(s, b));
  CHECK((I_plus_D * (s.b_sensor_nT - b) - refit.temperature_coefficient_nT_per_C * 10.0).norm() <
        1e-9);
  s.temperature_C = kReferenceTemperature_C;
  REQUIRE(c.correct(s, b));
  CHECK(b == s.b_sensor_nT);

  // Without a temperature: the last one within a minute (either side in time), else unused.
  s.temperature_C = 30.0;
  REQUIRE(c.correct(s, b));
  const Eigen::Vector3d at_30 = b;
  s.temperature_C = kNaN;
  s.utime += TemperatureCorrection::kTemperatureHoldMax_utime;
  REQUIRE(c.correct(s, b));
  CHECK(b == at_30);
  s.utime -= 2 * TemperatureCorrection::kTemperatureHoldMax_utime;  // a recorder dump
  REQUIRE(c.correct(s, b));
  CHECK(b == at_30);
  s.utime += 3 * TemperatureCorrection::kTemperatureHoldMax_utime;
  CHECK_FALSE(c.correct(s, b));
  CHECK(c.n_unused_no_temperature == 1);

  CalibrationResult snapshot;
  snapshot.method = "ukf";
  c.describe(snapshot);
  CHECK(snapshot.has_temperature_model);
  CHECK(snapshot.reference_temperature_C == kReferenceTemperature_C);
  CHECK(snapshot.temperature_coefficient_nT_per_C == refit.temperature_coefficient_nT_per_C);
  CHECK(snapshot.temperature_coefficient_covariance == refit.temperature_coefficient_covariance);

  // A later refit without a model (or with a broken one) ends the correction: every sample is
  // used as it is.
  c.take_from(anchor_refit(sc, false), 43);
  CHECK_FALSE(c.active);
  CHECK(c.refit_id == 0);
  CHECK(c.correct(s, b));
  CHECK(b == s.b_sensor_nT);
  s.temperature_C = 30.0;
  CHECK(c.correct(s, b));
  CHECK(b == s.b_sensor_nT);
  CalibrationResult broken = refit;
  broken.reference_temperature_C = kNaN;
  c.take_from(broken, 44);
  CHECK_FALSE(c.active);
  CalibrationResult plain;
  c.describe(plain);
  CHECK_FALSE(plain.has_temperature_model);
}

TEST_CASE("anchored on a refit's temperature model, the UKF bias at T0 is within its sigmas") {
  for (const uint64_t seed : {1u, 2u, 3u}) {
    DYNAMIC_SECTION("seed " << seed) {
      const Scenario sc = thermal_scenario(seed);
      const Outcome corrected = run(sc, anchor_refit(sc, true));
      const Outcome uncorrected = run(sc, anchor_refit(sc, false));
      const auto describe = [](const char* name, const Outcome& o) {
        std::ostringstream out;
        out << name << ": " << o.ok << " ok, worst " << o.worst_z << " sigma, rms error "
            << o.rms_error_nT() << " nT, " << o.n_used << " samples used";
        return out.str();
      };
      INFO(describe("corrected", corrected) << "; " << describe("uncorrected", uncorrected));
      CHECK(corrected.ok > 0);
      CHECK(corrected.worst_z < 3.0);
      CHECK(corrected.last.has_temperature_model);
      CHECK(uncorrected.rms_error_nT() > 5.0 * corrected.rms_error_nT());
      CHECK(uncorrected.worst_z > 5.0);
      for (const auto& [name, channel] :
           {std::pair{"every 6th", TemperatureChannel::kEverySixth},
            std::pair{"every 4th missing", TemperatureChannel::kEveryFourthMissing},
            std::pair{"long gaps", TemperatureChannel::kLongGaps}}) {
        const Outcome partial = run(sc, anchor_refit(sc, true), channel);
        INFO(describe(name, partial));
        CHECK(partial.ok > 0);
        CHECK(partial.worst_z < 3.0);
        if (channel == TemperatureChannel::kLongGaps) {
          CHECK(partial.n_used < corrected.n_used * 9 / 10);  // a fifth has no temperature
        } else {
          CHECK(partial.n_used >= corrected.n_used - 1);  // all but a first one without any
        }
      }
    }
  }
}
