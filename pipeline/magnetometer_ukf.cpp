#include "pipeline/magnetometer_ukf.hpp"

#include <cassert>
#include <cmath>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

namespace {

constexpr int kN = 9;  // state dimension

// The scaled unscented transform's spread and weights (magnetometer_ukf.hpp).
struct UnscentedWeights {
  double lambda, spread, w0m, w0c, wi;
};

UnscentedWeights unscented_weights(double alpha, double beta, double kappa) {
  UnscentedWeights w;
  w.lambda = alpha * alpha * (kN + kappa) - kN;
  w.spread = std::sqrt(kN + w.lambda);
  w.w0m = w.lambda / (kN + w.lambda);
  w.w0c = w.w0m + 1.0 - alpha * alpha + beta;
  w.wi = 1.0 / (2.0 * (kN + w.lambda));
  return w;
}

}  // namespace

std::string UkfOptions::validate() const {
  std::string e = FilterOptions::validate();
  if (!e.empty()) return e;
  if (!(alpha > 0.0) || !std::isfinite(alpha)) return "ukf alpha must be > 0";
  if (!std::isfinite(beta) || !std::isfinite(kappa)) return "ukf beta and kappa must be finite";
  const UnscentedWeights w = unscented_weights(alpha, beta, kappa);
  if (!(kN + w.lambda > 0.0)) return "ukf requires n + lambda = alpha^2 (n + kappa) > 0";
  if (w.w0c < 0.0) return "ukf requires W0c = lambda / (n + lambda) + 1 - alpha^2 + beta >= 0";
  return {};
}

MagnetometerUkf::MagnetometerUkf(const Options& options)
    : MagnetometerUkf(std::make_shared<const Options>(options)) {}

MagnetometerUkf::MagnetometerUkf(std::shared_ptr<const Options> options)
    : ScalarFilterBase(std::move(options), "ukf") {
  assert(options_ && this->options().validate().empty());
}

FilterUpdate MagnetometerUkf::update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT,
                                     int64_t utime) {
  FilterUpdate u;
  if (!begin_update(u, b_sensor_nT, h_norm_nT, utime)) return u;

  // Sigma points X_{+-i} = x +- spread S_i. The state is static, so propagation is h() only, and
  // y(p) = (I + D) B - b is linear in p: y(X_{+-i}) = y0 +- spread m_i, m_i = (dy/dp) S_i, so
  //   Z_{+-i} = |B|^2 - |y0|^2 -+ 2 spread y0.m_i - spread^2 |m_i|^2   (exact, no approximation).
  const Eigen::Vector3d& B = b_sensor_nT;
  const Matrix9d& S = state_.S;
  const Eigen::Vector3d y0 = parameters().apply(B);
  const double z0 = B.squaredNorm() - y0.squaredNorm();
  Vector9d a, q;
  for (int i = 0; i < kN; ++i) {
    const auto c = S.col(i);
    const Eigen::Vector3d m(-c(0) + B(0) * c(3) + B(1) * c(6) + B(2) * c(7),
                            -c(1) + B(1) * c(4) + B(0) * c(6) + B(2) * c(8),
                            -c(2) + B(2) * c(5) + B(0) * c(7) + B(1) * c(8));
    a(i) = y0.dot(m);
    q(i) = m.squaredNorm();
  }
  // Computed per sample (a few flops), not stored: memory per tracked spacecraft.
  const Options& o = options();
  const auto [lambda, spread, w0m, w0c, wi] = unscented_weights(o.alpha, o.beta, o.kappa);
  const double s2 = spread * spread;
  const Vector9d z_plus = (z0 - 2.0 * spread * a.array() - s2 * q.array()).matrix();
  const Vector9d z_minus = (z0 + 2.0 * spread * a.array() - s2 * q.array()).matrix();
  const double y_hat = w0m * z0 + wi * (z_plus.sum() + z_minus.sum());
  const double dz0 = z0 - y_hat;
  const Vector9d dzp = z_plus.array() - y_hat;
  const Vector9d dzm = z_minus.array() - y_hat;
  const double hph = w0c * dz0 * dz0 + wi * (dzp.squaredNorm() + dzm.squaredNorm());
  // Pxz = sum_i Wi (X_i - x)(Z_i - y_hat) = S v (the centre point has X_0 - x = 0).
  const Vector9d v = (wi * spread) * (dzp - dzm);
  finish_update(u, b_sensor_nT, h_norm_nT, y0, y_hat, hph, v);
  return u;
}

}  // namespace magcal
