#include "service/daemon/intake/storage_retry.hpp"

#include <algorithm>
#include <thread>

#include <fmt/format.h>
#include <spdlog/spdlog.h>

namespace magcal {
namespace {

// "busy, SQLite code 5", "unavailable, SQLSTATE 08006": the backend-neutral condition, then the
// engine's own code.
std::string describe(const storage::StorageError& e) {
  std::string out = storage::to_string(e.condition());
  if (const std::string code = e.code(); !code.empty()) out += ", " + code;
  return out;
}

}  // namespace

void StopDeadline::start(double bound_s) {
  bound_s_.store(bound_s);
  at_.store((Clock::now() +
             std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(bound_s)))
                .time_since_epoch()
                .count());
}

StorageRetry::StorageRetry(std::string what, double max_failure_s, DaemonCounters& counters,
                           std::string limit_key, const StopDeadline* stop)
    : what_(std::move(what)),
      max_failure_s_(max_failure_s),
      limit_key_(std::move(limit_key)),
      counters_(counters),
      stop_(stop) {}

StorageRetry::~StorageRetry() {
  if (failing_) counters_.storage_path_recovered();
}

void StorageRetry::sleep_until(Clock::time_point t) {
  std::this_thread::sleep_until(t);
}

void StorageRetry::attempting() {
  if (failing_) counters_.storage_retries.fetch_add(1, std::memory_order_relaxed);
}

void StorageRetry::failed(const storage::StorageError& e) {
  const auto now = Clock::now();
  counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
  if (!failing_) {
    failing_ = true;
    since_ = now;
    backoff_s_ = kFirstBackoff_s;
    attempts_failed_ = 0;
    counters_.storage_path_failing();
  }
  ++attempts_failed_;
  const double failing_s = std::chrono::duration<double>(now - since_).count();
  if (!e.transient()) {
    throw StorageOutage(
        fmt::format("database {}: permanent error ({}): {}", what_, describe(e), e.what()));
  }
  if (failing_s >= max_failure_s_) {
    throw StorageOutage(fmt::format(
        "database {} failed for {:.1f} s ([storage] {} = {}; {} attempts), last error ({}): {}",
        what_, failing_s, limit_key_, max_failure_s_, attempts_failed_, describe(e), e.what()));
  }
  const auto stop_at = stop_ != nullptr ? stop_->at() : Clock::time_point::max();
  if (now >= stop_at) {
    throw StorageOutage(fmt::format(
        "database {} still failing {:.1f} s after the stop ([storage] stop_max_failure_s = {}; "
        "failing for {:.1f} s, {} attempts), last error ({}): {}",
        what_, stop_->bound_s() + std::chrono::duration<double>(now - stop_at).count(),
        stop_->bound_s(), failing_s, attempts_failed_, describe(e), e.what()));
  }
  // One line per doubling of the backoff, then one every 5 attempts (10 s): a live outage stays
  // visible in the log without flooding it.
  if (backoff_s_ < kMaxBackoff_s || attempts_failed_ % 5 == 0) {
    spdlog::error(
        "database {} failed ({}; failing for {:.1f} s of {} {}), kept, retry in {:.2f} s: {}",
        what_, describe(e), failing_s, limit_key_, max_failure_s_, backoff_s_, e.what());
  }
  // Never retry later than the give-up time, so an outage (or a stop) ends on time.
  const double wait_s = std::min(backoff_s_, std::max(0.0, max_failure_s_ - failing_s));
  next_ = std::min(
      now + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(wait_s)),
      stop_at);
  backoff_s_ = std::min(2.0 * backoff_s_, kMaxBackoff_s);
}

void StorageRetry::succeeded() {
  if (!failing_) return;
  failing_ = false;
  counters_.storage_path_recovered();
  spdlog::warn("database {} works again after {:.1f} s ({} failed attempts)", what_,
               std::chrono::duration<double>(Clock::now() - since_).count(), attempts_failed_);
}

}  // namespace magcal
