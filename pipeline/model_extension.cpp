#include "pipeline/model_extension.hpp"

#include <cmath>

namespace magcal {
namespace {

// Hysteresis signs s_k (per axis) from the calibrated vectors of p, in sample order.
std::vector<Eigen::Vector3d> hysteresis_signs(const SampleSet& samples,
                                              const CalibrationParameters& p) {
  const std::size_t n = samples.size();
  std::vector<Eigen::Vector3d> s(n, Eigen::Vector3d::Ones());
  if (n < 2) return s;
  Eigen::Vector3d last = Eigen::Vector3d::Ones();
  for (std::size_t k = 0; k < n; ++k) {
    const std::size_t lo = k == 0 ? 0 : k - 1;
    const std::size_t hi = k + 1 < n ? k + 1 : n - 1;
    const Eigen::Vector3d change =
        p.apply(samples[hi].b_sensor_nT) - p.apply(samples[lo].b_sensor_nT);
    for (int i = 0; i < 3; ++i) {
      if (change(i) > 0.0) last(i) = 1.0;
      if (change(i) < 0.0) last(i) = -1.0;
    }
    s[k] = last;
  }
  return s;
}

}  // namespace

std::vector<Vector6d> model_extension_regressors(const SampleSet& samples,
                                                 const CalibrationParameters& p) {
  const std::vector<Eigen::Vector3d> s = hysteresis_signs(samples, p);
  std::vector<Vector6d> phi(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const Eigen::Vector3d y = p.apply(samples[k].b_sensor_nT);
    phi[k] << 2.0 * y.cwiseAbs2().cwiseProduct(y), 2.0 * y.cwiseProduct(s[k]);
  }
  return phi;
}

bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples) {
  if (!(chi2_base > 0.0) || !(chi2_extended > 0.0) || n_samples < 20) return false;
  const double n = static_cast<double>(n_samples);
  return n * std::log(chi2_base / chi2_extended) > 6.0 * std::log(n);
}

}  // namespace magcal
