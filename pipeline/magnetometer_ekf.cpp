#include "pipeline/magnetometer_ekf.hpp"

#include <cassert>
#include <cmath>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

MagnetometerEkf::MagnetometerEkf(const Options& options) : ScalarFilterBase(options, "ekf") {
  assert(options.validate().empty());
}

FilterUpdate MagnetometerEkf::update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT,
                                     int64_t utime) {
  FilterUpdate u;
  if (!begin_update(b_sensor_nT, h_norm_nT, utime)) return u;

  double y = 0.0, R = 0.0;
  measurement(b_sensor_nT, h_norm_nT, y, R);
  const Vector9d& x = state_.x;
  const Matrix9d& P = state_.P;
  const RowVector9d H = scalar_measurement_jacobian(x, b_sensor_nT);
  const Vector9d PHt = P * H.transpose();
  u.innovation_nT2 = y - predicted_scalar_measurement(x, b_sensor_nT);
  u.innovation_variance_nT4 = H.dot(PHt) + R;
  if (!(u.innovation_variance_nT4 > 0.0) || !std::isfinite(u.innovation_variance_nT4) ||
      !std::isfinite(u.innovation_nT2)) {
    ++state_.n_rejected_invalid;
    u.status = FilterUpdateStatus::kRejectedNumerical;
    return u;
  }
  if (!gate(u)) return u;

  const Vector9d K = PHt / u.innovation_variance_nT4;
  const Vector9d x_new = x + K * u.innovation_nT2;
  // Joseph form (I - K H) P (I - K H)^T + K R K^T, evaluated with the rank-1 structure of K H:
  // AP = P - K (P H^T)^T (P symmetric), AP (I - K H)^T = AP - (AP H^T) K^T. O(n^2), not O(n^3).
  const Matrix9d AP = P - K * PHt.transpose();
  const Vector9d APHt = AP * H.transpose();
  const Matrix9d P_new = AP - APHt * K.transpose() + (R * K) * K.transpose();
  commit_posterior(u, x_new, P_new);
  return u;
}

}  // namespace magcal
