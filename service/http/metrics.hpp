// Prometheus metrics of magcal (design.md "Operations surface"; the names are a contract that
// dashboards and deploy/ alert rules rely on). Built with prometheus-cpp's core registry and
// serialized by prometheus::TextSerializer (text exposition format 0.0.4), never by hand.
//
//   magcal_samples_received_total{sat}      samples received (decoded frames; an undecodable
//                                           frame counts 1 under sat="", as do samples with
//                                           an empty spacecraft id)
//   magcal_samples_stored_total{sat}        samples committed to the database
//   magcal_samples_rejected_total{reason}   rejected samples per reason (health.hpp's names)
//   magcal_samples_missing_total{sat}       gaps in `seq` (dropped before the socket)
//   magcal_queue_depth                      samples in the receive -> worker queue
//   magcal_queue_overflow_total             samples dropped because the queue was full
//   magcal_storage_commit_seconds           histogram: each sample-batch transaction, including
//                                           failed ones (a lock wait shows as a long commit),
//                                           whichever database (SQLite or PostgreSQL)
//   magcal_sqlite_commit_seconds            the same histogram under design.md's first name,
//                                           kept for dashboards and the shipped alert rule
//                                           (deprecated: it is emitted on PostgreSQL too)
//   magcal_ukf_bias_nT{sat,axis}            bias of the newest stored UKF snapshot (axis x|y|z)
//   magcal_ukf_bias_sigma_nT{sat,axis}      its 1-sigma (2000 nT while the filter collects for
//                                           its start: condition alerts on it, or on the next)
//   magcal_ukf_snapshot_accepted{sat}       1 when that snapshot passed the acceptance gates
//   magcal_refits_total{sat,verdict}        refits run: verdict accepted | rejected | error
//                                           (error: no result, e.g. the fit failed to read)
//   magcal_last_refit_success_timestamp_seconds{sat}  data time (s since 1970) of the newest
//                                           accepted refit (its t_ref; = wall time when live)
//   magcal_storage_healthy                  1, or 0 while a storage operation is failing and
//                                           being retried (then /-/healthy answers 503 on
//                                           SQLite; on PostgreSQL /-/ready does)
//   magcal_storage_failing_seconds          how long storage has been failing (0: it works)
//   magcal_storage_pending_samples          received samples held in memory, not committed
//   magcal_samples_spilled_total            samples written to the spill file (PostgreSQL
//                                           outages: service/daemon/intake/sample_spill.hpp)
//   magcal_spill_samples                    samples in the spill file, not committed yet (an
//                                           earlier run's too)
//   magcal_spill_bytes                      size of the spill file
//   magcal_spill_recovered_samples_total    samples committed at start from a spill file an
//                                           earlier run left (received by that run)
//   magcal_spill_dropped_records_total      records of such a file cut off as torn or corrupt
//   magcal_build_info{version}              1
//   magcal_spacecraft_owned{sat}            1 while this daemon holds the spacecraft's lease
//   magcal_leases_lost_total                leases lost to another daemon (stalled, cut off)
//   magcal_fleet_settings_mismatch          live stations whose result-affecting settings
//                                           differ from this daemon's (0: the fleet agrees;
//                                           service/io/station_settings.hpp)
//   magcal_station_info{station}            1, the daemon's [station] id (design.md "Fleet"):
//                                           an info metric, joined in queries
//                                           (`* on(instance) group_left(station)`) rather than
//                                           a label on every series, which would rename every
//                                           series when a station is renamed
//
// `magcal serve` adds magcal_window_samples{sat} and magcal_window_samples_by_station{sat,
// station} (database_metrics_text below).
//
// Spacecraft series are as many as the daemon's counter table holds (capped there: corrupt or
// hostile ids must not grow it without bound; later ids share sat="(other)").
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::http {

// The daemon's /metrics. The daemon keeps its counters once, in its own types
// (service/daemon/ops/health.hpp); this collector reads them at scrape time through a source the
// daemon sets, so no sample is counted twice and the ingest path knows no metrics library.
class DaemonMetrics {
 public:
  // What the daemon counted, at one scrape. Counters only move forward here.
  struct SpacecraftTotals {
    std::string sat_label;
    int64_t received = 0;
    int64_t stored = 0;
    int64_t missing = 0;
    int64_t refits_accepted = 0;
    int64_t refits_rejected = 0;
    int64_t refits_error = 0;
    int64_t refits_claimed_elsewhere = 0;
    bool owned = false;                    // this daemon holds its lease
    int64_t last_refit_success_utime = 0;  // 0 = none yet (no series: never a made-up time)
    bool has_ukf_snapshot = false;         // no series before the first snapshot
    std::array<double, 3> ukf_bias_nT{};
    std::array<double, 3> ukf_bias_sigma_nT{};
    bool ukf_accepted = false;
  };
  struct Totals {
    std::vector<std::pair<std::string, int64_t>> rejected_by_reason;
    int64_t queue_depth = 0;
    int64_t queue_overflow = 0;
    bool storage_healthy = true;
    double storage_failing_s = 0.0;
    int64_t storage_pending = 0;
    int64_t spilled = 0;
    int64_t spill_held = 0;
    int64_t spill_bytes = 0;
    int64_t spill_recovered = 0;
    int64_t spill_dropped = 0;
    int64_t leases_lost = 0;
    int64_t fleet_settings_mismatch = 0;
    std::vector<SpacecraftTotals> spacecraft;
    // Commit latency: one count per bucket of the constructor's bounds plus +Inf (not
    // cumulative), and the sum of the observations, s. Empty = none observed.
    std::vector<int64_t> commit_bucket_counts;
    double commit_sum_s = 0.0;
  };

  // station: the daemon's [station] id. commit_bucket_bounds_s: the upper bounds of the commit
  // latency histogram (ascending).
  DaemonMetrics(const std::string& version, const std::string& station,
                std::vector<double> commit_bucket_bounds_s);
  ~DaemonMetrics();
  DaemonMetrics(const DaemonMetrics&) = delete;
  DaemonMetrics& operator=(const DaemonMetrics&) = delete;

  void set_totals_source(std::function<Totals()> source);

  // The exposition text (TextSerializer over the registry). Thread-safe.
  std::string text();

 private:
  struct Impl;  // the registry and its series (prometheus-cpp stays out of this header)
  std::unique_ptr<Impl> impl_;
};

// What a database alone knows, for `magcal serve` (same names and types as the daemon's):
// magcal_window_samples{sat} = samples stored in the window of `window_utime` (us) ending at the
// spacecraft's newest sample, as `magcal status` counts them (retention keeps a little more),
// magcal_window_samples_by_station{sat,station} = the same by the station that stored them
// (station="" for samples stored without one, before schema 7; one query per spacecraft for
// both), the newest UKF snapshot's bias, sigma and verdict, refits_total{sat,verdict} from the
// history (accepted | rejected; errors leave no history row), the newest accepted refit's time, and
// build_info. Counters that only a running daemon knows (received, rejected, missing, queue,
// commit latency) are absent. `db` is read-only or not: this never writes. Throws
// storage::StorageError.
std::string database_metrics_text(storage::Connection& db, const std::string& version,
                                  int64_t window_utime);

}  // namespace magcal::http
