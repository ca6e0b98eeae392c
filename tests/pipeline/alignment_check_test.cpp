// The alignment stage's check of itself (pipeline/alignment_check.hpp) and the attitude lag
// (pipeline/attitude_lag.hpp). Truth from the simulator: the attitude a sample reports is the
// profile's at t + lead (attitude time tags ahead of the magnetometer's), the reference field
// the inertial one at t; axis mix-ups applied to the measured vector.
#include "pipeline/alignment_check.hpp"

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <catch2/catch.hpp>

#include "pipeline/attitude_lag.hpp"
#include "pipeline/batch_calibration.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"

using namespace magcal;

namespace {

struct LagCase {
  double lead_s = 1.0;  // attitude ahead of the magnetometer
  double rate_deg_s = 1.5;
  Eigen::Vector3d rate_axis = Eigen::Vector3d(2.0, -1.0, 3.0);
  double noise_nT = 3.0;
  double duration_h = 12.0;
  Eigen::Vector3d installation_deg = Eigen::Vector3d(0.5, -0.8, 1.2);
  uint64_t seed = 1;
};

struct LagRun {
  CalibrationResult result;
  Eigen::Matrix3d R_true;
};

// The tumbling preset at the case's rate and noise, with the reported attitude lead_s early.
LagRun run_lag_case(const LagCase& c, bool estimate_lag) {
  Scenario sc = *scenario_preset("tumbling");
  sc.duration_s = c.duration_h * 3600.0;
  sc.seed = c.seed;
  sc.sensor.noise_sigma_nT = c.noise_nT;
  sc.sensor.installation_deg = c.installation_deg;
  sc.attitude.omega0_body_rad_s = c.rate_axis.normalized() * c.rate_deg_s * M_PI / 180.0;
  Simulator sim(sc);
  // A profile started lead_s earlier reads, at t, the attitude of t + lead_s.
  AttitudeProfile ahead(sc.attitude, sc.epoch_utime - static_cast<int64_t>(c.lead_s * 1e6));
  SampleSet samples;
  SimulatedSample s;
  while (sim.next(&s)) {
    CalibrationSample cs = s.calibration_sample();
    cs.h_body_nT = dcm_from_quaternion(ahead.q_body_from_eci(s.utime, {})) * s.h_eci_nT;
    samples.push_back(cs);
  }
  BatchCalibrationOptions o;
  o.sigma_nT = c.noise_nT;
  o.estimate_attitude_lag = estimate_lag;
  o.gate_options.expected_residual_nT = std::max(o.gate_options.expected_residual_nT, c.noise_nT);
  return {calibrate_batch(samples, o), sim.truth().R_sensor_from_body};
}

// Squared Mahalanobis distance of the estimate from the truth (sensor-frame small rotation).
double rotation_error_chi2(const AlignmentEstimate& a, const Eigen::Matrix3d& R_true) {
  const Eigen::AngleAxisd aa(Eigen::Matrix3d(R_true * a.R_sensor_from_body.transpose()));
  const Eigen::Vector3d d = -aa.angle() * aa.axis();
  return d.dot(a.angle_covariance_rad2.ldlt().solve(d));
}

bool alignment_accepted(const CalibrationResult& r) {
  return r.accepted && r.has_alignment && r.alignment.inconsistency.empty();
}

LagCase random_case(std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> n(0.0, 1.0);
  LagCase c;
  c.lead_s = (0.2 + 1.8 * u(rng)) * (u(rng) < 0.5 ? -1.0 : 1.0);
  c.rate_deg_s = 0.7 + 2.3 * u(rng);
  c.rate_axis = Eigen::Vector3d(n(rng), n(rng), n(rng));
  c.noise_nT = std::exp(std::log(1.0) + u(rng) * std::log(30.0));
  c.duration_h = 3.0 + 9.0 * u(rng);
  c.installation_deg = 2.0 * Eigen::Vector3d(n(rng), n(rng), n(rng));
  c.seed = rng();
  return c;
}

struct LagCounts {
  int cases = 0, accepted_without_lag = 0, lag_within = 0, estimated_accepted = 0;
};

// One lag case, without and with the lag estimated: never accepted with the rotation outside 3
// sigma, and with the lag estimated, the lag within 3 sigma.
void check_lag_case(const LagCase& c, LagCounts* counts) {
  const LagRun plain = run_lag_case(c, false);
  const LagRun fitted = run_lag_case(c, true);
  const AlignmentEstimate& a = fitted.result.alignment;
  const double lag_z = (a.attitude_lag_s + c.lead_s) / a.attitude_lag_sigma_s;
  std::printf(
      "draw %d: lead %.2f s rate %.2f deg/s noise %.1f nT %.1f h | plain %s chi2 %.1f | lag "
      "%.3f +- %.3f (z %.2f) %s chi2 %.1f %s\n",
      counts->cases++, c.lead_s, c.rate_deg_s, c.noise_nT, c.duration_h,
      alignment_accepted(plain.result) ? "accepted" : "refused",
      rotation_error_chi2(plain.result.alignment, plain.R_true), a.attitude_lag_s,
      a.attitude_lag_sigma_s, lag_z, alignment_accepted(fitted.result) ? "accepted" : "refused",
      rotation_error_chi2(a, fitted.R_true),
      fitted.result.rejection_reasons.empty() ? ""
                                              : fitted.result.rejection_reasons.front().c_str());
  INFO(plain.result.alignment.inconsistency);
  INFO(a.inconsistency);
  // 3 sigma of a 3-dof rotation: chi-square 3 dof at the 3-sigma tail probability.
  if (alignment_accepted(plain.result)) {
    ++counts->accepted_without_lag;
    CHECK(rotation_error_chi2(plain.result.alignment, plain.R_true) < 14.16);
  }
  REQUIRE(a.attitude_lag_applied);
  CHECK(std::abs(lag_z) < 3.0);
  counts->lag_within += std::abs(lag_z) < 3.0;
  if (alignment_accepted(fitted.result)) {
    ++counts->estimated_accepted;
    CHECK(rotation_error_chi2(a, fitted.R_true) < 14.16);
  }
}

void lag_monte_carlo(int draws, uint64_t seed) {
  std::mt19937_64 rng(seed);
  LagCounts counts;
  for (int i = 0; i < draws; ++i) check_lag_case(random_case(rng), &counts);
  std::printf("%d draws: accepted without the lag %d, lag within 3 sigma %d, accepted with it %d\n",
              draws, counts.accepted_without_lag, counts.lag_within, counts.estimated_accepted);
}

}  // namespace

TEST_CASE("an attitude 1 s ahead on a 1.5 deg/s tumble is refused, naming the lag",
          "[alignment_check]") {
  const LagRun plain = run_lag_case({}, false);
  REQUIRE(plain.result.has_alignment);
  INFO(plain.result.alignment.inconsistency);
  CHECK_FALSE(plain.result.accepted);
  CHECK(plain.result.alignment.inconsistency.find("the attitude looks") != std::string::npos);
  CHECK(plain.result.alignment.inconsistency.find("ahead of the magnetometer") !=
        std::string::npos);

  const LagRun fitted = run_lag_case({}, true);
  const AlignmentEstimate& a = fitted.result.alignment;
  INFO(a.inconsistency);
  CHECK(a.attitude_lag_applied);
  CHECK(std::abs(a.attitude_lag_s + 1.0) < 3.0 * a.attitude_lag_sigma_s);
  // The stated sigma bounds the h-only model's bias (the rotation shares part of the lag's
  // signature on this tumble, which widens it): precise, and still a bound.
  CHECK(a.attitude_lag_sigma_s < 0.15);
  CHECK(fitted.result.accepted);
  CHECK(rotation_error_chi2(a, fitted.R_true) < 14.16);
}

TEST_CASE("without a lag the tumbling and paper alignments stay accepted", "[alignment_check]") {
  for (const char* name : {"paper", "tumbling", "pure"}) {
    Scenario sc = *scenario_preset(name);
    Simulator sim(sc);
    SampleSet samples;
    for (const SimulatedSample& s : sim.run()) samples.push_back(s.calibration_sample());
    const CalibrationResult r = calibrate_batch(samples, {});
    INFO(name << ": " << r.alignment.inconsistency);
    CHECK(r.has_alignment);
    CHECK(r.alignment.inconsistency.empty());
    CHECK(std::abs(r.alignment.attitude_lag_s) < 3.0 * r.alignment.attitude_lag_sigma_s);
  }
}

TEST_CASE("a negated or swapped sensor axis is named in the refusal", "[alignment_check]") {
  Scenario sc = *scenario_preset("tumbling");
  sc.duration_s = 6.0 * 3600.0;
  Simulator sim(sc);
  const std::vector<SimulatedSample> run = sim.run();
  struct Mixup {
    Eigen::Matrix3d P;  // reported = P_reported_from_true sensor axes
    const char* named;
  };
  Eigen::Matrix3d negate_y = Eigen::Vector3d(1, -1, 1).asDiagonal();
  Eigen::Matrix3d swap_xy;
  swap_xy << 0, 1, 0, 1, 0, 0, 0, 0, 1;
  for (const Mixup& m : {Mixup{negate_y, "the sensor's y axis looks negated"},
                         Mixup{swap_xy,
                               "the sensor's axes look swapped: x, y, z are the "
                               "reported y, x, z"}}) {
    SampleSet samples;
    for (const SimulatedSample& s : run) {
      CalibrationSample c = s.calibration_sample();
      c.b_sensor_nT = m.P * c.b_sensor_nT;
      samples.push_back(c);
    }
    const CalibrationResult r = calibrate_batch(samples, {});
    INFO(r.alignment.inconsistency);
    CHECK_FALSE(r.accepted);
    CHECK(r.alignment.inconsistency.find(m.named) != std::string::npos);
  }
}

// Spins nearly about a body axis (tumbling preset's minor z and major y axes, both stable): a lag
// looks almost exactly like a rotation about it, and only the inertial field's motion, which the
// h-only model gets wrong, tells them apart. A 1.87 s lead at 2.5 deg/s came out -0.90 +- 0.09
// s and was accepted 10 sigma off; a 1.97 s lead at 2.1 deg/s went undetected without the lag
// estimate, the rotation accepted 4 deg off.
TEST_CASE("lags on spins about a body axis: sigmas cover the lag and the rotation",
          "[alignment_check]") {
  LagCase about_z;
  about_z.lead_s = 1.8652426885979554;
  about_z.rate_deg_s = 2.4990469958987465;
  about_z.rate_axis =
      Eigen::Vector3d(-0.17321939288380583, -0.042166208399352818, 2.8676637948733408);
  about_z.noise_nT = 2.1613518163970089;
  about_z.duration_h = 3.2595369652108523;
  about_z.installation_deg =
      Eigen::Vector3d(5.0807113951936556, 1.1929644738451981, -2.5776177384269245);
  about_z.seed = 4250690405642391127ull;
  LagCase about_y;
  about_y.lead_s = -1.9720751803883581;
  about_y.rate_deg_s = 2.127097126144184;
  about_y.rate_axis =
      Eigen::Vector3d(0.0044606433522825645, 0.61640853085357683, 0.018280313213283876);
  about_y.noise_nT = 3.4563998874748201;
  about_y.duration_h = 10.19025559740583;
  about_y.installation_deg =
      Eigen::Vector3d(-0.33882227815953658, -0.50473270541582393, 1.7148359905866986);
  about_y.seed = 7651382403188225828ull;
  LagCounts counts;
  check_lag_case(about_z, &counts);
  check_lag_case(about_y, &counts);
  // Without the lag the first is refused, the second accepted (its covariance widened).
  CHECK(counts.accepted_without_lag == 1);
}

TEST_CASE("attitude lag Monte-Carlo: lag, noise, coverage and rotation drawn",
          "[alignment_check]") {
  lag_monte_carlo(6, 20261205);
}

TEST_CASE("attitude lag Monte-Carlo, long run", "[.][alignment_check_long]") {
  const char* draws = std::getenv("MAGCAL_LAG_DRAWS");
  lag_monte_carlo(draws ? std::atoi(draws) : 100, 7);
}
