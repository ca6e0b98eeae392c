#include "pipeline/model_extension.hpp"

#include <cmath>

namespace magcal {
ExtensionInputs extension_inputs(const SampleSet& samples, const CalibrationParameters& p) {
  const std::size_t n = samples.size();
  ExtensionInputs in;
  in.y_nT.resize(n);
  in.signs.resize(n);
  for (std::size_t k = 0; k < n; ++k) in.y_nT[k] = p.apply(samples[k].b_sensor_nT);
  Eigen::Vector3d last = Eigen::Vector3d::Ones();
  for (std::size_t k = 0; k < n; ++k) {
    const Eigen::Vector3d& y_previous = k > 0 ? in.y_nT[k - 1] : in.y_nT[k];
    const Eigen::Vector3d& y_next = k == 0 && n > 1 ? in.y_nT[1] : in.y_nT[k];
    const Eigen::Vector3d change = y_next - y_previous;
    for (int i = 0; i < 3; ++i) {
      if (change(i) > 0.0) last(i) = 1.0;
      if (change(i) < 0.0) last(i) = -1.0;
    }
    in.signs[k] = last;
  }
  return in;
}

std::vector<Vector6d> model_extension_regressors(const ExtensionInputs& in) {
  std::vector<Vector6d> phi(in.y_nT.size());
  for (std::size_t k = 0; k < phi.size(); ++k) {
    const Eigen::Vector3d& y = in.y_nT[k];
    phi[k] << 2.0 * y.cwiseAbs2().cwiseProduct(y), 2.0 * y.cwiseProduct(in.signs[k]);
  }
  return phi;
}

std::vector<Eigen::Vector3d> extension_corrected_vectors(const ExtensionInputs& in,
                                                         const Eigen::Vector3d& k_per_nT,
                                                         const Eigen::Vector3d& eta_nT) {
  std::vector<Eigen::Vector3d> x(in.y_nT.size());
  for (std::size_t k = 0; k < x.size(); ++k) {
    const Eigen::Vector3d& y = in.y_nT[k];
    x[k] = y - k_per_nT.cwiseProduct(y.cwiseAbs2()) - eta_nT.cwiseProduct(in.signs[k]);
  }
  return x;
}

bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples) {
  if (!(chi2_base > 0.0) || !(chi2_extended > 0.0) || n_samples < 20) return false;
  const double n = static_cast<double>(n_samples);
  return n * std::log(chi2_base / chi2_extended) > 6.0 * std::log(n);
}

}  // namespace magcal
