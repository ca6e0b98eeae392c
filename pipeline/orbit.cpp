#include "pipeline/orbit.hpp"

#include <cassert>
#include <cmath>
#include <numbers>

#include "pipeline/frames.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {

namespace {
constexpr double kTwoPi = 6.283185307179586476925286766559;
}  // namespace

double eccentric_anomaly(double mean_anomaly_rad, double eccentricity) {
  const double M = std::remainder(mean_anomaly_rad, kTwoPi);  // [-pi, pi]
  // Starting guess E = pi for high e avoids the slow start near M ~ 0 (Vallado).
  double E = eccentricity > 0.8 ? (M < 0 ? -std::numbers::pi : std::numbers::pi) : M;
  for (int i = 0; i < 50; ++i) {
    const double f = E - eccentricity * std::sin(E) - M;
    const double step = f / (1.0 - eccentricity * std::cos(E));
    E -= step;
    if (std::abs(step) < 1e-15) break;
  }
  return E;
}

std::string Orbit::Options::validate(const KeplerianElements& el) const {
  if (!std::isfinite(el.semi_major_axis_m) || el.semi_major_axis_m <= 0.0)
    return "semi_major_axis: must be positive";
  if (!std::isfinite(el.eccentricity) || el.eccentricity < 0.0 || el.eccentricity >= 1.0)
    return "eccentricity: must be in [0, 1)";
  if (el.semi_major_axis_m * (1.0 - el.eccentricity) < kEarthEquatorialRadius_m)
    return "semi_major_axis/eccentricity: perigee below the Earth's surface";
  if (!std::isfinite(el.inclination_rad) || el.inclination_rad < 0.0 ||
      el.inclination_rad > std::numbers::pi)
    return "inclination: must be in [0, 180] deg";
  if (!std::isfinite(el.raan_rad)) return "raan: not finite";
  if (!std::isfinite(el.arg_perigee_rad)) return "arg_perigee: not finite";
  if (!std::isfinite(el.mean_anomaly_rad)) return "mean_anomaly: not finite";
  return "";
}

Orbit::Orbit(const KeplerianElements& elements, const Options& options)
    : elements_(elements), options_(options) {
  assert(options.validate(elements).empty());
  const double a = elements.semi_major_axis_m;
  const double e = elements.eccentricity;
  n_ = std::sqrt(kEarthMu_m3_s2 / (a * a * a));
  m_rate_ = n_;
  if (options.j2 == J2Model::secular) {
    const double p = a * (1.0 - e * e);
    const double k =
        1.5 * kEarthJ2 * (kEarthEquatorialRadius_m / p) * (kEarthEquatorialRadius_m / p);
    const double ci = std::cos(elements.inclination_rad);
    const double s2 = 1.0 - ci * ci;
    raan_rate_ = -k * n_ * ci;
    omega_rate_ = k * n_ * (2.0 - 2.5 * s2);
    m_rate_ = n_ * (1.0 + k * std::sqrt(1.0 - e * e) * (1.0 - 1.5 * s2));
  }
}

double Orbit::period_s() const {
  return kTwoPi / n_;
}

OrbitState Orbit::state_eci(int64_t utime) const {
  const double dt = static_cast<double>(utime - elements_.epoch_utime) * 1e-6;
  const double e = elements_.eccentricity;
  const double a = elements_.semi_major_axis_m;
  const double M = elements_.mean_anomaly_rad + m_rate_ * dt;
  const double raan = elements_.raan_rad + raan_rate_ * dt;
  const double omega = elements_.arg_perigee_rad + omega_rate_ * dt;

  const double E = eccentric_anomaly(M, e);
  const double cE = std::cos(E), sE = std::sin(E);
  const double sq = std::sqrt(1.0 - e * e);
  const Eigen::Vector3d r_pf(a * (cE - e), a * sq * sE, 0.0);
  // Mean-element rate: with J2 the along-track rate is m_rate_, not n_.
  const double edot = m_rate_ / (1.0 - e * cE);
  const Eigen::Vector3d v_pf(-a * sE * edot, a * sq * cE * edot, 0.0);

  // Perifocal -> ECI: the transpose of the frame rotations Rz(omega) Rx(i) Rz(raan).
  const Eigen::Matrix3d eci_from_pf =
      (frame_rotation_z(omega) * frame_rotation_x(elements_.inclination_rad) *
       frame_rotation_z(raan))
          .transpose();
  OrbitState s;
  s.r_m = eci_from_pf * r_pf;
  s.v_m_s = eci_from_pf * v_pf;
  if (raan_rate_ != 0.0 || omega_rate_ != 0.0) {
    // The rotating node/perigee add omega_frame x r to the inertial velocity.
    const Eigen::Vector3d node_axis(0.0, 0.0, 1.0);
    const Eigen::Vector3d normal = eci_from_pf.col(2);
    s.v_m_s += (raan_rate_ * node_axis + omega_rate_ * normal).cross(s.r_m);
  }
  return s;
}

OrbitState Orbit::ecef_from_eci(const OrbitState& eci, const Eigen::Matrix3d& gcrs_from_itrf) {
  const Eigen::Matrix3d itrf_from_gcrs = gcrs_from_itrf.transpose();
  const Eigen::Vector3d omega_earth(0.0, 0.0, kEarthRotationRate_rad_s);
  OrbitState out;
  out.r_m = itrf_from_gcrs * eci.r_m;
  out.v_m_s = itrf_from_gcrs * eci.v_m_s - omega_earth.cross(out.r_m);
  return out;
}

}  // namespace magcal
