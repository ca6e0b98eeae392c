#include "service/daemon/ops/throttled_log.hpp"

#include <spdlog/spdlog.h>

namespace magcal {

void ThrottledLog::warn(const std::string& key, const std::string& message) {
  Entry& e = entries_[key];
  ++e.seen;
  const auto now = std::chrono::steady_clock::now();
  if (e.seen <= burst_) {
    spdlog::warn("{}", message);
    e.last_logged = now;
    return;
  }
  const double since_s = std::chrono::duration<double>(now - e.last_logged).count();
  if (since_s < period_s_) {
    ++e.suppressed;
    return;
  }
  spdlog::warn("{} ({} similar suppressed, {} total '{}')", message, e.suppressed, e.seen, key);
  e.suppressed = 0;
  e.last_logged = now;
}

int64_t ThrottledLog::suppressed(const std::string& key) const {
  const auto it = entries_.find(key);
  return it == entries_.end() ? 0 : it->second.suppressed;
}

}  // namespace magcal
