// The daemon's counters and its health report (daemon_status_t on MAGCAL_STATUS; the same
// numbers in the log at a lower rate).
//
// Invariant the tests check: received = stored + rejected (all reasons) + queue_overflow
// + samples still in flight (queue and uncommitted batch). A daemon that stops because storage
// stays broken counts every received sample it could not commit as storage_error.
//
// Storage health: a storage operation that fails is kept and retried with backoff
// (service/daemon/storage_retry.hpp); while any is failing, storage_healthy() is false (the status
// message says so, and /-/healthy will answer 503). An undecodable frame counts as one
// received and one rejected (decode_error / wrong_type): its sample count is unknowable.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <mutex>
#include <string>

#include "schemas/magcal_messages.hpp"

namespace magcal {

enum class RejectReason : int {
  kDecodeError = 0,    // truncated or corrupt frame of our type
  kWrongType,          // fingerprint of another type (or none we know)
  kNonFinite,          // NaN/Inf in b_sensor_nT or in a field whose has_* flag is set
  kBadAttitude,        // has_attitude with a quaternion far from unit norm
  kBatchSatMismatch,   // a batch's sample names another spacecraft than the batch
  kInvalidSatId,       // empty spacecraft id
  kUnknownSpacecraft,  // not on the configured whitelist
  kOutOfRange,         // |component| beyond [sensor] range_nT
  kAbsurdPosition,     // |r_ecef| not within 6400-8000 km
  kNoReference,        // neither h_body_nT nor a position to compute IGRF from
  kReferenceFailed,    // IGRF refused the date (outside the coefficient file's validity)
  kOlderThanWindow,    // older than the spacecraft's newest sample minus the window
  kDuplicate,          // (sat_id, utime) already received
  kFutureTime,         // more than [ingest] max_future_s ahead of the wall clock at receipt
  kTimeOutOfRange,     // utime outside 1990-01-01 .. 2100-01-01 (corrupt time tag)
  kTimeJump,           // held past the stream's newest time, then contradicted by the stream
  kJumpUnconfirmed,    // still held (uncorroborated) at shutdown
  kStorageError,       // not committed: storage stayed broken until magcald stopped (logged)
  kCount
};
constexpr int kRejectReasonCount = static_cast<int>(RejectReason::kCount);
const char* to_string(RejectReason r);  // "decode_error", "wrong_type", ...

// Thread-safe counters (relaxed atomics: they are statistics, not synchronisation).
struct DaemonCounters {
  std::atomic<int64_t> received{0};
  std::atomic<int64_t> stored{0};
  std::array<std::atomic<int64_t>, kRejectReasonCount> rejected{};
  std::atomic<int64_t> missing_by_seq{0};
  std::atomic<int64_t> ukf_updates{0};
  std::atomic<int64_t> snapshots{0};
  std::atomic<int64_t> refits_run{0};
  std::atomic<int64_t> refits_failed{0};
  std::atomic<int64_t> refits_accepted{0};
  std::atomic<int64_t> last_refit_utime{0};
  std::atomic<int32_t> n_spacecraft{0};
  // Storage (service/daemon/storage_retry.hpp): paths failing now, failed attempts, retries, and
  // the samples the worker holds uncommitted (a gauge it sets).
  std::atomic<int32_t> storage_failing_paths{0};
  std::atomic<int64_t> storage_failures{0};
  std::atomic<int64_t> storage_retries{0};
  std::atomic<int64_t> storage_pending{0};

  bool storage_healthy() const { return storage_failing_paths.load() == 0; }

  void reject(RejectReason r, int64_t n = 1) {
    rejected[static_cast<int>(r)].fetch_add(n, std::memory_order_relaxed);
  }
  int64_t rejected_total() const;
  int64_t rejected_count(RejectReason r) const {
    return rejected[static_cast<int>(r)].load(std::memory_order_relaxed);
  }
  void set_last_refit(const std::string& sat_id, int64_t utime);
  std::string last_refit_sat_id() const;

 private:
  mutable std::mutex sat_mutex_;
  std::string last_refit_sat_id_;
};

struct QueueGauge {
  int64_t depth = 0;
  int64_t capacity = 0;
  int64_t overflow = 0;
};

// The status message for the current counters.
daemon_status_t make_status_message(const DaemonCounters& c, const QueueGauge& q, int64_t now_utime,
                                    int64_t uptime_s);
// One log line with the same numbers ("received=... stored=... rejected=... (reason=n ...)").
std::string format_status_line(const daemon_status_t& s);

}  // namespace magcal
