// systemd service notifications for magcald (design.md "Operations surface": Type=notify with
// WatchdogSec, deploy/magcald.service), through sd_notify(3) from libsystemd.
//
//   ready()          READY=1: once the database is open and the LCM subscription is live
//   watchdog_ping()  WATCHDOG=1 from the worker loop: call it every iteration, it sends at most
//                    one ping per half of the watchdog interval (sd_watchdog_enabled(3): the
//                    interval comes from WatchdogSec= through $WATCHDOG_USEC)
//   stopping()       STOPPING=1: when shutdown starts (before the drain), so systemd waits for
//                    the drain within TimeoutStopSec instead of taking the daemon for hung;
//                    systemd stops the watchdog then, and so do later watchdog_ping() calls
//   status(text)     STATUS=text: the one-line state `systemctl status` shows
//
// Without $NOTIFY_SOCKET (not started by systemd, or Type= is not notify) every call is a no-op
// that returns false. The environment is read once, in the constructor. Thread-safe: ready()
// and stopping() come from the main thread, watchdog_ping() from the worker.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <string>

namespace magcal {

class SystemdNotifier {
 public:
  using Clock = std::chrono::steady_clock;

  // Reads $NOTIFY_SOCKET, $WATCHDOG_USEC and $WATCHDOG_PID (sd_watchdog_enabled).
  SystemdNotifier();

  // True when $NOTIFY_SOCKET is set: the calls below send something.
  bool enabled() const { return enabled_; }
  // The watchdog interval systemd expects pings within ($WATCHDOG_USEC), 0 when the watchdog
  // is off (no WatchdogSec=, or $WATCHDOG_PID names another process).
  std::chrono::microseconds watchdog_interval() const { return watchdog_interval_; }

  // Each returns true when the message was sent, false when disabled or sd_notify failed
  // (a failure never stops the daemon: systemd then restarts it through the watchdog).
  bool ready();
  bool stopping();
  bool status(const std::string& text);
  // Sends WATCHDOG=1 when the watchdog is on, stopping() was not called, and half of its
  // interval has passed since the last ping sent (the first call always sends). `now` is
  // injectable for tests.
  bool watchdog_ping(Clock::time_point now = Clock::now());

 private:
  bool send(const std::string& message);

  bool enabled_ = false;
  std::chrono::microseconds watchdog_interval_{0};
  // steady_clock ticks of the last ping sent; kNever before the first.
  static constexpr int64_t kNever = INT64_MIN;
  std::atomic<int64_t> last_ping_ticks_{kNever};
  std::atomic<bool> stopping_{false};
};

}  // namespace magcal
