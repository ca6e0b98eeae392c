// Orbit propagation from Keplerian elements (ECI = GCRS, metres, seconds).
//
// Two-body:  n = sqrt(mu / a^3),  M(t) = M0 + n (t - t0),  Kepler  M = E - e sin E,
//   r_pf = a (cos E - e, sqrt(1-e^2) sin E, 0),  v_pf = n a / (1 - e cos E) (-sin E, sqrt(1-e^2)
//   cos E, 0), r_eci = Rz(-RAAN) Rx(-i) Rz(-omega) r_pf   (perifocal -> ECI).
// J2 secular (first order, Vallado 9.41-9.43; p = a (1 - e^2), k = 1.5 J2 (Re / p)^2):
//   dRAAN/dt  = -k n cos i
//   domega/dt = +k n (2 - 2.5 sin^2 i)
//   dM/dt     =  n (1 + k sqrt(1 - e^2) (1 - 1.5 sin^2 i))
// J2 short-period terms are NOT modelled (deliberately: the mean-element secular model is
// what the reference-field geometry needs; short-period terms move the spacecraft by a few km
// (amplitude ~ J2 Re^2 / a), changing the field by ~0.1 %, which no estimator depends on).
// ECEF: r_ecef = itrf_from_gcrs(t) r_eci (pipeline/frames.hpp); v_ecef adds -omega_E x r.
#pragma once

#include <cstdint>
#include <string>

#include <Eigen/Core>

#include "pipeline/frames.hpp"

namespace magcal {

constexpr double kEarthMu_m3_s2 = 3.986004418e14;  // EGM-96 / WGS-84 GM
constexpr double kEarthJ2 = 1.08262668e-3;         // EGM-96 unnormalised C20 (sign flipped)
constexpr double kEarthEquatorialRadius_m = kWgs84SemiMajorAxis_m;  // J2 reference radius

struct KeplerianElements {
  double semi_major_axis_m = kEarthEquatorialRadius_m + 550e3;
  double eccentricity = 0.0;      // [0, 1)
  double inclination_rad = 0.0;   // [0, pi]
  double raan_rad = 0.0;          // right ascension of the ascending node
  double arg_perigee_rad = 0.0;   // omega
  double mean_anomaly_rad = 0.0;  // M0 at epoch_utime
  int64_t epoch_utime = 0;
};

enum class J2Model {
  none,     // two-body
  secular,  // secular drift of RAAN, omega, M (mean elements)
};

struct OrbitState {
  Eigen::Vector3d r_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_m_s = Eigen::Vector3d::Zero();
};

class Orbit {
 public:
  struct Options {
    J2Model j2 = J2Model::none;
    // "" if valid, else names the bad element.
    std::string validate(const KeplerianElements& elements) const;
  };

  // elements must satisfy options.validate(elements) == "".
  Orbit(const KeplerianElements& elements, const Options& options);

  OrbitState state_eci(int64_t utime) const;
  // ECEF (ITRF) state from an ECI state and the matching gcrs_from_itrf matrix.
  static OrbitState ecef_from_eci(const OrbitState& eci, const Eigen::Matrix3d& gcrs_from_itrf);

  double mean_motion_rad_s() const { return n_; }        // unperturbed n
  double period_s() const;                               // 2 pi / n (Keplerian)
  double raan_rate_rad_s() const { return raan_rate_; }  // 0 without J2
  double arg_perigee_rate_rad_s() const { return omega_rate_; }
  double mean_anomaly_rate_rad_s() const { return m_rate_; }
  const KeplerianElements& elements() const { return elements_; }

 private:
  KeplerianElements elements_;
  Options options_;
  double n_ = 0.0;
  double raan_rate_ = 0.0;
  double omega_rate_ = 0.0;
  double m_rate_ = 0.0;
};

// Solves Kepler's equation M = E - e sin E for E (Newton, |error| < 1e-15 rad).
double eccentric_anomaly(double mean_anomaly_rad, double eccentricity);

}  // namespace magcal
