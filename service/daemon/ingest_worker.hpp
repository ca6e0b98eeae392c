// The daemon's worker (design.md "Daemon data flow" and "Fleet"). Two parts with one job each,
// on one thread and one database connection:
//
// Receive and store (every station): for every decoded sample
//   validate (sample_validator.hpp, then the spacecraft's time base, older_than_window /
//   duplicate against the pending batch and the store) -> reference field -> pending row;
// pending rows are committed in one transaction per batch (commit_every_samples or
// commit_every_ms, whichever first) with the station id; retention runs in small transactions
// after commits.
//
// Track (the spacecraft's owner only): the daemon holding a spacecraft's lease (LeaseStore,
// maintain_leases() every [fleet] lease_s / 3; the live daemons share the spacecraft evenly)
// reads back the union of all stations' stored samples in time order, [fleet] reorder_delay_s
// of data time behind the newest (track_union()), and runs them through the UKF: snapshots
// every `snapshot_every_s` of DATA time (history row + calibration_t), and the refit triggers
// (with the data clock, each spacecraft on its own data time; early refits). Snapshot rows and
// the filter states of the spacecraft that had a snapshot or a re-anchor are committed
// together, fenced by the lease (a daemon that lost it writes nothing). The filter only ever
// takes committed samples, so a stored state never includes a sample that could come again.
//
// Storage faults (service/daemon/storage_retry.hpp): a failed commit keeps its samples and
// snapshots pending and is retried with backoff (snapshots are published only once stored); the
// caller stops feeding process() while backlogged() (pending at [storage] max_pending_samples). The
// duplicate check retries in place. Storage broken for [storage] max_failure_s (pg_max_failure_s
// on PostgreSQL), or a permanent error, throws StorageOutage out of process() / commit_if_due() /
// commit() / flush().
//
// PostgreSQL outages (issue 19, "Network faults"): once the pending batch reaches
// max_pending_samples while commits fail, it goes to the spill file (sample_spill.hpp) and
// intake goes on; the file is committed first when the database returns (a slice of at most
// 1 s per commit, the pending batch queued behind it in the file until it is empty), and at
// start when an earlier run left one. Meanwhile the duplicate check does not read the database (the
// insert, which counts duplicates, decides), and refits that fall due wait until everything is
// committed.
//
// Owns its own database connection and everything it touches, so it runs on one thread; the
// only cross-thread entry points are post_reanchor(), owns() and the retention floor.
//
// Restart (restore()), after a SIGTERM or a crash: the receive side comes back from the stored
// windows. Taking a spacecraft over (take_over(): at a restart, or from a daemon that died or
// handed it over): the UKF from its stored state, then the normal reading of the union goes on
// after the state's last sample, with its snapshots and refit triggers, as the previous owner
// would have (snapshots and states are committed together, so none is lost or repeated). An
// accepted refit the stored state was not re-anchored on is applied then. Each data-clock
// schedule resumes after the last scheduled refit that ran to its end, so a refit that was due
// when the owner died runs again (its job claim was given up: RefitJobLog).
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <span>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include "pipeline/calibration_result.hpp"
#include "service/daemon/daemon_config.hpp"
#include "service/daemon/health.hpp"
#include "service/daemon/ingest_queue.hpp"
#include "service/daemon/refit_scheduler.hpp"
#include "service/daemon/sample_spill.hpp"
#include "service/daemon/sample_validator.hpp"
#include "service/daemon/spacecraft_tracker.hpp"
#include "service/daemon/storage_retry.hpp"
#include "service/daemon/throttled_log.hpp"
#include "service/io/reference_field.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/filter_state_store.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

// Another live process beats under this daemon's [station] id: a misuse (two daemons with one
// id would both own the same spacecraft). Ends the daemon (exit 1) with the reason.
struct StationConflict : std::runtime_error {
  using std::runtime_error::runtime_error;
};

class IngestWorker {
 public:
  struct Hooks {
    // A UKF snapshot was committed (publish it).
    std::function<void(const std::string& sat_id, const CalibrationResult&)> on_snapshot;
    // A refit of sat_id's window ending at t_ref is due, and its samples up to t_ref are
    // committed. trigger "scheduled" (data clock: sat_id's own data time passed its scheduled
    // time t_ref), or "first" / "early" (EarlyRefitPlan: its UKF started from data and the
    // stored samples reached min_samples, or grew by [refit] early_growth since, while they span
    // less than window_hours; t_ref is the time of the N-th stored sample, so the window holds
    // exactly N: each refit re-anchors the filter with a covariance from the residuals'
    // structure, hours before the schedule would).
    std::function<void(const std::string& sat_id, int64_t t_ref_utime, const char* trigger)>
        on_refit_due;
  };

  // Opens its own connection to config.storage.db_path (throws storage::StorageError) and, on
  // PostgreSQL, a spill file left behind (throws SpillError). Counts in `counters` (must outlive
  // the worker), per spacecraft too, and times each commit.
  IngestWorker(const DaemonConfig& config, DaemonCounters& counters,
               std::unique_ptr<ReferenceField> field, Hooks hooks);
  ~IngestWorker();

  // Commits a spill file an earlier run left, rebuilds the receive side from the database, then
  // takes the leases this daemon may own (see file comment). Call once before process().
  void restore();

  // Heartbeat, lease renewal, takeovers and handovers (see file comment). commit_if_due() runs
  // it every [fleet] lease_s / 3; public for tests. A storage error is logged and counted; the
  // next round retries (leases not renewed in time are lost, and given up here).
  void maintain_leases();
  // At a clean stop: hands every owned spacecraft back (its state committed first) and ends
  // the heartbeat, so the other daemons take over at once instead of after the lease time.
  void leave_fleet();
  // From any thread: this daemon holds sat_id's lease.
  bool owns(const std::string& sat_id) const;
  // The owner's filters take every stored sample, without the reorder delay (end of a replay,
  // shutdown); their snapshots and refit triggers as usual.
  void track_all_now();

  // Validates and ingests every sample of a decoded frame.
  void process(const IngestItem& item);
  // Commits when the pending batch is full or old enough; call regularly.
  void commit_if_due();
  // Commits pending samples and snapshots now (one transaction), then runs retention. After a
  // failure, a no-op until the retry backoff has elapsed.
  void commit();
  // Commits everything pending, retrying through the backoff until it is stored; throws
  // StorageOutage when storage stays broken (shutdown, and before a data-clock refit).
  void flush();
  // At shutdown: flush(), except that with a spill file (PostgreSQL) while storage fails the
  // pending samples are spilled at once (committed at the next start) instead of waiting up to
  // pg_max_failure_s; UKF snapshots not yet stored are then dropped (logged).
  void flush_at_stop();
  // Moves every pending sample to the spill file (when there is one and it has room); returns
  // how many. After StorageOutage: what the daemon would otherwise count as not committed.
  int64_t spill_all_pending();
  // Pending at [storage] max_pending_samples and no spill file that takes them (SQLite, or the
  // spill full): take no more frames until a commit succeeds.
  bool backlogged() const {
    return static_cast<int64_t>(pending_.size()) >= config_.storage.max_pending_samples &&
           (!spill_ || spill_full_);
  }
  // A failed commit is waiting for its retry.
  bool commit_failing() const { return commit_retry_.failing(); }
  std::chrono::steady_clock::time_point next_commit_attempt() const {
    return commit_retry_.next_attempt();
  }
  // Commits, then writes the filter state of every spacecraft whose filter changed since the
  // last write (not while samples it has used are uncommitted). A failure is logged and counted;
  // the states are written next time. (Snapshots and re-anchors store theirs with the next
  // commit; this bounds the re-run of a restart for the rest.)
  void save_filter_states();
  // At shutdown, before the last commit (spacecraft_tracker.hpp): a spacecraft that never got a
  // time base takes it from its held samples, which are then stored; every other sample still
  // held for corroboration of its time is rejected as time_jump_unconfirmed, so it is counted.
  void settle_held();
  // The first samples of a new spacecraft held since before `now` - kFirstHoldMax_s give it its
  // time base and are stored (commit_if_due() calls it; public for tests).
  void release_first_holds(std::chrono::steady_clock::time_point now);
  // Samples currently held, all spacecraft (in flight, like the pending batch).
  int64_t held_samples();

  // From any thread: re-anchor sat_id's UKF on an accepted refit, stored as calibration_id
  // (applied by the worker thread at its next process()/commit_if_due()).
  void post_reanchor(const std::string& sat_id, const CalibrationResult& refit,
                     int64_t calibration_id);
  // From any thread: retention never deletes samples at or after this time (the oldest window
  // start of a refit that is due but not finished). INT64_MAX = no floor.
  void set_retention_floor(int64_t utime) { retention_floor_.store(utime); }

  // Newest accepted sample of any spacecraft (retention cadence; refits use each spacecraft's).
  int64_t data_clock_utime() const { return data_clock_utime_; }
  size_t n_spacecraft() const { return fleet_.size(); }
  int64_t pending_samples() const { return static_cast<int64_t>(pending_.size()); }
  int64_t pending_snapshots() const { return static_cast<int64_t>(pending_snapshots_.size()); }
  SpacecraftFleet& fleet() { return fleet_; }

 private:
  void ingest_sample(const mag_sample_t& s, const std::string& batch_sat_id, int64_t receive_utime);
  // The per-spacecraft checks and the store of a sample on its spacecraft's time base.
  void accept_sample(const std::string& sat, SpacecraftTracker& t, const mag_sample_t& s,
                     int64_t receive_utime);
  void hold_sample(const std::string& sat, SpacecraftTracker& t, const mag_sample_t& s,
                   int64_t receive_utime);
  // Re-examines t's held samples after its time base moved (see spacecraft_tracker.hpp).
  void resolve_held(const std::string& sat, SpacecraftTracker& t);
  // t has no time base: takes it from t's held samples (likeliest_held_utime) and resolves them.
  void base_from_held(const std::string& sat, SpacecraftTracker& t);
  void reject_sample(RejectReason r, const std::string& sat, const mag_sample_t& s);
  // A row of (sat_id, utime) is pending or stored. O(1) for the pending batch: pending_index_.
  bool is_duplicate(const std::string& sat_id, const SpacecraftTracker& t, int64_t utime);
  // Extends pending_index_ over the rows of pending_ added since it was last used.
  void index_pending();
  // pending_ lost rows at its front or was cleared: the index starts again.
  void reset_pending_index();
  void maybe_snapshot(const std::string& sat_id, SpacecraftTracker& t, int64_t utime);
  void apply_reanchors();
  // estimation.md 3a: t's UKF continues from the accepted refit (stored as calibration_id).
  void reanchor(const std::string& sat_id, SpacecraftTracker& t, const CalibrationResult& refit,
                int64_t calibration_id);
  // t's state goes into the next commit (SpacecraftTracker::state_due).
  void mark_state_due(const std::string& sat_id, SpacecraftTracker& t);
  storage::FilterState stored_state(const std::string& sat_id, const SpacecraftTracker& t) const;
  // restore(), for one spacecraft: its stored filter state, the re-run over newer samples and a
  // re-anchor the state does not have yet; returns the samples re-run.
  void restore_filter(const std::string& sat_id, SpacecraftTracker& t);
  // The re-anchor restore_filter() deferred to the refit's time (storage read errors throw).
  void apply_deferred_reanchor(const std::string& sat_id, SpacecraftTracker& t);
  // The receive side of a spacecraft from its stored window (its newest stored sample).
  void restore_received(const std::string& sat_id, SpacecraftTracker& t, int64_t newest_utime);
  // This daemon got sat_id's lease of `epoch`: the filter, its counts and schedule from the
  // database (see file comment).
  void take_over(const std::string& sat_id, SpacecraftTracker& t, int64_t epoch);
  // This daemon no longer owns sat_id (lost or handed over): its filter stops, nothing of it is
  // written any more.
  void give_up(const std::string& sat_id, SpacecraftTracker& t);
  // The owner's filter takes the union's stored samples after filtered_utime, up to the reorder
  // horizon (all of them with `drain`).
  void track_union(const std::string& sat_id, SpacecraftTracker& t, bool drain);
  // track_union() for every owned spacecraft whose union grew here (union_due), and for all
  // owned ones when another station may have stored samples (every kUnionPoll_s).
  void track_due();
  // track_due(), or with `drain` track_all_now(); a storage error leaves the filters where they
  // are (read again after the next commit).
  void track_owned(bool drain);
  void run_retention();
  // Data clock: advances sat_id's refit schedule to its newest sample; due refits are
  // committed up to their time, then handed to on_refit_due.
  void check_data_clock(const std::string& sat_id, SpacecraftTracker& t);
  // Requests sat_id's first or next early refit once it is due (Hooks::on_refit_due).
  void check_early_refit(const std::string& sat_id, SpacecraftTracker& t);
  void commit_pending();
  // In the commit of snapshots and states: gives up (and drops the writes of) every spacecraft
  // whose lease is no longer this daemon's.
  void fence_owned_writes();
  // The owned spacecraft among committed `rows` read the union next.
  void mark_union_due(std::span<const storage::StoredSample> rows);
  // Counts committed `rows` per spacecraft (minus duplicate_rows_, indices into them).
  void count_stored(std::span<const storage::StoredSample> rows);
  // Something awaits its commit: samples (pending or spilled), snapshots, filter states.
  bool uncommitted() const;
  // The pending batch goes to the spill file (all of it, or only once it is at
  // max_pending_samples); false when it did not (full, or no spill).
  bool spill_pending(bool at_any_size);
  // Commits the spill file's samples, chunk by chunk, until it is empty or `until` (throws
  // storage::StorageError; what was committed stays committed). `recovered`: an earlier run's
  // file (counted apart).
  void commit_spill(bool recovered, std::chrono::steady_clock::time_point until =
                                        std::chrono::steady_clock::time_point::max());
  void update_spill_gauges();
  // Before a refit reads the database: everything committed. Blocks (flush()) except on
  // PostgreSQL, where during an outage it returns false at once and the refit waits.
  bool committed_for_refit();
  SpacecraftTracker& tracker(const std::string& sat_id, bool* created);
  void count_missing(SpacecraftTracker& t, int64_t seq);

  const DaemonConfig config_;  // a copy: callers may pass a temporary
  DaemonCounters& counters_;
  std::unique_ptr<ReferenceField> field_;
  Hooks hooks_;
  ValidatorOptions validator_;
  std::unique_ptr<storage::Connection> db_;
  std::unique_ptr<storage::SampleWindowStore> samples_;
  std::unique_ptr<storage::CalibrationHistory> history_;
  std::unique_ptr<storage::FilterStateStore> filter_states_;
  std::unique_ptr<storage::RefitJobLog> jobs_;  // read by restore()
  std::unique_ptr<storage::LeaseStore> leases_;
  SpacecraftFleet fleet_;
  ThrottledLog warnings_;
  std::optional<RefitSchedule> data_schedule_;  // [refit] clock = "data": each tracker's schedule
  StorageRetry commit_retry_;
  StorageRetry read_retry_;

  std::vector<storage::StoredSample> pending_;
  std::unique_ptr<SampleSpill> spill_;  // PostgreSQL only (DaemonConfig::spill_path())
  bool spill_full_ = false;             // refused a batch: back-pressure until it is drained
  std::vector<storage::StoredSample> spill_chunk_;  // reused by commit_spill()
  // Data-clock refits that fell due during an outage: requested once everything is committed.
  std::vector<std::pair<std::string, int64_t>> deferred_refits_;
  std::vector<size_t> duplicate_rows_;  // of the last insert (reused: no allocation per batch)
  // pending_[0, pending_indexed_) by a hash of (sat_id, utime) -> row; built only when a
  // duplicate check needs it (out-of-order samples), so in-order ingest pays nothing.
  std::unordered_multimap<uint64_t, uint32_t> pending_index_;
  size_t pending_indexed_ = 0;
  struct PendingSnapshot {
    std::string sat_id;
    CalibrationResult result;
    int64_t temperature_model_refit_id = 0;  // the refit whose temperature model it applied
  };
  std::vector<PendingSnapshot> pending_snapshots_;
  std::vector<std::string> states_due_;  // spacecraft whose state goes into the next commit
  std::chrono::steady_clock::time_point first_pending_time_{};
  std::chrono::steady_clock::time_point last_retention_time_{};
  std::vector<std::string> retention_dirty_;
  // Spacecraft without a time base whose first samples are held, and since when (wall time),
  // in that order; one entry per spacecraft (its first hold), dropped once due.
  std::vector<std::pair<std::string, std::chrono::steady_clock::time_point>> first_holds_;
  int64_t last_retention_data_utime_ = std::numeric_limits<int64_t>::min() / 2;
  int64_t data_clock_utime_ = std::numeric_limits<int64_t>::min();
  // Newest retention edge of any spacecraft (run_retention()): received samples of the ones
  // owned elsewhere, the filter's time of the owned ones. Retention runs as it advances.
  int64_t retention_clock_utime_ = std::numeric_limits<int64_t>::min() / 2;
  int64_t frame_counter_ = 0;    // frames processed (a hold needs more than one to resolve)
  bool resolving_held_ = false;  // resolve_held() is running (no re-entry)
  std::atomic<int64_t> retention_floor_{std::numeric_limits<int64_t>::max()};

  // Ownership (maintain_leases()).
  std::vector<std::string> unregistered_;  // spacecraft new here: lease rows to ensure
  std::chrono::steady_clock::time_point next_lease_round_{};
  std::chrono::steady_clock::time_point next_union_poll_{};
  size_t live_stations_ = 1;     // at the last lease round (1: alone, no other station writes)
  const std::string instance_;   // this process in the stations table (random per start)
  int64_t last_beat_utime_ = 0;  // 0: not beaten yet
  bool tracking_ = false;        // track_union() is running (a flush inside it must not re-enter)
  std::vector<storage::StoredSample> union_rows_;  // reused by track_union()
  mutable std::mutex owned_mutex_;
  std::set<std::string> owned_names_;  // owns(), from any thread

  struct Reanchor {
    std::string sat_id;
    CalibrationResult refit;
    int64_t calibration_id = 0;
  };
  std::mutex reanchor_mutex_;
  std::vector<Reanchor> reanchors_;
  std::atomic<bool> have_reanchors_{false};
};

}  // namespace magcal
