#include "service/daemon/ops/systemd_notifier.hpp"

#include <cstdlib>

#include <systemd/sd-daemon.h>

namespace magcal {

SystemdNotifier::SystemdNotifier() {
  const char* socket = std::getenv("NOTIFY_SOCKET");
  enabled_ = socket != nullptr && socket[0] != '\0';
  uint64_t usec = 0;
  // > 0: WatchdogSec= is set for this process (unset_environment = 0: children of a test keep
  // the variables; magcald starts no children).
  if (enabled_ && sd_watchdog_enabled(0, &usec) > 0) {
    watchdog_interval_ = std::chrono::microseconds(static_cast<int64_t>(usec));
  }
}

bool SystemdNotifier::send(const std::string& message) {
  if (!enabled_) return false;
  // sd_notify: > 0 sent, 0 no socket, < 0 -errno.
  return sd_notify(0, message.c_str()) > 0;
}

bool SystemdNotifier::ready() {
  return send("READY=1");
}

bool SystemdNotifier::stopping() {
  stopping_.store(true);
  return send("STOPPING=1");
}

bool SystemdNotifier::status(const std::string& text) {
  // One line: sd_notify's format is newline-separated assignments.
  std::string line = text;
  for (char& c : line) {
    if (c == '\n') c = ' ';
  }
  return send("STATUS=" + line);
}

bool SystemdNotifier::watchdog_ping(Clock::time_point now) {
  if (!enabled_ || watchdog_interval_.count() <= 0 || stopping_.load()) return false;
  const int64_t half_ticks =
      std::chrono::duration_cast<Clock::duration>(watchdog_interval_ / 2).count();
  const int64_t now_ticks = now.time_since_epoch().count();
  int64_t last = last_ping_ticks_.load(std::memory_order_relaxed);
  if (last != kNever && now_ticks - last < half_ticks) return false;
  // One ping per half interval, also when two threads call at once.
  if (!last_ping_ticks_.compare_exchange_strong(last, now_ticks, std::memory_order_relaxed)) {
    return false;
  }
  return send("WATCHDOG=1");
}

}  // namespace magcal
