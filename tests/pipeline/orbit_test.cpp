#include "pipeline/orbit.hpp"

#include <catch2/catch.hpp>

#include <cmath>

#include <Eigen/Geometry>

#include "pipeline/frames.hpp"

using namespace magcal;

namespace {
constexpr double kDeg = 3.141592653589793 / 180.0;
constexpr int64_t kEpoch = 1577836800LL * 1'000'000;  // 2020-01-01

KeplerianElements elements(double alt_km, double e, double inc_deg) {
  KeplerianElements el;
  el.semi_major_axis_m = kEarthEquatorialRadius_m + alt_km * 1e3;
  el.eccentricity = e;
  el.inclination_rad = inc_deg * kDeg;
  el.raan_rad = 30.0 * kDeg;
  el.arg_perigee_rad = 40.0 * kDeg;
  el.mean_anomaly_rad = 10.0 * kDeg;
  el.epoch_utime = kEpoch;
  return el;
}
int64_t at(double t_s) {
  return kEpoch + static_cast<int64_t>(std::llround(t_s * 1e6));
}
double energy(const OrbitState& s) {
  return 0.5 * s.v_m_s.squaredNorm() - kEarthMu_m3_s2 / s.r_m.norm();
}
// Right ascension of the ascending node from the angular momentum h = r x v.
double node_rad(const OrbitState& s) {
  const Eigen::Vector3d h = s.r_m.cross(s.v_m_s);
  return std::atan2(h.x(), -h.y());
}
}  // namespace

TEST_CASE("two-body circular orbit: radius, speed and period") {
  const KeplerianElements el = elements(550.0, 0.0, 97.6);
  const Orbit orbit(el, {});
  const double a = el.semi_major_axis_m;
  REQUIRE(orbit.period_s() ==
          Approx(2.0 * M_PI * std::sqrt(a * a * a / kEarthMu_m3_s2)).epsilon(1e-14));
  REQUIRE(orbit.period_s() == Approx(5739.0).margin(5.0));  // ~95.7 min at 550 km
  const OrbitState s0 = orbit.state_eci(kEpoch);
  constexpr double kPosTol_m = 1e-6 * 7e6;
  for (double t : {0.0, 1000.0, 2345.6, 5000.0}) {
    const OrbitState s = orbit.state_eci(at(t));
    CHECK(s.r_m.norm() == Approx(a).epsilon(1e-12));
    CHECK(s.v_m_s.norm() == Approx(std::sqrt(kEarthMu_m3_s2 / a)).epsilon(1e-12));
    CHECK(std::abs(s.r_m.dot(s.v_m_s)) < 1e-6 * a * s.v_m_s.norm());
  }
  const OrbitState s1 = orbit.state_eci(at(orbit.period_s()));
  CHECK((s1.r_m - s0.r_m).norm() < kPosTol_m);
}

TEST_CASE("two-body eccentric orbit conserves energy and angular momentum, closes after a period") {
  const KeplerianElements el = elements(800.0, 0.2, 63.4);
  const Orbit orbit(el, {});
  const OrbitState s0 = orbit.state_eci(kEpoch);
  const double e0 = energy(s0);
  const Eigen::Vector3d h0 = s0.r_m.cross(s0.v_m_s);
  CHECK(e0 == Approx(-kEarthMu_m3_s2 / (2.0 * el.semi_major_axis_m)).epsilon(1e-12));
  for (int k = 1; k <= 50; ++k) {
    const OrbitState s = orbit.state_eci(at(k * 137.0));
    CHECK(energy(s) == Approx(e0).epsilon(1e-11));
    CHECK((s.r_m.cross(s.v_m_s) - h0).norm() < 1e-11 * h0.norm());
  }
  const OrbitState s1 = orbit.state_eci(at(orbit.period_s()));
  CHECK((s1.r_m - s0.r_m).norm() < 1e-2);  // metres after one period (microsecond time grid)
  // Perigee and apogee radii are a(1 -/+ e).
  double rmin = 1e30, rmax = 0.0;
  for (int k = 0; k < 10000; ++k) {
    const double r = orbit.state_eci(at(k * orbit.period_s() / 10000.0)).r_m.norm();
    rmin = std::min(rmin, r);
    rmax = std::max(rmax, r);
  }
  CHECK(rmin == Approx(el.semi_major_axis_m * 0.8).epsilon(1e-6));
  CHECK(rmax == Approx(el.semi_major_axis_m * 1.2).epsilon(1e-6));
}

TEST_CASE("velocity is the time derivative of position (finite differences)") {
  for (J2Model j2 : {J2Model::none, J2Model::secular}) {
    Orbit::Options opt;
    opt.j2 = j2;
    const Orbit orbit(elements(700.0, 0.05, 51.6), opt);
    constexpr double kStep_s = 0.5;
    for (double t : {100.0, 3000.0, 86400.0}) {
      const Eigen::Vector3d fd =
          (orbit.state_eci(at(t + kStep_s)).r_m - orbit.state_eci(at(t - kStep_s)).r_m) /
          (2.0 * kStep_s);
      const Eigen::Vector3d v = orbit.state_eci(at(t)).v_m_s;
      CHECK((fd - v).norm() < 1e-3);  // m/s; central-difference error ~ v (n dt)^2 / 6
    }
  }
}

TEST_CASE("J2 secular: sun-synchronous nodal regression at 550 km / 97.6 deg") {
  Orbit::Options opt;
  opt.j2 = J2Model::secular;
  const Orbit orbit(elements(550.0, 0.0, 97.6), opt);
  const double deg_per_day = orbit.raan_rate_rad_s() / kDeg * 86400.0;
  CHECK(deg_per_day == Approx(0.9856).margin(0.01));  // 360 deg / 365.2422 days
  // Measured from the propagated states, not the rate formula: node after 10 days.
  const double n0 = node_rad(orbit.state_eci(kEpoch));
  const double n10 = node_rad(orbit.state_eci(at(10.0 * 86400.0)));
  CHECK(std::remainder(n10 - n0, 2.0 * M_PI) / kDeg == Approx(9.856).margin(0.1));
  // Two-body keeps the node fixed.
  const Orbit kepler(elements(550.0, 0.0, 97.6), {});
  CHECK(std::abs(std::remainder(
            node_rad(kepler.state_eci(at(864000.0))) - node_rad(kepler.state_eci(kEpoch)),
            2.0 * M_PI)) < 1e-12);
  // Critical inclination: perigee frozen.
  const Orbit critical(elements(550.0, 0.01, 63.4349), opt);
  CHECK(std::abs(critical.arg_perigee_rate_rad_s()) < 1e-3 * std::abs(orbit.raan_rate_rad_s()));
}

TEST_CASE("Kepler's equation is solved for high eccentricity") {
  for (double e : {0.0, 0.3, 0.9, 0.99}) {
    for (double M = -3.1; M < 3.2; M += 0.37) {
      const double E = eccentric_anomaly(M, e);
      CHECK(std::abs(std::remainder(E - e * std::sin(E) - M, 2.0 * M_PI)) < 1e-12);
    }
  }
}

TEST_CASE("ECEF state: rotation preserves radius, velocity matches finite differences") {
  const Orbit orbit(elements(550.0, 0.0, 97.6), {});
  auto ecef = [&](double t) {
    return Orbit::ecef_from_eci(orbit.state_eci(at(t)), gcrs_from_itrf(at(t)));
  };
  const OrbitState s = ecef(1000.0);
  CHECK(s.r_m.norm() == Approx(orbit.state_eci(at(1000.0)).r_m.norm()).epsilon(1e-14));
  const Eigen::Vector3d fd = (ecef(1000.5).r_m - ecef(999.5).r_m) / 1.0;
  CHECK((fd - s.v_m_s).norm() < 2e-2);  // m/s
}

TEST_CASE("orbit elements are validated") {
  Orbit::Options opt;
  KeplerianElements el = elements(550.0, 0.0, 97.6);
  CHECK(opt.validate(el).empty());
  el.eccentricity = 1.0;
  CHECK(opt.validate(el).find("eccentricity") != std::string::npos);
  el = elements(550.0, 0.0, 97.6);
  el.semi_major_axis_m = 6000e3;
  CHECK(opt.validate(el).find("perigee") != std::string::npos);
  el = elements(550.0, 0.0, 97.6);
  el.inclination_rad = NAN;
  CHECK(opt.validate(el).find("inclination") != std::string::npos);
  el = elements(550.0, 0.5, 97.6);
  CHECK(opt.validate(el).find("perigee") != std::string::npos);
}
