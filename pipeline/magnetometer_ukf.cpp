#include "pipeline/magnetometer_ukf.hpp"

#include <cassert>
#include <cmath>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

namespace {
constexpr int kN = 9;  // state dimension
}

std::string UkfOptions::validate() const {
  std::string e = FilterOptions::validate();
  if (!e.empty()) return e;
  if (!(alpha > 0.0) || !std::isfinite(alpha)) return "ukf alpha must be > 0";
  if (!std::isfinite(beta) || !std::isfinite(kappa)) return "ukf beta and kappa must be finite";
  const double lambda = alpha * alpha * (kN + kappa) - kN;
  if (!(kN + lambda > 0.0)) return "ukf requires n + lambda = alpha^2 (n + kappa) > 0";
  return {};
}

MagnetometerUkf::MagnetometerUkf(const Options& options)
    : ScalarFilterBase(options, "ukf"), ukf_options_(options) {
  assert(options.validate().empty());
  const double lambda = options.alpha * options.alpha * (kN + options.kappa) - kN;
  spread_ = std::sqrt(kN + lambda);
  w0m_ = lambda / (kN + lambda);
  w0c_ = w0m_ + 1.0 - options.alpha * options.alpha + options.beta;
  wi_ = 1.0 / (2.0 * (kN + lambda));
}

FilterUpdate MagnetometerUkf::update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT,
                                     int64_t utime) {
  FilterUpdate u;
  if (!begin_update(b_sensor_nT, h_norm_nT, utime)) return u;

  double y = 0.0, R = 0.0;
  measurement(b_sensor_nT, h_norm_nT, y, R);
  Matrix9d L;
  switch (guard_covariance(state_.P, L)) {
    case CovarianceGuard::kOk:
      break;
    case CovarianceGuard::kRepaired:
      ++state_.n_covariance_repairs;
      break;
    case CovarianceGuard::kNonFinite:
      ++state_.n_rejected_invalid;
      u.status = FilterUpdateStatus::kRejectedNumerical;
      return u;
  }

  // Sigma points x +- spread L_i; the state is static, so propagation is just h().
  const Vector9d& x = state_.x;
  const double z0 = predicted_scalar_measurement(x, b_sensor_nT);
  Vector9d z_plus, z_minus;
  for (int i = 0; i < kN; ++i) {
    const Vector9d d = spread_ * L.col(i);
    z_plus(i) = predicted_scalar_measurement(x + d, b_sensor_nT);
    z_minus(i) = predicted_scalar_measurement(x - d, b_sensor_nT);
  }
  const double y_hat = w0m_ * z0 + wi_ * (z_plus.sum() + z_minus.sum());
  const double dz0 = z0 - y_hat;
  const Vector9d dzp = z_plus.array() - y_hat;
  const Vector9d dzm = z_minus.array() - y_hat;
  u.innovation_nT2 = y - y_hat;
  u.innovation_variance_nT4 = w0c_ * dz0 * dz0 + wi_ * (dzp.squaredNorm() + dzm.squaredNorm()) + R;
  if (!(u.innovation_variance_nT4 > 0.0) || !std::isfinite(u.innovation_variance_nT4) ||
      !std::isfinite(u.innovation_nT2)) {
    ++state_.n_rejected_invalid;
    u.status = FilterUpdateStatus::kRejectedNumerical;
    return u;
  }
  if (!gate(u)) return u;

  // Pxz = sum_i Wi (X_i - x)(Z_i - y_hat); the centre point has X_0 - x = 0.
  const Vector9d Pxz = (wi_ * spread_) * (L * (dzp - dzm));
  const Vector9d K = Pxz / u.innovation_variance_nT4;
  const Vector9d x_new = x + K * u.innovation_nT2;
  const Matrix9d P_new = state_.P - K * Pxz.transpose();  // = P - K S K^T
  commit_posterior(u, x_new, P_new);
  return u;
}

}  // namespace magcal
