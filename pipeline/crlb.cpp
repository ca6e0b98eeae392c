#include "pipeline/crlb.hpp"

#include <cmath>
#include <cstdio>
#include <limits>

#include <Eigen/Dense>

#include "pipeline/outer_product_sum.hpp"
#include "pipeline/scalar_measurement.hpp"

namespace magcal {

void scaled_condition(const Matrix9d& F, double* condition_number, double* min_eigenvalue) {
  const Vector9d d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !F.allFinite()) {
    *condition_number = std::numeric_limits<double>::infinity();
    *min_eigenvalue = 0.0;
    return;
  }
  const Vector9d s_inv = d.cwiseSqrt().cwiseInverse();
  const Matrix9d Fs = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  const Vector9d ev =
      Eigen::SelfAdjointEigenSolver<Matrix9d>(Fs, Eigen::EigenvaluesOnly).eigenvalues();
  *min_eigenvalue = ev(0);
  *condition_number = ev(0) > 0.0 ? ev(8) / ev(0) : std::numeric_limits<double>::infinity();
}

CrlbResult compute_crlb(const SampleSet& samples, const CalibrationParameters& p, double sigma_nT,
                        double max_condition) {
  CrlbResult r;
  OuterProductSum<9> F;  // sum w H^T H as sum (sqrt(w) H)^T (sqrt(w) H)
  for (const CalibrationSample& s : samples) {
    if (!s.b_sensor_nT.allFinite()) continue;
    const Eigen::Vector3d y = p.apply(s.b_sensor_nT);
    const RowVector9d H = scalar_measurement_jacobian_at(y, s.b_sensor_nT);
    const double w = 1.0 / scalar_noise_variance(y, sigma_nT);
    F.add(std::sqrt(w) * H.transpose());
    ++r.n_samples;
  }
  r.fisher = F.sum();
  scaled_condition(r.fisher, &r.condition_number, &r.min_eigenvalue);
  if (!(r.condition_number < max_condition)) {
    char buf[128];
    std::snprintf(buf, sizeof buf, "Fisher information is singular (scaled condition %.3g)",
                  r.condition_number);
    r.message = buf;
    return r;
  }
  const Vector9d s_inv = r.fisher.diagonal().cwiseSqrt().cwiseInverse();
  const Matrix9d Fs = s_inv.asDiagonal() * r.fisher * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Matrix9d> eig(Fs);
  r.covariance = s_inv.asDiagonal() * eig.eigenvectors() *
                 eig.eigenvalues().cwiseInverse().asDiagonal() * eig.eigenvectors().transpose() *
                 s_inv.asDiagonal();
  r.sigma = r.covariance.diagonal().cwiseSqrt();
  r.ok = true;
  return r;
}

}  // namespace magcal
