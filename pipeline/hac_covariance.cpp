#include "pipeline/hac_covariance.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Dense>

namespace magcal {

namespace {
template <class T>
double lag1(const std::vector<T>& residuals, double (*dot)(const T&, const T&)) {
  if (residuals.size() < 3) return std::numeric_limits<double>::quiet_NaN();
  double num = 0.0, den = 0.0;
  for (std::size_t k = 0; k < residuals.size(); ++k) {
    den += dot(residuals[k], residuals[k]);
    if (k + 1 < residuals.size()) num += dot(residuals[k], residuals[k + 1]);
  }
  if (!(den > 0.0)) return std::numeric_limits<double>::quiet_NaN();
  return num / den;
}
}  // namespace

double lag1_autocorrelation(const std::vector<double>& residuals) {
  return lag1<double>(residuals, [](const double& a, const double& b) { return a * b; });
}

double lag1_autocorrelation(const std::vector<Eigen::Vector3d>& residuals) {
  return lag1<Eigen::Vector3d>(
      residuals, [](const Eigen::Vector3d& a, const Eigen::Vector3d& b) { return a.dot(b); });
}

int bartlett_lag_window(double rho, int n) {
  if (n < 4 || !std::isfinite(rho)) return 0;
  if (std::abs(rho) < 3.0 / std::sqrt(static_cast<double>(n))) return 0;
  const double r = std::clamp(rho, -0.97, 0.97);
  const double alpha = 4.0 * r * r / ((1.0 - r) * (1.0 - r) * (1.0 + r) * (1.0 + r));
  const double lag = std::ceil(1.1447 * std::cbrt(alpha * n));
  return static_cast<int>(std::min(lag, static_cast<double>(n / 4)));
}

template Eigen::Matrix<double, 3, 3> covariance_not_below<3>(const Eigen::Matrix<double, 3, 3>&,
                                                             const Eigen::Matrix<double, 3, 3>&);
template Eigen::Matrix<double, 6, 6> covariance_not_below<6>(const Eigen::Matrix<double, 6, 6>&,
                                                             const Eigen::Matrix<double, 6, 6>&);
template Eigen::Matrix<double, 9, 9> covariance_not_below<9>(const Eigen::Matrix<double, 9, 9>&,
                                                             const Eigen::Matrix<double, 9, 9>&);

}  // namespace magcal
