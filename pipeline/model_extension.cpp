#include "pipeline/model_extension.hpp"

#include <cmath>

namespace magcal {
std::vector<Vector6d> model_extension_regressors(const SampleSet& samples,
                                                 const CalibrationParameters& p) {
  const std::size_t n = samples.size();
  std::vector<Vector6d> phi(n);
  if (n == 0) return phi;
  // Calibrated vectors y_k, computed once: phi_k holds y_k until its signs are known.
  for (std::size_t k = 0; k < n; ++k) phi[k].head<3>() = p.apply(samples[k].b_sensor_nT);
  // Hysteresis signs s_k (per axis) from the central differences y_{k+1} - y_{k-1} (one-sided
  // at the ends), held over a zero difference; y_{k-1} is kept aside before phi_{k-1} is
  // overwritten.
  Eigen::Vector3d last = Eigen::Vector3d::Ones();
  Eigen::Vector3d y_previous = phi[0].head<3>();
  for (std::size_t k = 0; k < n; ++k) {
    const Eigen::Vector3d y = phi[k].head<3>();
    const Eigen::Vector3d y_next = k + 1 < n ? Eigen::Vector3d(phi[k + 1].head<3>()) : y;
    const Eigen::Vector3d change =
        n < 2 ? Eigen::Vector3d::Zero() : Eigen::Vector3d(y_next - y_previous);
    for (int i = 0; i < 3; ++i) {
      if (change(i) > 0.0) last(i) = 1.0;
      if (change(i) < 0.0) last(i) = -1.0;
    }
    phi[k] << 2.0 * y.cwiseAbs2().cwiseProduct(y), 2.0 * y.cwiseProduct(last);
    y_previous = y;
  }
  return phi;
}

bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples) {
  if (!(chi2_base > 0.0) || !(chi2_extended > 0.0) || n_samples < 20) return false;
  const double n = static_cast<double>(n_samples);
  return n * std::log(chi2_base / chi2_extended) > 6.0 * std::log(n);
}

}  // namespace magcal
