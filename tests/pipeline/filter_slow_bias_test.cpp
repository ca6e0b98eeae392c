// The online filters on a slowly varying bias (issue 20 item 3): the simulator's paper sensor with
// an orbit-synchronous thermal swing (temperature-driven bias, no temperature channel in the
// filters) plus a linear drift. An `ok` snapshot must be within its sigmas of the TRUE CURRENT
// bias b(t, T) = b0 + k_T (T - T0) + k_drift t (sensor_model.hpp), not of b0 or the window mean.
#include <algorithm>
#include <cmath>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/sensor_model.hpp"
#include "pipeline/simulator.hpp"

using namespace magcal;

namespace {

struct TruthSample {
  CalibrationSample sample;
  Eigen::Vector3d bias_nT;  // b(t, T) at this sample
};

std::vector<TruthSample> simulate_slow_bias(uint64_t seed, double hours) {
  Scenario sc = *scenario_preset("paper");
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  sc.sensor.temperature_amplitude_C = 10.0;
  sc.sensor.temperature_coefficient_nT_per_C = Eigen::Vector3d(1.0, 1.0, 1.0);  // +-10 nT
  sc.sensor.drift_nT_per_day = Eigen::Vector3d(36.0, -36.0, 36.0);              // 1.5 nT/h
  Simulator sim(sc);
  SensorModelParameters p = sc.sensor;
  p.temperature_period_s = sim.truth().temperature_period_s;
  const SensorModel truth(p);
  std::vector<TruthSample> out;
  SimulatedSample s;
  while (sim.next(&s)) {
    const double t_s = static_cast<double>(s.utime - sc.epoch_utime) * 1e-6;
    out.push_back({s.calibration_sample(), truth.bias_nT(t_s, s.temperature_C)});
  }
  return out;
}

struct Outcome {
  int snapshots = 0, ok = 0, accepted = 0, beyond_3_sigma = 0;
  Eigen::Vector3d sum_z2 = Eigen::Vector3d::Zero();
  double worst = 0.0;
  double first_ok_h = -1.0;
  Eigen::Vector3d rms() const { return (sum_z2 / std::max(ok, 1)).cwiseSqrt(); }
};

template <class Filter>
void replay(Filter& f, const std::vector<TruthSample>& data, Outcome& o) {
  for (size_t k = 0; k < data.size(); ++k) {
    const CalibrationSample& c = data[k].sample;
    f.update(c.b_sensor_nT, c.h_body_nT.norm(), c.utime);
    if ((k + 1) % 90 != 0) continue;  // every 15 min, as the daemon
    CalibrationResult r = f.snapshot_and_reset_period();
    ++o.snapshots;
    GateVerdict v = evaluate_gates(r, GateInputs{}, GateOptions{});
    reject_unless_ok(r, v);
    if (r.status != CalibrationStatus::kOk) continue;
    const Eigen::Vector3d z =
        (r.parameters.bias_nT - data[k].bias_nT).cwiseQuotient(r.bias_sigma_nT());
    ++o.ok;
    o.accepted += v.accepted;
    o.sum_z2 += z.cwiseAbs2();
    const double worst = z.cwiseAbs().maxCoeff();
    o.beyond_3_sigma += worst > 3.0;
    o.worst = std::max(o.worst, worst);
    if (o.first_ok_h < 0) o.first_ok_h = (c.utime - data.front().sample.utime) * 1e-6 / 3600.0;
  }
}

}  // namespace

// Hidden ([.]): fails on the current filters (figures in the branch's report); run it with
// `filter_slow_bias_test "[slow_bias]"`. Bar: per-axis RMS of (estimate - current bias) / sigma
// over all ok snapshots below 1.5, and at most 1 in 50 ok snapshots beyond 3 sigma on some axis.
TEST_CASE("Slowly varying bias: ok snapshots are within their sigmas of the current bias",
          "[.][slow_bias]") {
  Outcome ekf, ukf;
  for (uint64_t seed : {1, 2, 3, 4}) {
    const auto data = simulate_slow_bias(seed, 24.0);
    MagnetometerEkf e;
    MagnetometerUkf u;
    replay(e, data, ekf);
    replay(u, data, ukf);
  }
  for (const auto& [name, o] : {std::pair{"EKF", ekf}, std::pair{"UKF", ukf}}) {
    WARN(name << ": " << o.snapshots << " snapshots, " << o.ok << " ok, " << o.accepted
              << " accepted, " << o.beyond_3_sigma << " beyond 3 sigma, worst " << o.worst
              << ", RMS(err/sigma) " << o.rms().transpose() << ", first ok " << o.first_ok_h
              << " h");
    // No `ok` at all is honest here (not_converged: the orbit-normal bias cannot be followed).
    CHECK(o.beyond_3_sigma <= o.ok / 50);
    CHECK((o.rms().array() < 1.5).all());
  }
}
