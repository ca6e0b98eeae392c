// The daemon's worker (design.md "Daemon data flow" and "Fleet"): the two parts of the fleet's
// seam, on one thread and one database connection, and the one place that says in which order
// they run. Like a rate group, it calls each part in turn; neither calls back into it.
//
//   SampleIntake (sample_intake.hpp), every station: validates each decoded sample, puts it on
//     its spacecraft's time base and stores it once, with the station id (pending batch,
//     commits, spill file, retention). A sample's whole path is there.
//   OwnedSpacecraftTracker (owned_spacecraft_tracker.hpp), the spacecraft's lease holder only:
//     reads the union of all stations' stored samples back into the UKF; snapshots, filter
//     states, refit triggers, re-anchors, leases.
//
// A round (commit()):
//   1. receive and validate (process(): the intake's pending batch);
//   2. commit the samples, with the owner's snapshots and due states in the last transaction,
//      fenced by the lease (CommitParticipant);
//   3. the lease round, when due (lease_round());
//   4. the owners read back what is committed and filter it (filter());
//   5. commit what the filters made (a second pass of 2-4);
//   6. the refits the filters ask for (DueRefit), once everything up to their time is
//      committed: a filter stops at a sample after which a refit is due, the worker commits
//      (waiting through the retry backoff where commits may block: storage::Capabilities), hands
//      the refits to Hooks::on_refit_due and the filter goes on at the next sample.
// So a stored filter state includes exactly the committed samples: the owner's writes only ever
// ride in the transaction of samples, and the filters only read committed ones.
// What the owner needs from the intake passes through here as data: the spacecraft new to this
// process (their lease rows), the time base of one taken over without being received, where
// retention may delete (behind the owner's filter), and whether other stations are live (then
// only the owner counts seq gaps, on the union).
//
// Storage faults: see sample_intake.hpp. Storage broken for [storage] max_failure_s
// (pg_max_failure_s on PostgreSQL), or a permanent error, throws StorageOutage out of
// process() / commit_if_due() / commit() / flush(). The only cross-thread entry points are
// post_reanchor(), owns() and set_retention_floor().
//
// Restart (restore()), after a SIGTERM or a crash: the receive side comes back from the stored
// windows, then the leases this daemon may hold are taken over (owned_spacecraft_tracker.hpp).
// A database whose engine makes an unreachable server at start an outage
// (Capabilities::unreachable_at_start_is_outage: a server on the network) starts in that outage:
// samples are received, validated and held or spilled as in any outage, no lease is taken and
// no filter runs; the restore is the commit path's first step, retried on its cadence, and once
// it goes through the spill is committed and the worker goes on as usual (past
// pg_max_failure_s: StorageOutage, as in any outage; a permanent error then is the start error
// it would have been: RefusedAtFirstContact).
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <stdexcept>

#include "pipeline/calibration_result.hpp"
#include "service/config/daemon_config.hpp"
#include "service/daemon/intake/ingest_queue.hpp"
#include "service/daemon/intake/sample_intake.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/daemon/ownership/owned_spacecraft_tracker.hpp"
#include "service/daemon/ownership/spacecraft_tracker.hpp"
#include "service/io/reference_field.hpp"
#include "storage/connection.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

// The database, unreachable at start, refused the daemon for good when it first answered (a
// missing database or role, authentication, a schema that is not magcal's): the start error it
// would have been at start (exit 2), not an outage of a database that worked (exit 3).
class RefusedAtFirstContact : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class IngestWorker {
 public:
  // The worker's outputs to the daemon.
  struct Hooks {
    // A UKF snapshot was committed (publish it).
    OwnedSpacecraftTracker::SnapshotHook on_snapshot;
    // A refit of sat_id's window ending at t_ref is due, and its samples up to t_ref are
    // committed (DueRefit). In a replay it waits for the refit, so that its re-anchor lands at
    // the same sample every time.
    std::function<void(const std::string& sat_id, int64_t t_ref_utime,
                       storage::RefitTrigger trigger)>
        on_refit_due;
  };

  // Opens its own connection to config.storage.db_path (throws storage::StorageError; a
  // PostgreSQL server that cannot be reached now is not an error: OpenOptions::connect_later)
  // and, on PostgreSQL, the spill file (throws SpillError). Counts in `counters` (must outlive
  // the worker), per spacecraft too, and times each commit. Its storage retries give up at
  // `stop` (nullptr: none; must outlive the worker).
  IngestWorker(const DaemonConfig& config, DaemonCounters& counters,
               std::unique_ptr<ReferenceField> field, Hooks hooks,
               const StopDeadline* stop = nullptr);
  ~IngestWorker();

  // Commits a spill file an earlier run left, rebuilds the receive side from the database, then
  // takes the leases this daemon may own. Call once before process(). False when the database
  // cannot be reached (PostgreSQL, a transient error: logged): the worker starts in the outage
  // state and restores at the first commit attempt that reaches it. Throws
  // storage::StorageError otherwise (a start error).
  bool restore();
  // From any thread: the database was reached and the restore done (at restore(), or since).
  bool restored() const { return restored_.load(); }

  // The lease round (lease_round()); commit_if_due() runs it every [fleet] lease_s / 3; public
  // for tests.
  void maintain_leases();
  // At a clean stop: hands every owned spacecraft back (its state committed first) and ends
  // the heartbeat, so the other daemons take over at once instead of after the lease time.
  void leave_fleet();
  // From any thread: this daemon holds sat_id's lease.
  bool owns(const std::string& sat_id) const { return owner_.owns(sat_id); }
  // From any thread: LCM input ended; from now on only the free leases of spacecraft received
  // here are taken (OwnedSpacecraftTracker::stop_taking_leases). At the end of a replay
  // (`end_of_log`), track_all_now() takes them first.
  void input_ended(bool end_of_log) {
    owner_.stop_taking_leases();
    replay_ended_.store(end_of_log);
  }
  // The owner's filters take every stored sample, without the reorder delay (end of a replay,
  // shutdown); their snapshots and refit triggers as usual.
  void track_all_now();

  // Validates and ingests every sample of a decoded frame (commits whenever the batch is full).
  // A commit that throws (storage failed for good) leaves the rest of the frame in the pending
  // batch, so that spill_all_pending() keeps it.
  void process(const IngestItem& item);
  // After storage failed for good: validates and ingests the samples of a frame from `first` on
  // into the pending batch, without committing (for spill_all_pending()).
  void ingest_without_commit(const IngestItem& item, size_t first = 0);
  // Commits when the pending batch is full or old enough; call regularly.
  void commit_if_due();
  // Commits pending samples and the owner's writes now (see file comment), then runs retention.
  // After a failure, a no-op until the retry backoff has elapsed.
  void commit();
  // Commits everything pending, retrying through the backoff until it is stored; throws
  // StorageOutage when storage stays broken (shutdown, and before a data-clock refit).
  void flush();
  // At shutdown: flush(), except that with a spill file (Capabilities::spill_during_outage)
  // while storage fails the pending samples are spilled at once (committed at the next start)
  // instead of waiting up to pg_max_failure_s; UKF snapshots not yet stored are then dropped
  // (logged).
  void flush_at_stop();
  // Moves every pending sample to the spill file (when there is one and it has room); returns
  // how many. After StorageOutage: what the daemon would otherwise count as not committed.
  int64_t spill_all_pending();
  // Take no more frames until a commit succeeds (SampleIntake::backlogged()).
  bool backlogged() const { return intake_.backlogged(); }
  // A failed commit is waiting for its retry.
  bool commit_failing() const { return intake_.commit_failing(); }
  std::chrono::steady_clock::time_point next_commit_attempt() const {
    return intake_.next_commit_attempt();
  }
  // Commits, then writes the filter state of every spacecraft whose filter changed since the
  // last write (not while samples it has used are uncommitted). A failure is logged and counted;
  // the states are written next time. (Snapshots and re-anchors store theirs with the next
  // commit; this bounds the re-run of a restart for the rest.)
  void save_filter_states();
  // At shutdown, before the last commit: held samples settled (SampleIntake::settle_held()).
  void settle_held() { intake_.settle_held(); }
  // The first samples of a new spacecraft held since before `now` - kFirstHoldMax_s give it its
  // time base and are stored (commit_if_due() calls it; public for tests).
  void release_first_holds(std::chrono::steady_clock::time_point now) {
    intake_.release_first_holds(now);
  }
  // Samples currently held, all spacecraft (in flight, like the pending batch).
  int64_t held_samples() { return intake_.held_samples(); }

  // From any thread: re-anchor sat_id's UKF on an accepted refit, stored as calibration_id
  // (applied by the worker thread at its next process()/commit_if_due()).
  void post_reanchor(const std::string& sat_id, const CalibrationResult& refit,
                     int64_t calibration_id) {
    owner_.post_reanchor(sat_id, refit, calibration_id);
  }
  // From any thread: retention never deletes samples at or after this time (the oldest window
  // start of a refit that is due but not finished). INT64_MAX = no floor.
  void set_retention_floor(int64_t utime) { intake_.set_retention_floor(utime); }

  // Newest accepted sample of any spacecraft.
  int64_t data_clock_utime() const { return intake_.data_clock_utime(); }
  size_t n_spacecraft() const { return fleet_.size(); }
  int64_t pending_samples() const { return intake_.pending_samples(); }
  int64_t pending_snapshots() const { return owner_.pending_snapshots(); }
  SpacecraftFleet& fleet() { return fleet_; }

 private:
  // Samples, snapshots or filter states await their commit.
  bool uncommitted() const { return intake_.uncommitted() || owner_.has_writes(); }
  // Step 2 of a round: one attempt (none during the retry backoff) at the pending samples and
  // the owner's writes; the deferred refits are requested once everything is committed. False
  // when it failed (everything stays pending).
  bool commit_pending();
  // One attempt at committing everything (step 2 alone, no filter pass): true when everything
  // is committed.
  bool commit_once();
  // Everything committed before a refit: commit_once() until it is, through the retry backoff,
  // where commits may block; else one commit_once().
  bool commit_for_refit();
  // Sleeps until the retry backoff lets the next commit attempt run.
  void await_commit_attempt();
  // Step 4: the owners read back and filter; their refits (step 6) when they ask.
  void filter(bool drain);
  void request_refits(const std::vector<DueRefit>& refits);
  // Retention, where the owner allows it (its retention edges passed to the intake first).
  void run_retention_if_due(bool by_data_time);
  // The lease round, with what the owner and the intake need from each other.
  void lease_round();
  // restore()'s work (throws storage::StorageError).
  void restore_from_database();
  // restored(), or one attempt to restore when the commit path's retry is due (file comment).
  bool try_restore();

  const DaemonConfig config_;  // a copy: callers may pass a temporary
  const storage::Capabilities storage_;
  Hooks hooks_;
  std::unique_ptr<storage::Connection> db_;
  std::unique_ptr<storage::SampleWindowStore> samples_;
  SpacecraftFleet fleet_;
  SampleIntake intake_;
  OwnedSpacecraftTracker owner_;
  // False while the database has not been reached since start; then the intake is in its
  // outage state (commit_failing()) and nothing of the owner's runs.
  std::atomic<bool> restored_{false};
  std::atomic<bool> replay_ended_{false};  // input_ended()
};

}  // namespace magcal
