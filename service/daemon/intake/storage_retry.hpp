// How the daemon rides out storage faults: a failed storage operation is never
// dropped. Each storage path of the daemon (the worker's commit, its duplicate check, the
// refit thread) owns one StorageRetry: after a transient failure (StorageError::transient():
// lock past the busy timeout, I/O error, full disk, file deleted / moved / read-only) the
// operation is retried with bounded exponential backoff (50 ms doubling to 2 s); while it fails,
// DaemonCounters::storage_healthy() is false and every failed attempt and retry is counted.
// When the path has failed continuously for [storage] max_failure_s (pg_max_failure_s on
// PostgreSQL: DaemonConfig::storage_max_failure_s()), or on a permanent error
// (corrupt or foreign file, constraint), StorageOutage is thrown: the daemon stops receiving,
// logs why and exits with kExitStorageFailed, so systemd restarts it and an operator is alerted.
// Once the daemon is stopping on a signal, a StopDeadline shared by its paths gives up sooner:
// [storage] stop_max_failure_s after the stop.
#pragma once

#include <atomic>
#include <chrono>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "service/daemon/ops/health.hpp"
#include "storage/storage_error.hpp"

namespace magcal {

// Storage stayed broken past [storage] max_failure_s, or failed permanently. Fatal for the
// daemon (exit code kExitStorageFailed).
class StorageOutage : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// When a stop (SIGTERM/SIGINT) gives up on failing storage ([storage] stop_max_failure_s after
// it): unset while the daemon runs, set once by the stop, read by the StorageRetry of every
// thread. A failure past it throws StorageOutage whatever the path's own limit, so the drain
// ends (exit 3, what was not committed counted) before systemd's TimeoutStopSec kills it.
class StopDeadline {
 public:
  using Clock = std::chrono::steady_clock;
  // From now on, `bound_s` from now.
  void start(double bound_s);
  // time_point::max() while unset.
  Clock::time_point at() const { return Clock::time_point(Clock::duration(at_.load())); }
  double bound_s() const { return bound_s_.load(); }

 private:
  std::atomic<double> bound_s_{0.0};
  std::atomic<Clock::rep> at_{Clock::duration::max().count()};
};

// One storage path's retry state; used by one thread (the worker's commit, its duplicate
// check, the refit thread each have their own). The health flag is shared through counters.
class StorageRetry {
 public:
  using Clock = std::chrono::steady_clock;
  static constexpr double kFirstBackoff_s = 0.05;
  static constexpr double kMaxBackoff_s = 2.0;

  // `what` names the path in the log ("commit", "duplicate check", "refit"); `limit_key` the
  // [storage] key max_failure_s came from (DaemonConfig::storage_max_failure_key()); `stop`
  // the daemon's (nullptr: none).
  StorageRetry(std::string what, double max_failure_s, DaemonCounters& counters,
               std::string limit_key = "max_failure_s", const StopDeadline* stop = nullptr);
  ~StorageRetry();
  StorageRetry(const StorageRetry&) = delete;
  StorageRetry& operator=(const StorageRetry&) = delete;

  // Records a failed attempt (logged, counted) and schedules the next one. Throws
  // StorageOutage when `e` is permanent, the path has now failed for max_failure_s, or the
  // stop's deadline has passed.
  void failed(const storage::StorageError& e);
  // Records a successful attempt: ends the outage (logged with its length).
  void succeeded();
  // Call before each attempt: counted as a retry when the path is failing.
  void attempting();

  bool failing() const { return failing_; }
  // No failure pending, or its backoff has elapsed.
  bool due(Clock::time_point now = Clock::now()) const { return !failing_ || now >= next_; }
  Clock::time_point next_attempt() const { return next_; }

  // Runs `op` until it succeeds, sleeping through the backoff; throws StorageOutage as above.
  template <typename Op>
  auto run_blocking(Op&& op) {
    for (;;) {
      if (failing_) {
        sleep_until(next_);
        attempting();
      }
      try {
        if constexpr (std::is_void_v<decltype(op())>) {
          op();
          succeeded();
          return;
        } else {
          auto result = op();
          succeeded();
          return result;
        }
      } catch (const storage::StorageError& e) {
        failed(e);
      }
    }
  }

 private:
  static void sleep_until(Clock::time_point t);

  std::string what_;
  double max_failure_s_;
  std::string limit_key_;
  DaemonCounters& counters_;
  const StopDeadline* stop_;
  bool failing_ = false;
  Clock::time_point since_{};
  Clock::time_point next_{};
  double backoff_s_ = kFirstBackoff_s;
  int64_t attempts_failed_ = 0;
};

}  // namespace magcal
