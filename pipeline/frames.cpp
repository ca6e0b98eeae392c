// Earth frames (see frames.hpp).
//
// GCRS <-> ITRF model, CIO based as in IERS Conventions 2010 ch. 5 (and ERFA's eraC2t06a):
//   v_itrf = R3(ERA) C(X, Y, s) v_gcrs,   C = celestial-to-intermediate matrix
// X, Y are the CIP coordinates taken from the bias-precession-nutation matrix
//   NPB = R1(-(eps_A + d_eps)) R3(-(psi_bar + d_psi)) R1(phi_bar) R3(gamma_bar)
// with the IAU 2006 Fukushima-Williams bias-precession angles (full polynomials) and the 15
// largest luni-solar terms of IAU 2000B nutation (of 77; the dropped terms are each < 0.06
// arcsec) plus 2000B's fixed planetary offsets and the IAU 2006 J2 rate correction.
// s = -XY/2 + the two leading terms of the s + XY/2 series (mas level).
// Measured against eraC2t06a (IAU 2006/2000A, xp = yp = 0, same UT1 and TT) at 403 epochs
// over 2000-2035 (frames_test.cpp): max 0.014 arcsec. With UT1 = UTC the error of the product is
// dominated by |UT1 - UTC| < 0.9 s, i.e. < 13.5 arcsec of Earth rotation; polar motion
// (< 0.5 arcsec) is ignored.
#include "pipeline/frames.hpp"

#include <cmath>
#include <numbers>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {
namespace {

constexpr double kTwoPi = 2.0 * std::numbers::pi;
constexpr double kArcsecToRad = std::numbers::pi / (180.0 * 3600.0);
constexpr double kTurnArcsec = 1296000.0;
constexpr int64_t kMicrosPerDay = 86'400LL * kMicrosPerSecond;
// Days from J2000.0 (JD 2451545.0) to the Unix epoch (JD 2440587.5).
constexpr double kUnixEpochMinusJ2000_days = kJulianDateUnixEpoch - kJulianDateJ2000;

// IAU 2000B luni-solar nutation, the 15 largest terms (McCarthy & Luzum 2003; the same
// numbers as ERFA nut00b.c). Multipliers of (l, l', F, D, Om); coefficients in 0.1 uas:
// d_psi = (sp + spt t) sin(arg) + cp cos(arg), d_eps = (ce + cet t) cos(arg) + se sin(arg).
struct NutationTerm {
  int nl, nlp, nf, nd, nom;
  double sp, spt, cp, ce, cet, se;
};
constexpr NutationTerm kNutation2000B[] = {
    {0, 0, 0, 0, 1, -172064161.0, -174666.0, 33386.0, 92052331.0, 9086.0, 15377.0},
    {0, 0, 2, -2, 2, -13170906.0, -1675.0, -13696.0, 5730336.0, -3015.0, -4587.0},
    {0, 0, 2, 0, 2, -2276413.0, -234.0, 2796.0, 978459.0, -485.0, 1374.0},
    {0, 0, 0, 0, 2, 2074554.0, 207.0, -698.0, -897492.0, 470.0, -291.0},
    {0, 1, 0, 0, 0, 1475877.0, -3633.0, 11817.0, 73871.0, -184.0, -1924.0},
    {0, 1, 2, -2, 2, -516821.0, 1226.0, -524.0, 224386.0, -677.0, -174.0},
    {1, 0, 0, 0, 0, 711159.0, 73.0, -872.0, -6750.0, 0.0, 358.0},
    {0, 0, 2, 0, 1, -387298.0, -367.0, 380.0, 200728.0, 18.0, 318.0},
    {1, 0, 2, 0, 2, -301461.0, -36.0, 816.0, 129025.0, -63.0, 367.0},
    {0, -1, 2, -2, 2, 215829.0, -494.0, 111.0, -95929.0, 299.0, 132.0},
    {0, 0, 2, -2, 1, 128227.0, 137.0, 181.0, -68982.0, -9.0, 39.0},
    {-1, 0, 2, 0, 2, 123457.0, 11.0, 19.0, -53311.0, 32.0, -4.0},
    {-1, 0, 0, 2, 0, 156994.0, 10.0, -168.0, -1235.0, 0.0, 82.0},
    {1, 0, 0, 0, 1, 63110.0, 63.0, 27.0, -33228.0, 0.0, -9.0},
    {-1, 0, 0, 0, 1, -57976.0, -63.0, -189.0, 31429.0, 0.0, -75.0},
};

double wrap_arcsec_to_rad(double arcsec) {
  return std::fmod(arcsec, kTurnArcsec) * kArcsecToRad;
}

// Nutation in longitude and obliquity (radians), IAU 2000B truncated, IAU 2006-adjusted.
void nutation_rad(double t, double* dpsi, double* deps) {
  // Delaunay arguments, 2000B's linear forms (Simon et al. 1994).
  const double el = wrap_arcsec_to_rad(485868.249036 + 1717915923.2178 * t);
  const double elp = wrap_arcsec_to_rad(1287104.79305 + 129596581.0481 * t);
  const double f = wrap_arcsec_to_rad(335779.526232 + 1739527262.8478 * t);
  const double d = wrap_arcsec_to_rad(1072260.70369 + 1602961601.2090 * t);
  const double om = wrap_arcsec_to_rad(450160.398036 - 6962890.5431 * t);
  double dp = 0.0, de = 0.0;
  for (const NutationTerm& k : kNutation2000B) {
    const double arg =
        std::fmod(k.nl * el + k.nlp * elp + k.nf * f + k.nd * d + k.nom * om, kTwoPi);
    const double s = std::sin(arg), c = std::cos(arg);
    dp += (k.sp + k.spt * t) * s + k.cp * c;
    de += (k.ce + k.cet * t) * c + k.se * s;
  }
  constexpr double k01uasToRad = kArcsecToRad / 1e7;
  // Fixed offsets standing in for the planetary terms (2000B), -0.135 / +0.388 mas.
  constexpr double kDpsiPlanetary = -0.135e-3 * kArcsecToRad;
  constexpr double kDepsPlanetary = 0.388e-3 * kArcsecToRad;
  // IAU 2006 adjustment of the 2000 nutation for the J2 rate (as eraNut06a).
  const double fj2 = -2.7774e-6 * t;
  *dpsi = (dp * k01uasToRad + kDpsiPlanetary) * (1.0 + 0.4697e-6 + fj2);
  *deps = (de * k01uasToRad + kDepsPlanetary) * (1.0 + fj2);
}

// Days since J2000.0 on the UT1 scale, split into whole-day-aligned parts for ERA precision.
double earth_rotation_angle_from_utime(int64_t utime, double dut1_s) {
  const int64_t whole_days =
      utime >= 0 ? utime / kMicrosPerDay : -((-utime + kMicrosPerDay - 1) / kMicrosPerDay);
  const double day_fraction =
      static_cast<double>(utime - whole_days * kMicrosPerDay) / kMicrosPerDay +
      dut1_s / kSecondsPerDay;
  // Du = days since J2000 = whole_days + day_fraction - 10957.5; its fractional part is
  // day_fraction + 0.5 (mod 1), kept separate so the 2 pi * Du term loses no precision.
  const double du = static_cast<double>(whole_days) + day_fraction + kUnixEpochMinusJ2000_days;
  const double turns = (day_fraction + 0.5) + 0.7790572732640 + 0.00273781191135448 * du;
  double era = kTwoPi * (turns - std::floor(turns));
  if (era >= kTwoPi) era -= kTwoPi;
  return era;
}

}  // namespace

double earth_rotation_angle_rad(int64_t utime, double dut1_s) {
  return earth_rotation_angle_from_utime(utime, dut1_s);
}

Eigen::Matrix3d precession_nutation_matrix(int64_t utime) {
  const double t = julian_centuries_tt_from_utime(utime);
  // IAU 2006 Fukushima-Williams bias-precession angles and mean obliquity (arcsec).
  const double gamb =
      (-0.052928 +
       (10.556378 + (0.4932044 + (-0.00031238 + (-0.000002788 + 0.0000000260 * t) * t) * t) * t) *
           t) *
      kArcsecToRad;
  const double phib =
      (84381.412819 +
       (-46.811016 + (0.0511268 + (0.00053289 + (-0.000000440 - 0.0000000176 * t) * t) * t) * t) *
           t) *
      kArcsecToRad;
  const double psib =
      (-0.041775 +
       (5038.481484 + (1.5584175 + (-0.00018522 + (-0.000026452 - 0.0000000148 * t) * t) * t) * t) *
           t) *
      kArcsecToRad;
  const double epsa =
      (84381.406 +
       (-46.836769 + (-0.0001831 + (0.00200340 + (-0.000000576 - 0.0000000434 * t) * t) * t) * t) *
           t) *
      kArcsecToRad;
  double dpsi = 0.0, deps = 0.0;
  nutation_rad(t, &dpsi, &deps);
  const Eigen::Matrix3d npb = frame_rotation_x(-(epsa + deps)) * frame_rotation_z(-(psib + dpsi)) *
                              frame_rotation_x(phib) * frame_rotation_z(gamb);

  // CIP coordinates and the CIO locator s, then the celestial-to-intermediate matrix.
  const double x = npb(2, 0), y = npb(2, 1);
  const double om = wrap_arcsec_to_rad(450160.398036 - 6962890.5431 * t);
  const double s =
      -0.5 * x * y + (94.0 + 3808.65 * t - 2640.73 * std::sin(om) - 63.53 * std::sin(2.0 * om)) *
                         1e-6 * kArcsecToRad;
  const double r2 = x * x + y * y;
  const double e = r2 > 0.0 ? std::atan2(y, x) : 0.0;
  const double d = std::atan(std::sqrt(r2 / (1.0 - r2)));
  return frame_rotation_z(-(e + s)) * frame_rotation_y(d) * frame_rotation_z(e);
}

Eigen::Matrix3d itrf_from_gcrs(int64_t utime, double dut1_s) {
  return frame_rotation_z(earth_rotation_angle_rad(utime, dut1_s)) *
         precession_nutation_matrix(utime);
}

Eigen::Matrix3d gcrs_from_itrf(int64_t utime, double dut1_s) {
  return itrf_from_gcrs(utime, dut1_s).transpose();
}

EarthOrientationCache::EarthOrientationCache(double refresh_s, double dut1_s)
    : refresh_s_(refresh_s), dut1_s_(dut1_s) {}

const Eigen::Matrix3d& EarthOrientationCache::gcrs_from_itrf(int64_t utime) {
  const bool stale = npb_utime_ == INT64_MIN || std::abs(static_cast<double>(utime - npb_utime_)) >
                                                    refresh_s_ * kMicrosPerSecond;
  if (stale) {
    npb_ = precession_nutation_matrix(utime);
    npb_utime_ = utime;
  }
  result_.noalias() =
      (frame_rotation_z(earth_rotation_angle_rad(utime, dut1_s_)) * npb_).transpose();
  return result_;
}

// ---------------------------------------------------------------------------------------------
// WGS-84 geodetic / geocentric coordinates.

namespace {
constexpr double kE2 = kWgs84Flattening * (2.0 - kWgs84Flattening);  // first eccentricity^2
}

Eigen::Vector3d ecef_from_geodetic(const GeodeticPosition& g) {
  const double sl = std::sin(g.latitude_rad), cl = std::cos(g.latitude_rad);
  const double n = kWgs84SemiMajorAxis_m / std::sqrt(1.0 - kE2 * sl * sl);  // prime vertical
  return {(n + g.altitude_m) * cl * std::cos(g.longitude_rad),
          (n + g.altitude_m) * cl * std::sin(g.longitude_rad),
          (n * (1.0 - kE2) + g.altitude_m) * sl};
}

GeodeticPosition geodetic_from_ecef(const Eigen::Vector3d& r) {
  // Iterate on the latitude from Bowring's initial guess: h and lat are refined until the
  // latitude changes by < 1e-14 rad (far below 1 mm); converges in 2-4 steps in LEO.
  const double a = kWgs84SemiMajorAxis_m;
  const double b = a * (1.0 - kWgs84Flattening);
  const double p = std::hypot(r.x(), r.y());
  GeodeticPosition g;
  g.longitude_rad = std::atan2(r.y(), r.x());
  if (p < 1e-9) {  // on the axis: latitude +-90 deg, altitude from the pole
    g.latitude_rad = r.z() >= 0.0 ? std::numbers::pi / 2 : -std::numbers::pi / 2;
    g.altitude_m = std::abs(r.z()) - b;
    return g;
  }
  const double ep2 = (a * a - b * b) / (b * b);
  const double beta = std::atan2(a * r.z(), b * p);
  double lat = std::atan2(r.z() + ep2 * b * std::pow(std::sin(beta), 3),
                          p - kE2 * a * std::pow(std::cos(beta), 3));
  for (int k = 0; k < 10; ++k) {
    const double sl = std::sin(lat);
    const double n = a / std::sqrt(1.0 - kE2 * sl * sl);
    const double h = p / std::cos(lat) - n;
    const double next = std::atan2(r.z(), p * (1.0 - kE2 * n / (n + h)));
    const bool done = std::abs(next - lat) < 1e-14;
    lat = next;
    if (done) break;
  }
  const double sl = std::sin(lat), cl = std::cos(lat);
  const double n = a / std::sqrt(1.0 - kE2 * sl * sl);
  g.latitude_rad = lat;
  // The better-conditioned form of h for any latitude (avoids p / cos(lat) near the poles).
  g.altitude_m = p * cl + r.z() * sl - a * a / n;
  return g;
}

GeocentricPosition geocentric_from_ecef(const Eigen::Vector3d& r) {
  GeocentricPosition s;
  s.radius_m = r.norm();
  s.colatitude_rad = std::atan2(std::hypot(r.x(), r.y()), r.z());
  s.longitude_rad = std::atan2(r.y(), r.x());
  return s;
}

Eigen::Vector3d ecef_from_geocentric(const GeocentricPosition& s) {
  const double st = std::sin(s.colatitude_rad), ct = std::cos(s.colatitude_rad);
  return s.radius_m *
         Eigen::Vector3d(st * std::cos(s.longitude_rad), st * std::sin(s.longitude_rad), ct);
}

Eigen::Matrix3d ecef_from_ned_geocentric(double colatitude_rad, double longitude_rad) {
  // Columns: north = -e_theta, east = e_phi, down = -e_r.
  const double st = std::sin(colatitude_rad), ct = std::cos(colatitude_rad);
  const double sp = std::sin(longitude_rad), cp = std::cos(longitude_rad);
  Eigen::Matrix3d m;
  m << -ct * cp, -sp, -st * cp,  //
      -ct * sp, cp, -st * sp,    //
      st, 0.0, -ct;
  return m;
}

Eigen::Matrix3d ecef_from_ned_geodetic(double latitude_rad, double longitude_rad) {
  // Geodetic colatitude gives the same matrix with the ellipsoid normal as "up".
  return ecef_from_ned_geocentric(std::numbers::pi / 2 - latitude_rad, longitude_rad);
}

}  // namespace magcal
