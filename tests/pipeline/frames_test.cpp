// Earth frames against ERFA (IAU SOFA): Earth rotation angle (eraEra00), the full
// GCRS <- ITRF rotation without polar motion (eraC2t06a, IAU 2006/2000A, xp = yp = 0, the same
// UT1 and TT), the celestial-to-intermediate matrix (eraC2i06a) and WGS-84 geodetic
// conversions (eraGd2gc / eraGc2gd).
#include "pipeline/frames.hpp"

#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>

#include <erfa.h>
#include <erfam.h>
#include <catch2/catch.hpp>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

using namespace magcal;

namespace {
constexpr double kArcsec = std::numbers::pi / (180.0 * 3600.0);
constexpr double kTtMinusUtc_s = 69.184;  // what the model assumes by default
// Requirement (issue 2): <= 15 arcsec over 2000-2035 with UT1 = UTC. The truncated nutation
// series measures ~0.014 arcsec (printed below); the test guards it at 0.1 arcsec so a
// regression in the model shows up long before the requirement is at risk.
constexpr double kRequiredGcrsItrf_arcsec = 15.0;
constexpr double kModelGcrsItrf_arcsec = 0.1;
constexpr double kEraTolerance_rad = 1e-10;  // 20 uas: double rounding of ERA at ~1e4 turns
constexpr double kPositionTolerance_m = 1e-6;

Eigen::Matrix3d from_erfa(double r[3][3]) {
  Eigen::Matrix3d m;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) m(i, j) = r[i][j];
  return m;
}

// Two-part Julian date of a utime plus an offset in seconds (ERFA's preferred split).
void jd_split(int64_t utime, double offset_s, double* jd1, double* jd2) {
  const int64_t day_us = 86400LL * kMicrosPerSecond;
  const int64_t days = utime >= 0 ? utime / day_us : -((-utime + day_us - 1) / day_us);
  *jd1 = kJulianDateUnixEpoch + static_cast<double>(days);
  *jd2 = (static_cast<double>(utime - days * day_us) / kMicrosPerSecond + offset_s) / 86400.0;
}

std::vector<int64_t> epochs_2000_2035() {
  std::vector<int64_t> out;
  std::mt19937_64 rng(2035);
  const int64_t start = utime_from_calendar({2000, 1, 1, 0, 0, 0.0});
  const int64_t end = utime_from_calendar({2035, 12, 31, 0, 0, 0.0});
  std::uniform_int_distribution<int64_t> dist(start, end);
  for (int i = 0; i < 400; ++i) out.push_back(dist(rng));
  out.push_back(start);
  out.push_back(end);
  out.push_back(utime_from_calendar({2000, 1, 1, 12, 0, 0.0}));
  return out;
}
}  // namespace

TEST_CASE("Earth rotation angle equals eraEra00", "[frames]") {
  for (int64_t t : epochs_2000_2035()) {
    double u1 = 0.0, u2 = 0.0;
    jd_split(t, 0.0, &u1, &u2);
    const double diff =
        std::remainder(earth_rotation_angle_rad(t) - eraEra00(u1, u2), 2 * std::numbers::pi);
    REQUIRE(std::abs(diff) < kEraTolerance_rad);
    const double era = earth_rotation_angle_rad(t);
    REQUIRE(era >= 0.0);
    REQUIRE(era < 2 * std::numbers::pi);
  }
  // dut1 shifts UT1: ERA(t, +0.4 s) = ERA(t + 0.4 s).
  const int64_t t = utime_from_calendar({2024, 3, 1, 5, 0, 0.0});
  CHECK(std::abs(
            std::remainder(earth_rotation_angle_rad(t, 0.4) - earth_rotation_angle_rad(t + 400000),
                           2 * std::numbers::pi)) < kEraTolerance_rad);
}

TEST_CASE("GCRS <- ITRF agrees with eraC2t06a over 2000-2035", "[frames]") {
  double max_full = 0.0, max_c2i = 0.0;
  for (int64_t t : epochs_2000_2035()) {
    double tt1, tt2, ut1, ut2;
    jd_split(t, kTtMinusUtc_s, &tt1, &tt2);
    jd_split(t, 0.0, &ut1, &ut2);
    double rc2t[3][3], rc2i[3][3];
    eraC2t06a(tt1, tt2, ut1, ut2, 0.0, 0.0, rc2t);
    eraC2i06a(tt1, tt2, rc2i);
    const Eigen::Matrix3d itrf_from_gcrs_ref = from_erfa(rc2t);
    const double full = rotation_angle(gcrs_from_itrf(t) * itrf_from_gcrs_ref) / kArcsec;
    const double c2i =
        rotation_angle(precession_nutation_matrix(t) * from_erfa(rc2i).transpose()) / kArcsec;
    max_full = std::max(max_full, full);
    max_c2i = std::max(max_c2i, c2i);
  }
  std::printf(
      "frames: max |GCRS<-ITRF - eraC2t06a| over 2000-2035 = %.4f arcsec "
      "(celestial-to-intermediate part %.4f arcsec)\n",
      max_full, max_c2i);
  CHECK(max_full < kRequiredGcrsItrf_arcsec);
  CHECK(max_full < kModelGcrsItrf_arcsec);
  CHECK(max_c2i < kModelGcrsItrf_arcsec);
}

TEST_CASE("frame rotations are proper and invert", "[frames]") {
  for (int64_t t : epochs_2000_2035()) {
    const Eigen::Matrix3d G = gcrs_from_itrf(t, 0.1);
    REQUIRE((G * G.transpose() - Eigen::Matrix3d::Identity()).norm() < 1e-14);
    REQUIRE(std::abs(G.determinant() - 1.0) < 1e-14);
    REQUIRE((itrf_from_gcrs(t, 0.1) * G - Eigen::Matrix3d::Identity()).norm() < 1e-14);
  }
  // Sanity of the direction of rotation: a point fixed on Earth moves east in inertial space.
  const int64_t t = utime_from_calendar({2025, 6, 1, 0, 0, 0.0});
  const Eigen::Vector3d r_itrf(6378e3, 0, 0);
  const Eigen::Vector3d a = gcrs_from_itrf(t) * r_itrf;
  const Eigen::Vector3d b = gcrs_from_itrf(t + 60 * kMicrosPerSecond) * r_itrf;
  CHECK(a.cross(b).z() > 0.0);
}

TEST_CASE("EarthOrientationCache matches the direct rotation and refreshes", "[frames]") {
  EarthOrientationCache cache(1.0, 0.2);
  const int64_t t0 = utime_from_calendar({2026, 11, 22, 6, 0, 0.0});
  // Inside the refresh interval: precession-nutation is reused (moves ~1e-6 arcsec per s).
  for (int64_t dt_us : {0LL, 300000LL, 999000LL}) {
    const Eigen::Matrix3d cached = cache.gcrs_from_itrf(t0 + dt_us);
    const double err =
        rotation_angle(cached.transpose() * gcrs_from_itrf(t0 + dt_us, 0.2)) / kArcsec;
    REQUIRE(err < 1e-5);
  }
  // A day later it must have recomputed (nutation alone moves by ~0.1 arcsec a day).
  const int64_t t1 = t0 + 86400LL * kMicrosPerSecond;
  const double err1 =
      rotation_angle(cache.gcrs_from_itrf(t1).transpose() * gcrs_from_itrf(t1, 0.2));
  CHECK(err1 < 1e-12);
  // Going back in time also refreshes.
  const double err0 =
      rotation_angle(cache.gcrs_from_itrf(t0).transpose() * gcrs_from_itrf(t0, 0.2));
  CHECK(err0 < 1e-12);
}

TEST_CASE("WGS-84 geodetic <-> ECEF against ERFA and round trip", "[frames]") {
  std::mt19937_64 rng(84);
  std::uniform_real_distribution<double> lat(-std::numbers::pi / 2, std::numbers::pi / 2);
  std::uniform_real_distribution<double> lon(-std::numbers::pi, std::numbers::pi);
  std::uniform_real_distribution<double> alt(-5e3, 40000e3);
  std::vector<GeodeticPosition> points;
  for (int i = 0; i < 2000; ++i) points.push_back({lat(rng), lon(rng), alt(rng)});
  for (double la : {-std::numbers::pi / 2, 0.0, std::numbers::pi / 2, 1e-12, 1.5707963})
    for (double h : {0.0, 400e3, -100.0}) points.push_back({la, 0.3, h});

  for (const GeodeticPosition& g : points) {
    const Eigen::Vector3d r = ecef_from_geodetic(g);
    double xyz[3];
    REQUIRE(eraGd2gc(ERFA_WGS84, g.longitude_rad, g.latitude_rad, g.altitude_m, xyz) == 0);
    REQUIRE((r - Eigen::Vector3d(xyz[0], xyz[1], xyz[2])).norm() < kPositionTolerance_m);

    const GeodeticPosition back = geodetic_from_ecef(r);
    // Round trip converged to far below 1 mm (compared as a position).
    REQUIRE((ecef_from_geodetic(back) - r).norm() < 1e-6);
    REQUIRE(std::abs(back.altitude_m - g.altitude_m) < 1e-6);
    double elong, phi, height;
    REQUIRE(eraGc2gd(ERFA_WGS84, xyz, &elong, &phi, &height) == 0);
    // The truth is the input; ERFA's closed form (Fukushima 2006) is good to ~1e-11 rad at
    // GEO distances, i.e. sub-millimetre.
    REQUIRE(std::abs(back.latitude_rad - g.latitude_rad) < 1e-12);
    REQUIRE(std::abs(back.latitude_rad - phi) < 1e-10);
    REQUIRE(std::abs(back.altitude_m - height) < 1e-6);
  }
}

TEST_CASE("geocentric coordinates and NED matrices", "[frames]") {
  const GeocentricPosition s{7000e3, 0.7, -2.0};
  const GeocentricPosition back = geocentric_from_ecef(ecef_from_geocentric(s));
  CHECK(std::abs(back.radius_m - s.radius_m) < 1e-6);
  CHECK(std::abs(back.colatitude_rad - s.colatitude_rad) < 1e-14);
  CHECK(std::abs(back.longitude_rad - s.longitude_rad) < 1e-14);
  CHECK(geocentric_from_ecef(Eigen::Vector3d(0, 0, -7e6)).colatitude_rad == std::numbers::pi);

  // Geocentric NED: down = -r_hat, north = direction of decreasing colatitude.
  const Eigen::Matrix3d M = ecef_from_ned_geocentric(s.colatitude_rad, s.longitude_rad);
  CHECK((M.transpose() * M - Eigen::Matrix3d::Identity()).norm() < 1e-14);
  CHECK(std::abs(M.determinant() - 1.0) < 1e-14);
  const Eigen::Vector3d r = ecef_from_geocentric(s);
  CHECK((M.col(2) + r.normalized()).norm() < 1e-14);
  const double h = 1e-6;
  const Eigen::Vector3d north_fd =
      ecef_from_geocentric({s.radius_m, s.colatitude_rad - h, s.longitude_rad}) - r;
  CHECK((M.col(0) - north_fd.normalized()).norm() < 2 * h);  // forward difference: O(h)

  // Geodetic NED: down is the ellipsoid normal (finite difference along the altitude).
  const GeodeticPosition g{0.6, 1.1, 500e3};
  const Eigen::Matrix3d N = ecef_from_ned_geodetic(g.latitude_rad, g.longitude_rad);
  const Eigen::Vector3d up =
      ecef_from_geodetic({g.latitude_rad, g.longitude_rad, g.altitude_m + 1.0}) -
      ecef_from_geodetic(g);
  CHECK((N.col(2) + up.normalized()).norm() < 1e-8);
  const Eigen::Vector3d north =
      ecef_from_geodetic({g.latitude_rad + h, g.longitude_rad, g.altitude_m}) -
      ecef_from_geodetic(g);
  CHECK((N.col(0) - north.normalized()).norm() < 1e-6);
  CHECK((N.col(1) - N.col(2).cross(N.col(0))).norm() < 1e-14);
}
