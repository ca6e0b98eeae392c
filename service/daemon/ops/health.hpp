// The daemon's counters and its health report (daemon_status_t on MAGCAL_STATUS; the same
// numbers in the log at a lower rate).
//
// Invariant the tests check: received = stored + rejected (all reasons) + queue_overflow
// + samples still in flight (queue, uncommitted batch and spill file). A daemon that stops because
// storage stays broken counts every received sample it could not commit as storage_error.
//
// Storage health: a storage operation that fails is kept and retried with backoff
// (service/daemon/intake/storage_retry.hpp); while any is failing, storage_healthy() is false (the
// status message says so, and /-/healthy answers 503 on SQLite; on PostgreSQL /-/ready does, while
// /-/healthy stays 200: service/daemon/ops/health_probes.hpp). An undecodable frame counts as one
// received and one rejected (decode_error / wrong_type): its sample count is unknowable.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <unordered_map>

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
  kZeroVector,         // b_sensor_nT exactly (0, 0, 0): a sensor dropout, no measurement
  kCount
};
constexpr int kRejectReasonCount = static_cast<int>(RejectReason::kCount);
const char* to_string(RejectReason r);  // "decode_error", "wrong_type", ...

// One spacecraft's counters. The daemon keeps them once; /metrics (service/http/metrics.hpp)
// reads them at scrape time, so the per-sample path is one relaxed atomic add and knows no
// metrics library.
struct SpacecraftCounters {
  std::string sat_label;  // the spacecraft id, or SpacecraftCounterTable::kOther past the cap
  std::atomic<int64_t> received{0};
  std::atomic<int64_t> stored{0};
  std::atomic<int64_t> missing{0};  // implied by gaps in seq
  std::atomic<int64_t> refits_accepted{0};
  std::atomic<int64_t> refits_rejected{0};
  std::atomic<int64_t> refits_error{0};  // a refit that produced no result
  // Refits due here that another station had claimed (design.md "Fleet"): run there.
  std::atomic<int64_t> refits_claimed_elsewhere{0};
  // Data time of the newest accepted refit (its t_ref), 0 = none.
  std::atomic<int64_t> last_refit_success_utime{0};
  // This daemon holds its lease: runs its UKF and refits (design.md "Fleet").
  std::atomic<bool> owned{false};

  // The newest stored UKF snapshot: bias and its 1-sigma (nT, sensor frame), and its verdict.
  struct UkfSnapshot {
    bool present = false;
    std::array<double, 3> bias_nT{};
    std::array<double, 3> bias_sigma_nT{};
    bool accepted = false;
  };
  void set_ukf_snapshot(const UkfSnapshot& s) {
    std::lock_guard lock(snapshot_mutex_);
    ukf_ = s;
    ukf_.present = true;
  }
  UkfSnapshot ukf_snapshot() const {
    std::lock_guard lock(snapshot_mutex_);
    return ukf_;
  }

  enum class RefitVerdict { kAccepted, kRejected, kError };
  // A refit that ran; an accepted one also sets the last-success time (its result's utime).
  void count_refit(RefitVerdict verdict, int64_t result_utime);

 private:
  mutable std::mutex snapshot_mutex_;  // a snapshot is 7 values, written once a minute
  UkfSnapshot ukf_;
};

// The spacecraft counters by id. Thread-safe; a reference stays valid for the life of the table,
// so threads cache it and count without a lookup. Corrupt or hostile ids must not grow it without
// bound: past kMaxSpacecraft distinct ids, later ones share the entry kOther.
class SpacecraftCounterTable {
 public:
  static constexpr size_t kMaxSpacecraft = 4096;
  static constexpr const char* kOther = "(other)";

  SpacecraftCounters& spacecraft(const std::string& sat_id);
  // Calls visit(counters) for every entry, in no particular order, under the table's lock
  // (visit must not call back into the table).
  void for_each(const std::function<void(const SpacecraftCounters&)>& visit) const;

 private:
  mutable std::mutex mutex_;
  std::unordered_map<std::string, std::unique_ptr<SpacecraftCounters>> by_sat_;
};

// Duration of each sample-batch transaction (failed ones too: a lock wait shows as a long
// commit), in fixed buckets so that the daemon counts it lock-free and /metrics exposes it as
// the histogram magcal_storage_commit_seconds.
class CommitLatencyHistogram {
 public:
  // Upper bounds, s: 100 µs (a small batch in WAL mode) to 10 s (past SQLite's default busy
  // timeout of 5 s, so lock waits land in a finite bucket). One more bucket counts +Inf.
  static constexpr std::array<double, 16> kUpperBounds_s{
      0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025,
      0.05,   0.1,     0.25,   0.5,   1.0,    2.5,   5.0,  10.0};
  static constexpr size_t kBuckets = kUpperBounds_s.size() + 1;

  void observe(double seconds);
  // Per-bucket counts (not cumulative; the last is +Inf) and the sum of the observations, s.
  std::array<int64_t, kBuckets> bucket_counts() const;
  double sum_s() const;

 private:
  std::array<std::atomic<int64_t>, kBuckets> counts_{};
  std::atomic<int64_t> sum_ns_{0};
};

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
  // Storage (service/daemon/intake/storage_retry.hpp): paths failing now, failed attempts, retries,
  // and the samples the worker holds uncommitted (a gauge it sets).
  std::atomic<int32_t> storage_failing_paths{0};
  std::atomic<int64_t> storage_failures{0};
  std::atomic<int64_t> storage_retries{0};
  std::atomic<int64_t> storage_pending{0};
  // Spacecraft leases lost to another daemon (this one stalled past the lease, or the database
  // was unreachable for that long): their filters stopped here and went on there.
  std::atomic<int64_t> leases_lost{0};
  // Live stations of the fleet whose result-affecting settings differ from this one's (a gauge,
  // FleetSettingsWatch).
  std::atomic<int32_t> fleet_settings_mismatch{0};
  // Wall time (utime) since when some storage path has been failing; 0 while none is.
  std::atomic<int64_t> storage_failing_since_utime{0};
  // The spill file (PostgreSQL outages, service/daemon/intake/sample_spill.hpp): samples written to
  // it, this run's samples it holds now (not committed yet: in flight, like storage_pending), an
  // earlier run's it holds now (received and counted by that run; committed first once the
  // database answers) and its size; samples committed at start from a file an earlier run left,
  // and records of such a file dropped as torn or corrupt (a crash during a write).
  std::atomic<int64_t> spilled{0};
  std::atomic<int64_t> spill_held{0};
  std::atomic<int64_t> spill_held_earlier{0};
  std::atomic<int64_t> spill_bytes{0};
  std::atomic<int64_t> spill_recovered{0};
  std::atomic<int64_t> spill_dropped{0};
  SpacecraftCounterTable spacecraft;
  CommitLatencyHistogram commit_seconds;

  bool storage_healthy() const { return storage_failing_paths.load() == 0; }
  // A storage path starts failing / works again (StorageRetry).
  void storage_path_failing();
  void storage_path_recovered();

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
