// Publishes results (calibration_t) and health (daemon_status_t) from any thread. Owns its own
// lcm::LCM (publish-only: no subscriptions, so no receive thread) and serialises publishes.
// A publisher without a URL is a no-op (replay mode without [lcm] publish_url).
#pragma once

#include <memory>
#include <mutex>
#include <string>

#include <lcm/lcm-cpp.hpp>

#include "schemas/magcal_messages.hpp"

namespace magcal {

class LcmPublisher {
 public:
  LcmPublisher() = default;  // disabled
  // "" = LCM's default URL. Check ok() afterwards.
  explicit LcmPublisher(const std::string& url, std::string calibration_channel,
                        std::string status_channel);

  bool enabled() const { return lcm_ != nullptr; }
  bool ok() const { return !lcm_ || lcm_->good(); }
  // Why the URL could not be opened (open_lcm's words) when !ok().
  const std::string& error() const { return error_; }

  void publish(const calibration_t& msg);
  void publish(const daemon_status_t& msg);
  int64_t failures() const;

 private:
  std::string error_;  // before lcm_: open_lcm writes it while lcm_ is initialised
  std::unique_ptr<lcm::LCM> lcm_;
  std::string calibration_channel_, status_channel_;
  mutable std::mutex mutex_;
  int64_t failures_ = 0;
};

}  // namespace magcal
