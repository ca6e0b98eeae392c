#include "pipeline/magnetometer_ekf.hpp"

#include <cassert>
#include <cmath>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

MagnetometerEkf::MagnetometerEkf(const Options& options)
    : MagnetometerEkf(std::make_shared<const Options>(options)) {}

MagnetometerEkf::MagnetometerEkf(std::shared_ptr<const Options> options)
    : ScalarFilterBase(std::move(options), "ekf") {
  assert(options_ && this->options().validate().empty());
}

FilterUpdate MagnetometerEkf::update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT,
                                     int64_t utime) {
  FilterUpdate u;
  if (!begin_update(u, b_sensor_nT, h_norm_nT, utime)) return u;

  const Vector9d& x = state_.x;
  const RowVector9d H = scalar_measurement_jacobian(x, b_sensor_nT);
  // f = S^T H^T, H P H^T = |f|^2, P H^T = S f.
  const Vector9d f = state_.S.transpose() * H.transpose();
  const Eigen::Vector3d y = parameters().apply(b_sensor_nT);
  finish_update(u, b_sensor_nT, h_norm_nT, y, b_sensor_nT.squaredNorm() - y.squaredNorm(),
                f.squaredNorm(), f);
  return u;
}

}  // namespace magcal
