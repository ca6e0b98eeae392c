// Earth frames: ITRF (ECEF) <-> GCRS (the inertial frame of attitude quaternions), WGS-84
// geodetic <-> ECEF, and geocentric spherical coordinates.
//
// Model (stated accuracy is checked against ERFA in tests/pipeline/frames_test.cpp):
//   GCRS_from_ITRF = C^T(t) · R3(-ERA(UT1)): C(X, Y, s) is the celestial-to-intermediate
//   matrix from IAU 2006 bias-precession and IAU 2000B nutation truncated to its 15 largest
//   terms (frames.cpp), R3(-ERA) undoes the Earth rotation angle (IAU 2000).
//   Polar motion (< 0.5 arcsec) and UT1-UTC (unless dut1_s is given) are ignored.
//   The implementation states the truncation and its measured error (target <= 15 arcsec over
//   2000-2035 with UT1 = UTC; a few arcsec when dut1_s is supplied). Measured: the model is
//   within 0.014 arcsec of ERFA's IAU 2006/2000A; the rest of the error budget is UT1 - UTC
//   (< 0.9 s, i.e. < 13.5 arcsec of Earth rotation, when dut1_s is not given) and polar motion.
//   precession_nutation_matrix() is the CIO-based celestial-to-intermediate matrix
//   C(X, Y, s), so itrf_from_gcrs = R3(ERA) C (IERS Conventions 2010, eq. 5.1 without W).
#pragma once

#include <cstdint>

#include <Eigen/Core>

namespace magcal {

constexpr double kWgs84SemiMajorAxis_m = 6378137.0;
constexpr double kWgs84Flattening = 1.0 / 298.257223563;
constexpr double kEarthRotationRate_rad_s = 7.292115146706979e-5;  // ERA rate (IERS 2010)

// Earth rotation angle (IAU 2000), radians in [0, 2 pi), at UT1 = UTC + dut1_s.
double earth_rotation_angle_rad(int64_t utime, double dut1_s = 0.0);

// Precession-nutation-bias as the celestial-to-intermediate matrix: v_CIRS = C v_GCRS (the
// part without the Earth rotation). Depends only slowly on time (cache it per second).
Eigen::Matrix3d precession_nutation_matrix(int64_t utime);

// v_gcrs = gcrs_from_itrf(t) v_itrf (and the transpose for the other way).
Eigen::Matrix3d gcrs_from_itrf(int64_t utime, double dut1_s = 0.0);
Eigen::Matrix3d itrf_from_gcrs(int64_t utime, double dut1_s = 0.0);

// Caches the precession-nutation matrix: recomputed only when the time moves by more than
// refresh_s (default 1 s; NPB changes by ~1e-6 arcsec per second). The Earth rotation angle
// is evaluated exactly every call. Not thread-safe: one per thread/worker.
class EarthOrientationCache {
 public:
  explicit EarthOrientationCache(double refresh_s = 1.0, double dut1_s = 0.0);
  const Eigen::Matrix3d& gcrs_from_itrf(int64_t utime);

 private:
  double refresh_s_;
  double dut1_s_;
  int64_t npb_utime_ = INT64_MIN;
  Eigen::Matrix3d npb_ = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d result_ = Eigen::Matrix3d::Identity();
};

struct GeodeticPosition {
  double latitude_rad = 0.0;   // WGS-84 geodetic
  double longitude_rad = 0.0;  // east positive
  double altitude_m = 0.0;     // above the ellipsoid
};
struct GeocentricPosition {
  double radius_m = 0.0;
  double colatitude_rad = 0.0;  // 0 at the north pole
  double longitude_rad = 0.0;
};

Eigen::Vector3d ecef_from_geodetic(const GeodeticPosition& g);
GeodeticPosition geodetic_from_ecef(const Eigen::Vector3d& r_ecef_m);
GeocentricPosition geocentric_from_ecef(const Eigen::Vector3d& r_ecef_m);
Eigen::Vector3d ecef_from_geocentric(const GeocentricPosition& s);

// Rotation from local geocentric (north, east, down) at colatitude/longitude to ECEF.
Eigen::Matrix3d ecef_from_ned_geocentric(double colatitude_rad, double longitude_rad);
// Same with the geodetic latitude (north/east/down tangent to the ellipsoid).
Eigen::Matrix3d ecef_from_ned_geodetic(double latitude_rad, double longitude_rad);

}  // namespace magcal
