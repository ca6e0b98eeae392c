// Track: the part of the daemon's worker that runs only for the spacecraft this daemon owns
// (design.md "Fleet"). The daemon holding a spacecraft's lease (LeaseStore; a lease round every
// [fleet] lease_s / 3 decides who should own what: lease_round.hpp) reads back the union of all
// stations' stored samples in time order, [fleet] reorder_delay_s of data time behind the newest
// (track_owned()), and runs them through the UKF: snapshots every `snapshot_every_s` of DATA
// time, on a grid every owner shares (history row + calibration_t), and the refit triggers (the
// data clock, each spacecraft on its own data time; early refits).
//
// It touches only the OwnedSpacecraft half of each spacecraft and the history, filter-state,
// job-log and lease stores; it reads the sample window. It never writes a sample, and never
// calls the worker that sequences it (IngestWorker): what it needs from a round it returns as
// data, and the worker acts on it:
//   - refits_waiting(): a filter stopped at a sample after which a refit is due; the refit reads
//     the window from the database, so the worker commits everything up to there first, then
//     asks refits_after_commit() for the requests and resume_tracking(). During a PostgreSQL
//     outage (samples held or spilled) a data-clock refit waits, and is requested once
//     everything is committed (take_deferred_refits()).
//   - lease_round_over_share(): the excess is handed over once its writes are committed.
//   - take_retention_edges(): only the owner lets the intake delete, behind its filter
//     (SampleIntake::allow_retention()).
//   - acquired_unreceived(): a spacecraft taken over that this process never received gets its
//     time base from the stored window (SampleIntake::restore_spacecraft()).
// Its snapshot rows and the filter states due ride in the transaction of the intake's last
// sample chunk (CommitParticipant), fenced by the lease inside that transaction
// (LeaseStore::holds(); on PostgreSQL the lease row stays locked until the commit, so a takeover
// waits for it): a daemon that stalled past its lease writes nothing.
//
// Takeover (at a restart, or from a daemon that died or handed it over): the UKF from its stored
// state, then the normal reading of the union goes on after the state's last sample, with its
// snapshots and refit triggers, as the previous owner would have (snapshots and states are
// committed together, so none is lost or repeated). An accepted refit the stored state was not
// re-anchored on is applied then; one still running elsewhere when the lease came here is
// applied when it ends (poll_refits_elsewhere()). Each data-clock schedule resumes after the
// last scheduled refit that ran to its end, so a refit that was due when the owner died runs
// again (its job claim was given up: RefitJobLog).
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <mutex>
#include <optional>
#include <set>
#include <span>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include "pipeline/calibration_result.hpp"
#include "service/config/daemon_config.hpp"
#include "service/daemon/intake/sample_intake.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/daemon/ops/throttled_log.hpp"
#include "service/daemon/ownership/fleet_settings_watch.hpp"
#include "service/daemon/ownership/lease_round.hpp"
#include "service/daemon/ownership/spacecraft_tracker.hpp"
#include "service/refit/refit_scheduler.hpp"
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

// A refit the owner asks for, its samples up to t_ref committed. kScheduled: the data clock
// (sat_id's own data time passed its scheduled time t_ref); kFirst / kEarly (EarlyRefitPlan:
// its UKF started from data and the stored samples reached min_samples, or grew by [refit]
// early_growth since, while they span less than window_hours; t_ref is the time of the N-th
// stored sample, so the window holds exactly N: each refit re-anchors the filter with a
// covariance from the residuals' structure, hours before the schedule would).
struct DueRefit {
  std::string sat_id;
  int64_t t_ref_utime = 0;
  storage::RefitTrigger trigger = storage::RefitTrigger::kScheduled;
};

class OwnedSpacecraftTracker final : public CommitParticipant {
 public:
  // A UKF snapshot was committed (publish it).
  using SnapshotHook = std::function<void(const std::string& sat_id, const CalibrationResult&)>;

  // Uses the stores on one thread's connection `db`; reads `samples`.
  OwnedSpacecraftTracker(const DaemonConfig& config, DaemonCounters& counters,
                         storage::Connection& db, storage::SampleWindowStore& samples,
                         SpacecraftFleet& fleet, SnapshotHook on_snapshot);
  ~OwnedSpacecraftTracker();
  OwnedSpacecraftTracker(const OwnedSpacecraftTracker&) = delete;
  OwnedSpacecraftTracker& operator=(const OwnedSpacecraftTracker&) = delete;

  // A lease round, in steps the worker sequences (owned_spacecraft_leases.cpp): heartbeat,
  // renewals, the decisions (decide_lease_round()) and acquisitions; true when this station
  // holds more than its share (hand_over_excess() then, once the writes are committed). A
  // storage error is logged and counted; the next round retries (leases not renewed in time are
  // lost, and given up here). Throws StationConflict.
  bool begin_lease_round();
  // Over the share: hands over the excess when `writes_committed` (never waits through an
  // outage for it).
  void hand_over_excess(bool writes_committed);
  // Refits elsewhere polled; the round's success or failure counted.
  void end_lease_round();
  // Acquired this round, not known to this process (its time base comes from the stored window
  // before the takeover; a failure there: takeover_failed()).
  std::vector<std::string> acquired_unreceived();
  void takeover_failed(const std::string& sat_id, const storage::StorageError& e);
  // The takeovers of the leases acquired this round (the filter, its counts and schedule from
  // the database: see file comment).
  void take_over_acquired();
  std::chrono::steady_clock::time_point next_lease_round() const { return next_lease_round_; }
  // Spacecraft new here: their lease rows are ensured at the next round, which is now.
  void register_spacecraft(std::vector<std::string> sat_ids);
  // Live stations at the last lease round (1: alone).
  size_t live_stations() const { return live_stations_; }
  // From any thread: this daemon's LCM input has ended (end of a replay, a stop): from the next
  // lease round it takes only the free leases of spacecraft it received itself (what it still
  // drains), none of those another station handed over or left (a draining daemon that took a
  // stopped station's would read back and filter them only to hand them over again at its own
  // stop); it still renews, reclaims and hands over its own.
  void stop_taking_leases() { taking_leases_.store(false); }
  // At a clean stop, with everything committed: hands every owned spacecraft back and ends the
  // heartbeat, so the other daemons take over at once instead of after the lease time.
  void release_all();
  // From any thread: this daemon holds sat_id's lease.
  bool owns(const std::string& sat_id) const;
  size_t owned_count();

  // The owned filters read the union where it grew (union_due), and every kUnionPoll_s where
  // other stations may have stored samples; with `drain` all of them, without the reorder
  // delay (end of a replay, shutdown). A storage error leaves the filters where they are (read
  // again after the next commit).
  void track_owned(bool drain);
  // A filter stopped at a sample after which a refit is due: commit everything up to there,
  // then refits_after_commit() and resume_tracking().
  bool refits_waiting() const { return stop_.waiting; }
  // The refits of the stop: requested when `committed`; otherwise a data-clock refit waits for
  // the commit (take_deferred_refits()) and an early one is asked again with the next sample.
  std::vector<DueRefit> refits_after_commit(bool committed);
  // The filters go on after the sample they stopped at.
  void resume_tracking();
  // Data-clock refits deferred during an outage (call once everything is committed).
  std::vector<DueRefit> take_deferred_refits();
  // Where retention may delete behind each owned filter since the last call (sat_id,
  // filtered_utime; kNoTime: no longer owned here), in order: SampleIntake::allow_retention().
  std::vector<std::pair<std::string, int64_t>> take_retention_edges() {
    return std::exchange(retention_edges_, {});
  }
  // From any thread: re-anchor sat_id's UKF on an accepted refit, stored as calibration_id
  // (applied by the worker thread at its next apply_reanchors()).
  void post_reanchor(const std::string& sat_id, const CalibrationResult& refit,
                     int64_t calibration_id);
  void apply_reanchors_if_posted() {
    if (have_reanchors_.load(std::memory_order_acquire)) apply_reanchors();
  }
  // Writes the filter state of every owned spacecraft whose filter changed since the last write,
  // fenced by its lease (call with every sample it used committed). A failure is logged and
  // counted; the states are written next time.
  void save_dirty_states();
  // At a stop while the database is unreachable: the snapshots not stored are dropped (logged),
  // the states are not saved (the next start re-runs the filters over the newer samples).
  void drop_unstored_writes();
  int64_t pending_snapshots() const { return static_cast<int64_t>(pending_snapshots_.size()); }

  // CommitParticipant: snapshots and due states, fenced by the leases; the owned spacecraft
  // among committed rows read the union next.
  bool has_writes() const override { return !pending_snapshots_.empty() || !states_due_.empty(); }
  void write() override;
  void written() override;
  void samples_committed(std::span<const storage::StoredSample> rows) override;

 private:
  // estimation.md 3a: t's UKF continues from the accepted refit (stored as calibration_id).
  void reanchor(const std::string& sat_id, OwnedSpacecraft& t, const CalibrationResult& refit,
                int64_t calibration_id);
  void apply_reanchors();
  // t's state goes into the next commit (OwnedSpacecraft::state_due).
  void mark_state_due(const std::string& sat_id, OwnedSpacecraft& t);
  storage::FilterState stored_state(const std::string& sat_id, const OwnedSpacecraft& t) const;
  void maybe_snapshot(const std::string& sat_id, OwnedSpacecraft& t, int64_t utime);
  // The filter from its stored state, and a re-anchor the state does not have yet (deferred to
  // the refit's time).
  void restore_filter(const std::string& sat_id, OwnedSpacecraft& t);
  // An accepted refit newer than t's anchor, stored meanwhile: t re-anchors on it once its
  // filter has passed the refit's time (at once when it has).
  void catch_up_reanchor(const std::string& sat_id, OwnedSpacecraft& t, int64_t reanchor_id);
  void apply_deferred_reanchor(const std::string& sat_id, OwnedSpacecraft& t);
  // A refit of an owned spacecraft still running at another station after the takeover: its
  // re-anchor is applied once it ends (checked every lease round).
  void poll_refits_elsewhere();
  // A refit of sat_id another station is running (claimed, not ended).
  bool refit_running_elsewhere(const std::string& sat_id);
  // A storage error ended the lease round: counted, logged, retried at the next round.
  void lease_round_failed(const storage::StorageError& e);
  // This daemon got sat_id's lease of `epoch`: the filter, its counts and schedule from the
  // database (see file comment).
  void take_over(const std::string& sat_id, SpacecraftTracker& t, int64_t epoch);
  // This daemon no longer owns sat_id (lost or handed over): its filter stops, nothing of it is
  // written any more.
  void give_up(const std::string& sat_id, OwnedSpacecraft& t);
  // The pass of track_owned() from where it is (pass_), until every due spacecraft is read
  // and filtered or a filter stops at a refit (stop_). A storage error ends the pass.
  void run_pass();
  // Reads the union of the next kUnionReadsPerStatement spacecraft of the pass.
  void read_pass_batch();
  // The owner's filter of the pass's current spacecraft takes its union rows (its stored
  // samples after filtered_utime) up to the reorder horizon (all of them with `drain`); false
  // when it stopped at a refit.
  bool track_union(const std::string& sat_id, OwnedSpacecraft& t);
  // After the filter took a row: a refit due (early or data clock) stops the pass there.
  bool stop_for_refits(const std::string& sat_id, OwnedSpacecraft& t);
  // The early refit of the stop, its samples committed: its window end from the database.
  std::optional<DueRefit> early_refit(const std::string& sat_id, OwnedSpacecraft& t);
  // Where retention may delete behind sat_id's filter (take_retention_edges()).
  void retention_edge(const std::string& sat_id, int64_t filtered_utime) {
    retention_edges_.emplace_back(sat_id, filtered_utime);
  }
  // In the commit of snapshots and states: gives up (and drops the writes of) every spacecraft
  // whose lease is no longer this daemon's.
  void fence_owned_writes();

  const DaemonConfig& config_;
  DaemonCounters& counters_;
  SnapshotHook on_snapshot_;
  storage::Connection& db_;
  storage::SampleWindowStore& samples_;  // read only
  std::unique_ptr<storage::CalibrationHistory> history_;
  std::unique_ptr<storage::FilterStateStore> filter_states_;
  std::unique_ptr<storage::RefitJobLog> jobs_;
  std::unique_ptr<storage::LeaseStore> leases_;
  SpacecraftFleet& fleet_;
  ThrottledLog warnings_;
  std::optional<RefitSchedule> data_schedule_;  // [refit] clock = "data": each tracker's schedule

  struct PendingSnapshot {
    std::string sat_id;
    CalibrationResult result;
    int64_t temperature_model_refit_id = 0;  // the refit whose temperature model it applied
    uint64_t number = 0;                     // in the order they were made
  };
  std::vector<PendingSnapshot> pending_snapshots_;
  uint64_t snapshots_made_ = 0;
  // What the last write() wrote: written() marks those written (a commit in doubt is resolved
  // later, when more may be pending), the snapshots up to this number and these states.
  uint64_t written_snapshot_number_ = 0;
  std::vector<std::string> written_states_;
  std::vector<storage::CalibrationRecord> snapshot_records_;  // reused by write()
  std::vector<storage::FilterState> due_states_;              // reused by write()
  std::vector<std::string> states_due_;  // spacecraft whose state goes into the next commit
  // Data-clock refits that fell due during an outage: requested once everything is committed.
  std::vector<DueRefit> deferred_refits_;
  std::vector<std::pair<std::string, int64_t>> retention_edges_;  // take_retention_edges()
  // Owned spacecraft with a refit another station was running when the lease came here.
  std::vector<std::string> refits_elsewhere_;

  std::vector<std::string> unregistered_;  // spacecraft new here: lease rows to ensure
  // Free leases not received here, left to their receivers at the last lease round, and since
  // when (wall time; LeaseRoundDecisions::free_since).
  std::unordered_map<std::string, int64_t> free_since_;
  // The lease round under way (begin_lease_round() to take_over_acquired()).
  struct LeaseRoundState {
    bool failed = false;  // a storage error ended it (no handover, no poll)
    size_t held = 0;
    size_t share = 0;
    size_t n_leases = 0;
    int64_t received_since_utime = 0;                       // received here since then: preferred
    std::vector<std::pair<std::string, int64_t>> acquired;  // (sat, epoch), taken over at its end
  } round_;
  std::chrono::steady_clock::time_point next_lease_round_{};
  std::chrono::steady_clock::time_point next_union_poll_{};
  size_t live_stations_ = 1;     // at the last lease round (1: alone, no other station writes)
  const std::string instance_;   // this process in the stations table (random per start)
  int64_t last_beat_utime_ = 0;  // 0: not beaten yet
  // This station's settings, declared in its heartbeat; the other live stations' compared.
  FleetSettingsWatch settings_watch_;
  // The last lease round failed on storage: counted as a failing storage path (storage_healthy()
  // false: /-/ready 503 on PostgreSQL) until a round succeeds, also on a station with nothing to
  // commit.
  bool lease_round_failing_ = false;
  std::atomic<bool> taking_leases_{true};  // false once LCM input ended: received ones only
  // The pass of track_owned() under way: the due spacecraft, their rows read a batch at a
  // time, and where the filters are (a stop at a refit resumes there).
  struct Pass {
    bool drain = false;
    size_t sat = 0;          // the spacecraft being filtered (index into union_due_sats_)
    size_t batch_begin = 0;  // union_rows_ holds the rows of [batch_begin, batch_end)
    size_t batch_end = 0;
    bool sat_started = false;   // its horizon set, its first row at `row`
    size_t row = 0;             // its next row in union_rows_
    int64_t horizon_utime = 0;  // its rows up to here are filtered now
    bool state_was_due = false;
  } pass_;
  struct RefitStop {
    bool waiting = false;
    std::string sat_id;
    bool early = false;
    std::vector<int64_t> scheduled_utimes;  // data-clock refits due
  } stop_;
  std::vector<storage::StoredSample> union_rows_;   // reused by track_owned()
  std::vector<size_t> union_row_ends_;              // reused by track_owned()
  std::vector<const std::string*> union_due_sats_;  // reused by track_owned()
  std::vector<storage::SampleWindowStore::WindowRequest> union_requests_;  // reused too
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
