// Prometheus metrics of magcal (design.md "Operations surface"; the names are a contract that
// dashboards and deploy/ alert rules rely on). Built with prometheus-cpp's core registry and
// serialized by prometheus::TextSerializer (text exposition format 0.0.4), never by hand.
//
//   magcal_samples_received_total{sat}      samples received (decoded frames; an undecodable
//                                           frame counts 1 under sat="", as do samples with
//                                           an empty spacecraft id)
//   magcal_samples_stored_total{sat}        samples committed to SQLite
//   magcal_samples_rejected_total{reason}   rejected samples per reason (health.hpp's names)
//   magcal_samples_missing_total{sat}       gaps in `seq` (dropped before the socket)
//   magcal_queue_depth                      samples in the receive -> worker queue
//   magcal_queue_overflow_total             samples dropped because the queue was full
//   magcal_sqlite_commit_seconds            histogram: each sample-batch transaction, including
//                                           failed ones (a lock wait shows as a long commit)
//   magcal_ukf_bias_nT{sat,axis}            bias of the newest stored UKF snapshot (axis x|y|z)
//   magcal_ukf_bias_sigma_nT{sat,axis}      its 1-sigma (2000 nT while the filter collects for
//                                           its start: condition alerts on it, or on the next)
//   magcal_ukf_snapshot_accepted{sat}       1 when that snapshot passed the acceptance gates
//   magcal_refits_total{sat,verdict}        refits run: verdict accepted | rejected | error
//                                           (error: no result, e.g. the fit failed to read)
//   magcal_last_refit_success_timestamp_seconds{sat}  data time (s since 1970) of the newest
//                                           accepted refit (its t_ref; = wall time when live)
//   magcal_storage_healthy                  1, or 0 while a storage operation is failing and
//                                           being retried (then /-/healthy answers 503)
//   magcal_build_info{version}              1
//
// Spacecraft series are capped at kMaxSpacecraftSeries distinct ids (corrupt or hostile ids
// must not grow the registry without bound); later ids share sat="(other)".
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <unordered_map>

#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include "storage/database.hpp"

namespace magcal::http {

// One spacecraft's series. References stay valid for the life of the DaemonMetrics, so the
// daemon caches a pointer per spacecraft and its per-sample path does no label lookup and no
// allocation (prometheus-cpp's Counter::Increment is an atomic add).
struct SpacecraftMetrics {
  std::string sat_label;
  prometheus::Counter* received = nullptr;
  prometheus::Counter* stored = nullptr;
  prometheus::Counter* missing = nullptr;
  // Created by the first snapshot / accepted refit (written by one thread: the worker / the
  // refit thread).
  std::array<prometheus::Gauge*, 3> ukf_bias_nT{};
  std::array<prometheus::Gauge*, 3> ukf_bias_sigma_nT{};
  prometheus::Gauge* ukf_snapshot_accepted = nullptr;
  prometheus::Counter* refits_accepted = nullptr;
  prometheus::Counter* refits_rejected = nullptr;
  prometheus::Counter* refits_error = nullptr;
  prometheus::Gauge* last_refit_success_s = nullptr;
};

// Bucket upper bounds of magcal_sqlite_commit_seconds: 100 µs (a small batch in WAL mode)
// to 10 s (past the default busy timeout of 5 s, so lock waits land in a finite bucket).
const std::vector<double>& sqlite_commit_buckets_s();

class DaemonMetrics {
 public:
  static constexpr size_t kMaxSpacecraftSeries = 4096;
  static constexpr const char* kOtherSpacecraft = "(other)";

  explicit DaemonMetrics(const std::string& version);
  DaemonMetrics(const DaemonMetrics&) = delete;
  DaemonMetrics& operator=(const DaemonMetrics&) = delete;

  // Thread-safe; the same reference for the same id, for the life of this object.
  SpacecraftMetrics& spacecraft(const std::string& sat_id);

  // Thread-safe (atomics inside prometheus-cpp).
  void observe_commit_seconds(double seconds) { commit_seconds_->Observe(seconds); }
  // A stored UKF snapshot (bias, its 1-sigma, nT) and whether it was accepted.
  // From one thread per spacecraft (the worker).
  void set_ukf(SpacecraftMetrics& m, const std::array<double, 3>& bias_nT,
               const std::array<double, 3>& sigma_nT, bool accepted);
  enum class RefitVerdict { kAccepted, kRejected, kError };
  // From one thread (the refit thread): a refit that ran; an accepted one also sets the
  // last-success time (its result's utime).
  void count_refit(SpacecraftMetrics& m, RefitVerdict verdict, int64_t result_utime);

  // Totals the daemon already keeps elsewhere (health.hpp's atomics), brought in at scrape time
  // by the hook so the ingest path counts them once. Counters only move forward here.
  struct Totals {
    std::vector<std::pair<std::string, int64_t>> rejected_by_reason;
    int64_t queue_depth = 0;
    int64_t queue_overflow = 0;
    bool storage_healthy = true;
  };
  void set_totals_source(std::function<Totals()> source);

  // The exposition text (TextSerializer over the registry). Thread-safe.
  std::string text();

  prometheus::Registry& registry() { return *registry_; }

 private:
  void apply_totals(const Totals& t);

  std::shared_ptr<prometheus::Registry> registry_;
  prometheus::Family<prometheus::Counter>* received_;
  prometheus::Family<prometheus::Counter>* stored_;
  prometheus::Family<prometheus::Counter>* rejected_;
  prometheus::Family<prometheus::Counter>* missing_;
  prometheus::Gauge* queue_depth_;
  prometheus::Counter* queue_overflow_;
  prometheus::Histogram* commit_seconds_;
  prometheus::Family<prometheus::Gauge>* ukf_bias_;
  prometheus::Family<prometheus::Gauge>* ukf_sigma_;
  prometheus::Family<prometheus::Gauge>* ukf_accepted_;
  prometheus::Family<prometheus::Counter>* refits_;
  prometheus::Family<prometheus::Gauge>* last_refit_success_;
  prometheus::Gauge* storage_healthy_;

  std::mutex mutex_;  // the spacecraft map, the totals source and scrapes
  std::unordered_map<std::string, std::unique_ptr<SpacecraftMetrics>> spacecraft_;
  std::function<Totals()> totals_source_;
  std::unordered_map<std::string, prometheus::Counter*> rejected_by_reason_;
};

// What a database alone knows, for `magcal serve` (same names and types as the daemon's):
// samples_stored_total{sat} = samples stored now (the window: retention deletes older ones),
// the newest UKF snapshot's bias, sigma and verdict, refits_total{sat,verdict} from the history
// (accepted | rejected; errors leave no history row), the newest accepted refit's time, and
// build_info. Counters that only a running daemon knows (received, rejected, missing, queue,
// commit latency) are absent. `db` is read-only or not: this never writes. Throws
// storage::StorageError.
std::string database_metrics_text(storage::Database& db, const std::string& version);

}  // namespace magcal::http
