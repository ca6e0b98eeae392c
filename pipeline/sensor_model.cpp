#include "pipeline/sensor_model.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <numbers>

#include <Eigen/LU>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {}  // namespace

double NormalSampler::next() {
  if (has_spare_) {
    has_spare_ = false;
    return spare_;
  }
  // u1 in (0, 1] so log(u1) is finite; u2 in [0, 1). 53-bit uniforms.
  const double u1 = static_cast<double>((engine_() >> 11) + 1) * 0x1.0p-53;
  const double u2 = static_cast<double>(engine_() >> 11) * 0x1.0p-53;
  const double r = std::sqrt(-2.0 * std::log(u1));
  const double a = 2.0 * std::numbers::pi * u2;
  spare_ = r * std::sin(a);
  has_spare_ = true;
  return r * std::cos(a);
}

std::string SensorModelParameters::validate() const {
  if (!bias_nT.allFinite() || bias_nT.cwiseAbs().maxCoeff() > 1e6)
    return "sensor.bias_nT: must be finite, |b| <= 1e6 nT";
  if (!D.allFinite() || (D - D.transpose()).cwiseAbs().maxCoeff() > 1e-12)
    return "sensor.D: must be a finite symmetric matrix";
  if (D.cwiseAbs().maxCoeff() > 0.5) return "sensor.D: entries must be within [-0.5, 0.5]";
  if (std::abs((Eigen::Matrix3d::Identity() + D).determinant()) < 1e-6)
    return "sensor.D: I + D is singular";
  if (!permeability.allFinite() || permeability.cwiseAbs().maxCoeff() > 0.5)
    return "sensor.permeability: entries must be finite and within [-0.5, 0.5]";
  if (!internal_misalignment_mrad.allFinite() ||
      internal_misalignment_mrad.cwiseAbs().maxCoeff() > 100.0)
    return "sensor.internal_misalignment_mrad: must be within [-100, 100] mrad";
  if (!installation_deg.allFinite() || installation_deg.cwiseAbs().maxCoeff() > 180.0)
    return "sensor.installation_deg: must be within [-180, 180] deg";
  if (!std::isfinite(noise_sigma_nT) || noise_sigma_nT < 0.0 || noise_sigma_nT > 1e4)
    return "sensor.noise_sigma_nT: must be in [0, 1e4]";
  if (!std::isfinite(nonlinearity_fraction_fs) || std::abs(nonlinearity_fraction_fs) > 0.1)
    return "sensor.nonlinearity_fraction_fs: must be within [-0.1, 0.1]";
  if (!std::isfinite(hysteresis_fraction_fs) || hysteresis_fraction_fs < 0.0 ||
      hysteresis_fraction_fs > 0.1)
    return "sensor.hysteresis_fraction_fs: must be in [0, 0.1]";
  if (!std::isfinite(full_scale_nT) || full_scale_nT < 1000.0 || full_scale_nT > 1e7)
    return "sensor.full_scale_nT: must be in [1e3, 1e7]";
  if (nbits != 0 && (nbits < 4 || nbits > 32)) return "sensor.nbits: must be 0 (off) or 4..32";
  if (!temperature_coefficient_nT_per_C.allFinite() ||
      temperature_coefficient_nT_per_C.cwiseAbs().maxCoeff() > 1e3)
    return "sensor.temperature_coefficient_nT_per_C: must be within [-1e3, 1e3]";
  if (!std::isfinite(reference_temperature_C) || std::abs(reference_temperature_C) > 200.0)
    return "sensor.reference_temperature_C: must be within [-200, 200]";
  if (!drift_nT_per_day.allFinite() || drift_nT_per_day.cwiseAbs().maxCoeff() > 1e4)
    return "sensor.drift_nT_per_day: must be within [-1e4, 1e4]";
  if (!std::isfinite(temperature_mean_C) || std::abs(temperature_mean_C) > 200.0)
    return "temperature.mean_C: must be within [-200, 200]";
  if (!std::isfinite(temperature_amplitude_C) || temperature_amplitude_C < 0.0 ||
      temperature_amplitude_C > 200.0)
    return "temperature.amplitude_C: must be in [0, 200]";
  if (!std::isfinite(temperature_period_s) || temperature_period_s < 0.0)
    return "temperature.period_s: must be >= 0 (0 = orbital period)";
  if (!std::isfinite(temperature_phase_deg)) return "temperature.phase_deg: not finite";
  return "";
}

Eigen::Matrix3d SensorModelParameters::internal_misalignment() const {
  const Eigen::Vector3d a = internal_misalignment_mrad * 1e-3;
  return dcm_from_roll_pitch_yaw({a.x(), a.y(), a.z()});
}

Eigen::Matrix3d SensorModelParameters::installation() const {
  const Eigen::Vector3d a = installation_deg * kDegToRad;
  return dcm_from_roll_pitch_yaw({a.x(), a.y(), a.z()});
}

double SensorModelParameters::lsb_nT() const {
  return nbits == 0 ? 0.0 : 2.0 * full_scale_nT / std::ldexp(1.0, nbits);
}

SensorModel::SensorModel(const SensorModelParameters& parameters)
    : p_(parameters),
      M_(parameters.internal_misalignment() * parameters.installation()),
      inv_I_plus_D_((Eigen::Matrix3d::Identity() + parameters.D).inverse()) {
  assert(p_.validate().empty());
}

double SensorModel::temperature_C(double t_s) const {
  if (p_.temperature_amplitude_C == 0.0 || p_.temperature_period_s <= 0.0)
    return p_.temperature_mean_C;
  return p_.temperature_mean_C +
         p_.temperature_amplitude_C *
             std::sin(2.0 * std::numbers::pi * t_s / p_.temperature_period_s +
                      p_.temperature_phase_deg * kDegToRad);
}

Eigen::Vector3d SensorModel::bias_nT(double t_s, double temperature_C) const {
  return p_.bias_nT +
         p_.temperature_coefficient_nT_per_C * (temperature_C - p_.reference_temperature_C) +
         p_.drift_nT_per_day * (t_s / kSecondsPerDay);
}

Eigen::Vector3d SensorModel::digitise(const Eigen::Vector3d& y_nT) const {
  Eigen::Vector3d B = inv_I_plus_D_ * y_nT;
  const double fs = p_.full_scale_nT;
  if (p_.saturation) B = B.cwiseMax(-fs).cwiseMin(fs);
  if (p_.nbits > 0) {
    const double lsb = p_.lsb_nT();
    for (int i = 0; i < 3; ++i) B(i) = std::clamp(std::round(B(i) / lsb) * lsb, -fs, fs - lsb);
  }
  return B;
}

Eigen::Vector3d SensorModel::measure(const Eigen::Vector3d& h_body_nT, double t_s,
                                     NormalSampler& normal) {
  const Eigen::Vector3d x = M_ * h_body_nT;
  const double fs = p_.full_scale_nT;
  Eigen::Vector3d y = x;
  if (!p_.permeability.isZero(0.0)) y += p_.permeability * x;
  y += bias_nT(t_s, temperature_C(t_s));
  if (p_.nonlinearity_fraction_fs != 0.0) y += (p_.nonlinearity_fraction_fs / fs) * x.cwiseAbs2();
  if (p_.hysteresis_fraction_fs != 0.0) {
    if (has_last_x_) {
      for (int i = 0; i < 3; ++i) {
        const double change = x(i) - last_x_(i);
        if (change > 0.0) hyst_sign_(i) = 1.0;
        if (change < 0.0) hyst_sign_(i) = -1.0;
      }
    }
    y += (p_.hysteresis_fraction_fs * fs) * hyst_sign_;
  }
  last_x_ = x;
  has_last_x_ = true;
  if (p_.noise_sigma_nT > 0.0) y += p_.noise_sigma_nT * normal.next3();
  return digitise(y);
}

}  // namespace magcal
