#include "service/daemon/ops/health.hpp"

#include <algorithm>
#include <cmath>

#include <fmt/format.h>

#include "pipeline/time_utc.hpp"

namespace magcal {

const char* to_string(RejectReason r) {
  switch (r) {
    case RejectReason::kDecodeError:
      return "decode_error";
    case RejectReason::kWrongType:
      return "wrong_type";
    case RejectReason::kNonFinite:
      return "non_finite";
    case RejectReason::kBadAttitude:
      return "bad_attitude";
    case RejectReason::kBatchSatMismatch:
      return "batch_sat_mismatch";
    case RejectReason::kInvalidSatId:
      return "invalid_sat_id";
    case RejectReason::kUnknownSpacecraft:
      return "unknown_spacecraft";
    case RejectReason::kOutOfRange:
      return "out_of_range";
    case RejectReason::kAbsurdPosition:
      return "absurd_position";
    case RejectReason::kNoReference:
      return "no_reference";
    case RejectReason::kReferenceFailed:
      return "reference_failed";
    case RejectReason::kOlderThanWindow:
      return "older_than_window";
    case RejectReason::kDuplicate:
      return "duplicate";
    case RejectReason::kFutureTime:
      return "future_time";
    case RejectReason::kTimeOutOfRange:
      return "time_out_of_range";
    case RejectReason::kTimeJump:
      return "time_jump";
    case RejectReason::kJumpUnconfirmed:
      return "time_jump_unconfirmed";
    case RejectReason::kStorageError:
      return "storage_error";
    case RejectReason::kZeroVector:
      return "zero_vector";
    case RejectReason::kCount:
      break;
  }
  return "unknown";
}

void SpacecraftCounters::count_refit(RefitVerdict verdict, int64_t result_utime) {
  switch (verdict) {
    case RefitVerdict::kAccepted:
      refits_accepted.fetch_add(1, std::memory_order_relaxed);
      last_refit_success_utime.store(result_utime, std::memory_order_relaxed);
      break;
    case RefitVerdict::kRejected:
      refits_rejected.fetch_add(1, std::memory_order_relaxed);
      break;
    case RefitVerdict::kError:
      refits_error.fetch_add(1, std::memory_order_relaxed);
      break;
  }
}

SpacecraftCounters& SpacecraftCounterTable::spacecraft(const std::string& sat_id) {
  std::lock_guard lock(mutex_);
  if (const auto it = by_sat_.find(sat_id); it != by_sat_.end()) return *it->second;
  const std::string label = by_sat_.size() >= kMaxSpacecraft ? kOther : sat_id;
  if (const auto it = by_sat_.find(label); it != by_sat_.end()) return *it->second;
  auto c = std::make_unique<SpacecraftCounters>();
  c->sat_label = label;
  return *by_sat_.emplace(label, std::move(c)).first->second;
}

void SpacecraftCounterTable::for_each(
    const std::function<void(const SpacecraftCounters&)>& visit) const {
  std::lock_guard lock(mutex_);
  for (const auto& [sat, counters] : by_sat_) visit(*counters);
}

void CommitLatencyHistogram::observe(double seconds) {
  const auto bucket =
      static_cast<size_t>(std::lower_bound(kUpperBounds_s.begin(), kUpperBounds_s.end(), seconds) -
                          kUpperBounds_s.begin());
  counts_[bucket].fetch_add(1, std::memory_order_relaxed);
  sum_ns_.fetch_add(static_cast<int64_t>(std::llround(seconds * 1e9)), std::memory_order_relaxed);
}

std::array<int64_t, CommitLatencyHistogram::kBuckets> CommitLatencyHistogram::bucket_counts()
    const {
  std::array<int64_t, kBuckets> out{};
  for (size_t i = 0; i < kBuckets; ++i) out[i] = counts_[i].load(std::memory_order_relaxed);
  return out;
}

double CommitLatencyHistogram::sum_s() const {
  return static_cast<double>(sum_ns_.load(std::memory_order_relaxed)) * 1e-9;
}

int64_t DaemonCounters::rejected_total() const {
  int64_t sum = 0;
  for (const auto& r : rejected) sum += r.load(std::memory_order_relaxed);
  return sum;
}

void DaemonCounters::storage_path_failing() {
  if (storage_failing_paths.fetch_add(1) == 0) {
    storage_failing_since_utime.store(now_utime());
  }
}

void DaemonCounters::storage_path_recovered() {
  if (storage_failing_paths.fetch_sub(1) == 1) storage_failing_since_utime.store(0);
}

void DaemonCounters::set_last_refit(const std::string& sat_id, int64_t utime) {
  std::lock_guard lock(sat_mutex_);
  last_refit_sat_id_ = sat_id;
  last_refit_utime.store(utime, std::memory_order_relaxed);
}

std::string DaemonCounters::last_refit_sat_id() const {
  std::lock_guard lock(sat_mutex_);
  return last_refit_sat_id_;
}

daemon_status_t make_status_message(const DaemonCounters& c, const QueueGauge& q, int64_t now_utime,
                                    int64_t uptime_s) {
  daemon_status_t s{};
  s.utime = now_utime;
  s.version = MAGCAL_VERSION;
  s.uptime_s = uptime_s;
  s.received = c.received.load(std::memory_order_relaxed);
  s.stored = c.stored.load(std::memory_order_relaxed);
  // Every reason is listed, zeros included, so a reader sees the full vocabulary.
  for (int i = 0; i < kRejectReasonCount; ++i) {
    s.rejected_reason.emplace_back(to_string(static_cast<RejectReason>(i)));
    s.rejected_count.push_back(c.rejected_count(static_cast<RejectReason>(i)));
  }
  s.n_reasons = static_cast<int32_t>(s.rejected_reason.size());
  s.rejected = c.rejected_total();
  s.missing_by_seq = c.missing_by_seq.load(std::memory_order_relaxed);
  s.queue_overflow = q.overflow;
  s.queue_depth = static_cast<int32_t>(q.depth);
  s.queue_capacity = static_cast<int32_t>(q.capacity);
  s.n_spacecraft = c.n_spacecraft.load(std::memory_order_relaxed);
  s.refits_run = c.refits_run.load(std::memory_order_relaxed);
  s.refits_failed = c.refits_failed.load(std::memory_order_relaxed);
  s.last_refit_utime = c.last_refit_utime.load(std::memory_order_relaxed);
  s.last_refit_sat_id = c.last_refit_sat_id();
  s.storage_healthy = c.storage_healthy();
  s.storage_pending = c.storage_pending.load(std::memory_order_relaxed);
  s.storage_failures = c.storage_failures.load(std::memory_order_relaxed);
  s.storage_retries = c.storage_retries.load(std::memory_order_relaxed);
  return s;
}

std::string format_status_line(const daemon_status_t& s) {
  std::string reasons;
  for (int i = 0; i < s.n_reasons; ++i) {
    if (s.rejected_count[static_cast<size_t>(i)] == 0) continue;
    reasons += fmt::format(" {}={}", s.rejected_reason[static_cast<size_t>(i)],
                           s.rejected_count[static_cast<size_t>(i)]);
  }
  return fmt::format(
      "status: received={} stored={} rejected={}{}{} missing_by_seq={} queue={}/{} "
      "overflow={} spacecraft={} refits={} (failed {}) storage={} (pending {}, failures {}, "
      "retries {})",
      s.received, s.stored, s.rejected, reasons.empty() ? "" : " (",
      reasons.empty() ? "" : reasons.substr(1) + ")", s.missing_by_seq, s.queue_depth,
      s.queue_capacity, s.queue_overflow, s.n_spacecraft, s.refits_run, s.refits_failed,
      s.storage_healthy ? "healthy" : "FAILING", s.storage_pending, s.storage_failures,
      s.storage_retries);
}

}  // namespace magcal
