#include "service/daemon/ops/lcm_publisher.hpp"

#include "service/daemon/intake/lcm_ingest.hpp"

namespace magcal {

LcmPublisher::LcmPublisher(const std::string& url, std::string calibration_channel,
                           std::string status_channel)
    : lcm_(open_lcm(url, &error_)),
      calibration_channel_(std::move(calibration_channel)),
      status_channel_(std::move(status_channel)) {}

void LcmPublisher::publish(const calibration_t& msg) {
  if (!lcm_) return;
  std::lock_guard lock(mutex_);
  if (lcm_->publish(calibration_channel_, &msg) != 0) ++failures_;
}

void LcmPublisher::publish(const daemon_status_t& msg) {
  if (!lcm_) return;
  std::lock_guard lock(mutex_);
  if (lcm_->publish(status_channel_, &msg) != 0) ++failures_;
}

int64_t LcmPublisher::failures() const {
  std::lock_guard lock(mutex_);
  return failures_;
}

}  // namespace magcal
