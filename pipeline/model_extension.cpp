#include "pipeline/model_extension.hpp"

#include <cmath>

namespace magcal {
std::vector<Eigen::Vector3d> hysteresis_signs(const std::vector<Eigen::Vector3d>& y) {
  const std::size_t n = y.size();
  std::vector<Eigen::Vector3d> signs(n);
  Eigen::Vector3d last = Eigen::Vector3d::Ones();
  for (std::size_t k = 0; k < n; ++k) {
    const Eigen::Vector3d& y_previous = k > 0 ? y[k - 1] : y[k];
    const Eigen::Vector3d& y_next = k == 0 && n > 1 ? y[1] : y[k];
    const Eigen::Vector3d change = y_next - y_previous;
    for (int i = 0; i < 3; ++i) {
      if (change(i) > 0.0) last(i) = 1.0;
      if (change(i) < 0.0) last(i) = -1.0;
    }
    signs[k] = last;
  }
  return signs;
}

std::vector<Vector6d> model_extension_regressors(const SampleSet& samples,
                                                 const CalibrationParameters& p) {
  std::vector<Eigen::Vector3d> y(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) y[k] = p.apply(samples[k].b_sensor_nT);
  const std::vector<Eigen::Vector3d> s = hysteresis_signs(y);
  std::vector<Vector6d> phi(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) {
    phi[k] << 2.0 * y[k].cwiseAbs2().cwiseProduct(y[k]), 2.0 * y[k].cwiseProduct(s[k]);
  }
  return phi;
}

std::vector<Eigen::Vector3d> extension_corrected_vectors(const SampleSet& samples,
                                                         const CalibrationParameters& p,
                                                         const Eigen::Vector3d& k_per_nT,
                                                         const Eigen::Vector3d& eta_nT) {
  std::vector<Eigen::Vector3d> x(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) x[k] = p.apply(samples[k].b_sensor_nT);
  const std::vector<Eigen::Vector3d> s = hysteresis_signs(x);
  for (std::size_t k = 0; k < samples.size(); ++k) {
    x[k] -= k_per_nT.cwiseProduct(x[k].cwiseAbs2()) + eta_nT.cwiseProduct(s[k]);
  }
  return x;
}

bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples) {
  if (!(chi2_base > 0.0) || !(chi2_extended > 0.0) || n_samples < 20) return false;
  const double n = static_cast<double>(n_samples);
  return n * std::log(chi2_base / chi2_extended) > 6.0 * std::log(n);
}

}  // namespace magcal
