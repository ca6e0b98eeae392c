#include "pipeline/magnetometer_ukf.hpp"

#include <cassert>
#include <cmath>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

namespace {

constexpr int kN = 9;  // state dimension

// The scaled unscented transform's squared spread n + lambda and weights (magnetometer_ukf.hpp;
// W0m = 1 - 2n Wi is not needed on its own).
struct UnscentedWeights {
  double lambda, spread2, w0c, wi;
};

UnscentedWeights unscented_weights(double alpha, double beta, double kappa) {
  UnscentedWeights w;
  w.lambda = alpha * alpha * (kN + kappa) - kN;
  w.spread2 = kN + w.lambda;
  w.w0c = w.lambda / w.spread2 + 1.0 - alpha * alpha + beta;
  w.wi = 1.0 / (2.0 * w.spread2);
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
  // Their weighted sums in closed form (W0m + 2n Wi = 1 and 2 Wi spread^2 = 1 for every alpha,
  // beta, kappa), with a_i = y0.m_i, q_i = |m_i|^2, Q = sum q_i, e_i = Q - spread^2 q_i:
  //   y_hat = Z_0 - Q,  Z_0 - y_hat = Q,  Z_{+-i} - y_hat = -+ 2 spread a_i + e_i,
  //   H P H^T = W0c Q^2 + 2 Wi sum e_i^2 + 4 sum a_i^2,  S^-1 Pxz = Wi spread (Z_+ - Z_-) = -2 a
  // (the same sums, without forming the 2n + 1 points).
  const Eigen::Vector3d& B = b_sensor_nT;
  const Matrix9d& S = state_.S;
  const Eigen::Vector3d y0 = parameters().apply(B);
  const double z0 = B.squaredNorm() - y0.squaredNorm();
  Vector9d a, q;
  for_each_column<kN>([&](auto column) {
    constexpr int i = decltype(column)::value;
    // S is lower triangular: S(r, i) = 0 for r < i drops out at compile time.
    const auto c = [&](int r) { return r >= i ? S(r, i) : 0.0; };
    const Eigen::Vector3d m(-c(0) + B(0) * c(3) + B(1) * c(6) + B(2) * c(7),
                            -c(1) + B(1) * c(4) + B(0) * c(6) + B(2) * c(8),
                            -c(2) + B(2) * c(5) + B(0) * c(7) + B(1) * c(8));
    a(i) = y0.dot(m);
    q(i) = m.squaredNorm();
  });
  // Computed per sample (a few flops), not stored: memory per tracked spacecraft.
  const Options& o = options();
  const UnscentedWeights w = unscented_weights(o.alpha, o.beta, o.kappa);
  const double q_sum = q.sum();
  const double y_hat = z0 - q_sum;
  const Vector9d e = (q_sum - w.spread2 * q.array()).matrix();
  const double hph = w.w0c * q_sum * q_sum + 2.0 * w.wi * e.squaredNorm() + 4.0 * a.squaredNorm();
  const Vector9d v = -2.0 * a;
  finish_update(u, b_sensor_nT, h_norm_nT, y0, y_hat, hph, v);
  return u;
}

}  // namespace magcal
