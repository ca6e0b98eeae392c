#include "pipeline/simulator.hpp"

#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>

#include "pipeline/scalar_measurement.hpp"

using namespace magcal;

namespace {
constexpr double kDeg = 3.141592653589793 / 180.0;

double angle_between(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

Scenario short_run(const char* preset, double hours) {
  Scenario s = *scenario_preset(preset);
  s.duration_s = hours * 3600.0;
  return s;
}
}  // namespace

TEST_CASE("presets are valid and match the paper's table") {
  for (const auto& name : scenario_preset_names()) {
    INFO(name);
    CHECK(scenario_preset(name)->validate().empty());
  }
  CHECK_FALSE(scenario_preset("nope").has_value());
  const Scenario p = *scenario_preset("paper");
  CHECK(p.sample_count() == 4320);  // 12 h at 10 s
  CHECK(p.sensor.bias_nT == Eigen::Vector3d(1000.0, 800.0, 900.0));
  CHECK(p.sensor.D(1, 1) == 0.02);
  CHECK(p.sensor.lsb_nT() == 2e5 / 65536.0);
  CHECK(p.orbit.inclination_rad == Approx(97.6 * kDeg));
  CHECK(p.attitude.mode == AttitudeMode::nadir);
  const Scenario pure = *scenario_preset("pure");
  CHECK(pure.sensor.nbits == 0);
  CHECK(pure.sensor.internal_misalignment_mrad.isZero());
  CHECK(pure.attitude.mode == AttitudeMode::tumbling);
}

TEST_CASE("paper scenario: |h| range and field rotation per orbit (body and ECI)") {
  Simulator sim(short_run("paper", 12.0));
  const double period_s = sim.orbit().period_s();
  const std::vector<SimulatedSample> s = sim.run();
  REQUIRE(s.size() == 4320);
  double hmin = 1e9, hmax = 0.0;
  for (const auto& x : s) {
    hmin = std::min(hmin, x.h_norm_nT);
    hmax = std::max(hmax, x.h_norm_nT);
    CHECK(x.h_body_nT.norm() == Approx(x.h_norm_nT).epsilon(1e-12));
  }
  WARN("paper 12 h: |h| in [" << hmin << ", " << hmax << "] nT");
  CHECK(hmin > 17000.0);
  CHECK(hmax < 52000.0);
  CHECK(hmax - hmin > 20000.0);  // pole-to-equator contrast of a polar orbit
  // Angle swept by the field direction over each full orbit (sum of consecutive angles).
  const auto per_orbit = static_cast<size_t>(std::floor(period_s / 10.0));
  const size_t orbits = s.size() / per_orbit;
  REQUIRE(orbits >= 7);
  double body_sum = 0.0, eci_sum = 0.0;
  for (size_t o = 0; o < orbits; ++o) {
    double body = 0.0, eci = 0.0;
    for (size_t k = o * per_orbit + 1; k <= (o + 1) * per_orbit && k < s.size(); ++k) {
      body += angle_between(s[k - 1].h_body_nT, s[k].h_body_nT);
      eci += angle_between(s[k - 1].h_eci_nT, s[k].h_eci_nT);
    }
    // Per orbit: ~360 deg in body (orbit) frame, ~720 deg inertially (dipole, polar orbit).
    CHECK(body / kDeg == Approx(360.0).margin(60.0));
    CHECK(eci / kDeg == Approx(720.0).margin(90.0));
    body_sum += body;
    eci_sum += eci;
  }
  WARN("per orbit: body " << body_sum / orbits / kDeg << " deg, ECI " << eci_sum / orbits / kDeg
                          << " deg");
}

TEST_CASE("same seed gives bit-identical samples, another seed differs") {
  auto bytes = [](uint64_t seed, const char* preset) {
    Scenario sc = short_run(preset, 1.0);
    sc.seed = seed;
    sc.attitude_noise_deg = 0.01;
    sc.gnss_noise_m = 5.0;
    Simulator sim(sc);
    std::vector<double> out;
    SimulatedSample x;
    while (sim.next(&x)) {
      for (int i = 0; i < 3; ++i) out.push_back(x.b_sensor_nT(i));
      for (int i = 0; i < 3; ++i) out.push_back(x.h_body_reported_nT(i));
      for (int i = 0; i < 4; ++i) out.push_back(x.q_body_from_eci_reported(i));
    }
    return out;
  };
  for (const char* preset : {"paper", "tumbling"}) {
    const auto a = bytes(5, preset), b = bytes(5, preset), c = bytes(6, preset);
    REQUIRE(a.size() == b.size());
    CHECK(std::memcmp(a.data(), b.data(), a.size() * sizeof(double)) == 0);
    CHECK(std::memcmp(a.data(), c.data(), a.size() * sizeof(double)) != 0);
  }
}

TEST_CASE("pure scenario follows the estimation model exactly") {
  // B = (I+D)^-1 (R h + b + eps): the residual (I+D) B - R h - b is the white noise.
  Scenario sc = short_run("pure", 6.0);
  Simulator sim(sc);
  const TruthParameters t = sim.truth();
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  Eigen::Vector3d sum = Eigen::Vector3d::Zero(), sum2 = Eigen::Vector3d::Zero();
  SimulatedSample x;
  int n = 0;
  while (sim.next(&x)) {
    const Eigen::Vector3d e =
        (I + t.D) * x.b_sensor_nT - t.R_sensor_from_body * x.h_body_nT - t.bias_nT;
    sum += e;
    sum2 += e.cwiseAbs2();
    ++n;
  }
  const Eigen::Vector3d sd = (sum2 / n - (sum / n).cwiseAbs2()).cwiseSqrt();
  CHECK((sd.array() - 3.0).abs().maxCoeff() < 5.0 * 3.0 / std::sqrt(2.0 * n));
  CHECK((sum / n).cwiseAbs().maxCoeff() < 5.0 * 3.0 / std::sqrt(n));

  // Noise off: the shared scalar measurement model holds to rounding.
  sc.sensor.noise_sigma_nT = 0.0;
  Simulator exact(sc);
  const Vector9d p = CalibrationParameters{t.bias_nT, t.D}.packed();
  for (int k = 0; k < 200 && exact.next(&x); ++k) {
    const double z = scalar_measurement(x.b_sensor_nT, x.h_norm_nT);
    CHECK(z == Approx(predicted_scalar_measurement(p, x.b_sensor_nT))
                   .margin(1e-6 * x.h_norm_nT * x.h_norm_nT));
  }
}

TEST_CASE("tumbling scenario observes every body axis in both directions") {
  Simulator sim(short_run("tumbling", 3.0));
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1.0), hi = Eigen::Vector3d::Constant(-1.0);
  SimulatedSample x;
  while (sim.next(&x)) {
    const Eigen::Vector3d u = x.h_body_nT.normalized();
    lo = lo.cwiseMin(u);
    hi = hi.cwiseMax(u);
  }
  CHECK(lo.maxCoeff() < -0.9);
  CHECK(hi.minCoeff() > 0.9);
}

TEST_CASE("truth parameters: stage 2 sees C_int R") {
  Simulator sim(short_run("paper", 0.1));
  const TruthParameters t = sim.truth();
  CHECK((t.R_sensor_from_body - t.internal_C * t.installation_R).norm() < 1e-15);
  const Eigen::Matrix3d from_angles = dcm_from_roll_pitch_yaw(
      {t.alignment_deg(0) * kDeg, t.alignment_deg(1) * kDeg, t.alignment_deg(2) * kDeg});
  CHECK((from_angles - t.R_sensor_from_body).norm() < 1e-12);
  // Small angles: the alignment is about installation + internal (5 mrad = 0.286 deg).
  CHECK((t.alignment_deg - Eigen::Vector3d(1.0, 2.0, 1.0)).cwiseAbs().maxCoeff() < 0.35);
  CHECK(rotation_angle(t.R_sensor_from_body * t.installation_R.transpose()) / kDeg ==
        Approx(std::sqrt(3.0) * 5e-3 / kDeg).epsilon(0.01));
  CHECK(t.lsb_nT == 2e5 / 65536.0);
  CHECK(t.noise_sigma_nT == 3.0);
}

TEST_CASE("knowledge noise perturbs the reported attitude and position, not the measurement") {
  Scenario quiet = short_run("paper", 2.0);
  Scenario noisy = quiet;
  noisy.attitude_noise_deg = 0.1;
  noisy.gnss_noise_m = 20.0;
  Simulator a(quiet), b(noisy);
  SimulatedSample xa, xb;
  double att2 = 0.0, pos2 = 0.0;
  int n = 0;
  while (a.next(&xa) && b.next(&xb)) {
    CHECK(xa.b_sensor_nT == xb.b_sensor_nT);  // separate random streams
    CHECK(xa.q_body_from_eci_reported == xa.q_body_from_eci);
    const double ang = rotation_angle(dcm_from_quaternion(xb.q_body_from_eci_reported) *
                                      dcm_from_quaternion(xb.q_body_from_eci).transpose());
    att2 += ang * ang;
    pos2 += (xb.r_ecef_reported_m - xb.r_ecef_m).squaredNorm();
    CHECK(xb.calibration_sample().h_body_nT == xb.h_body_reported_nT);
    ++n;
  }
  // rms rotation angle of 3 independent axes: sqrt(3) sigma; rms 3-D position error: sqrt(3) sigma.
  CHECK(std::sqrt(att2 / n) / kDeg == Approx(0.1 * std::sqrt(3.0)).epsilon(0.1));
  CHECK(std::sqrt(pos2 / n) == Approx(20.0 * std::sqrt(3.0)).epsilon(0.1));
}

TEST_CASE("scenario validation names the bad key") {
  Scenario s = *scenario_preset("paper");
  s.sample_period_s = 0.0;
  CHECK(s.validate().find("sample_period_s") != std::string::npos);
  s = *scenario_preset("paper");
  s.orbit.eccentricity = -0.1;
  CHECK(s.validate().find("orbit.eccentricity") != std::string::npos);
  s = *scenario_preset("paper");
  s.epoch_utime = -2208988800LL * 1'000'000 - 86400LL * 1'000'000 * 365;  // 1899
  CHECK(s.validate().find("epoch") != std::string::npos);
  s = *scenario_preset("paper");
  s.sensor.hysteresis_fraction_fs = NAN;
  CHECK(s.validate().find("sensor.hysteresis_fraction_fs") != std::string::npos);
  s = *scenario_preset("paper");
  s.gnss_noise_m = -1.0;
  CHECK(s.validate().find("knowledge.gnss_noise_m") != std::string::npos);
  s = *scenario_preset("paper");
  s.sat_id.clear();
  CHECK(s.validate().find("sat_id") != std::string::npos);
}
