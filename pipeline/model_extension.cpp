#include "pipeline/model_extension.hpp"

#include <cmath>

#include <Eigen/Eigenvalues>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/outer_product_sum.hpp"
#include "pipeline/scalar_measurement.hpp"

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

bool extension_effects_small(const Vector6d& a, double mean_h_nT, double max_fraction) {
  const double limit_nT = max_fraction * mean_h_nT;
  return (a.head<3>().cwiseAbs() * (mean_h_nT * mean_h_nT)).maxCoeff() <= limit_nT &&
         a.tail<3>().cwiseAbs().maxCoeff() <= limit_nT;
}

ExtensionFitAtEstimate fit_extension_at_estimate(const SampleSet& samples,
                                                 const ExtensionInputs& in, double sigma_nT) {
  ExtensionFitAtEstimate fit;
  const std::size_t n = samples.size();
  if (n < 20 || in.y_nT.size() != n) return fit;
  const std::vector<Vector6d> phi = model_extension_regressors(in);
  const double mu = scalar_noise_mean(sigma_nT);
  std::vector<double> r(n), w(n);
  OuterProductSum<7> normal;  // sum w [phi; r] [phi; r]^T
  double mean_h_nT = 0.0;
  for (std::size_t k = 0; k < n; ++k) {
    const double h = samples[k].h_body_nT.norm();
    mean_h_nT += h;
    r[k] = in.y_nT[k].squaredNorm() - h * h - mu;
    w[k] = 1.0 / scalar_noise_variance(in.y_nT[k], sigma_nT);
    Eigen::Matrix<double, 7, 1> row;
    row << phi[k], r[k];
    normal.add(std::sqrt(w[k]) * row);
  }
  mean_h_nT /= static_cast<double>(n);
  const Eigen::Matrix<double, 7, 7> sum = normal.sum();
  const Matrix6d F = sum.topLeftCorner<6, 6>();
  const Vector6d d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return fit;
  // k (1/nT) and eta (nT) columns differ by ~1e9: solve in the diagonally scaled form.
  const Vector6d s_inv = d.cwiseSqrt().cwiseInverse();
  const Eigen::SelfAdjointEigenSolver<Matrix6d> eig(s_inv.asDiagonal() * F * s_inv.asDiagonal());
  if (!(eig.eigenvalues()(0) > 1e-12 * eig.eigenvalues()(5))) return fit;
  const Matrix6d F_inv = s_inv.asDiagonal() * eig.eigenvectors() *
                         eig.eigenvalues().cwiseInverse().asDiagonal() *
                         eig.eigenvectors().transpose() * s_inv.asDiagonal();
  fit.a = F_inv * sum.block<6, 1>(0, 6);
  std::vector<Vector6d> scores(n);
  std::vector<double> e(n);
  double chi2_extended = 0.0;
  for (std::size_t k = 0; k < n; ++k) {
    const double residual = r[k] - phi[k].dot(fit.a);
    chi2_extended += w[k] * residual * residual;
    scores[k] = (w[k] * residual) * phi[k];
    e[k] = std::sqrt(w[k]) * residual;
  }
  const double dof = static_cast<double>(n) - 6.0;
  const int lag = bartlett_lag_window(lag1_autocorrelation(e), static_cast<int>(n));
  const Matrix6d hac =
      F_inv * newey_west_meat<6>(scores, lag) * F_inv * (static_cast<double>(n) / dof);
  fit.covariance = covariance_not_below(F_inv, hac);
  fit.used = fit.a.allFinite() &&
             bic_prefers_extension(sum(6, 6), chi2_extended, static_cast<int>(n)) &&
             extension_effects_small(fit.a, mean_h_nT);
  return fit;
}

}  // namespace magcal
