// Receive and store: the part of the daemon's worker that every station runs (design.md
// "Daemon data flow" and "Fleet"). Where a decoded sample goes:
//
//   ingest() -> check_sample (sample_validator.hpp) -> the spacecraft's time base (held until
//   corroborated: spacecraft_tracker.hpp) -> older_than_window / duplicate (against the pending
//   batch and the store) -> reference field -> pending row
//
// and the pending rows are committed, with this station's id, in transactions of
// commit_every_samples (try_commit(); the owner's snapshots and filter states ride in the last
// one: CommitParticipant). Retention deletes old samples in small transactions. Counts every
// sample once: stored, or rejected with its reason (DaemonCounters), and the gaps in the
// received seq numbers while this station is alone.
//
// It touches only the ReceivedSpacecraft half of each spacecraft, the sample window store and
// the spill file. Ownership is not its business: every spacecraft it receives is stored the
// same way, whoever owns it (OwnedSpacecraftTracker).
//
// Storage faults (storage_retry.hpp): a failed commit keeps its samples pending (and the
// owner's writes) and is retried with backoff; the caller stops feeding ingest() while
// backlogged() (pending at [storage] max_pending_samples). The duplicate check retries in
// place. Storage broken for [storage] max_failure_s (pg_max_failure_s on PostgreSQL), or a
// permanent error, throws StorageOutage out of try_commit() and ingest().
//
// Outages of a database that spills (Capabilities::spill_during_outage: PostgreSQL, design.md
// "Network faults"): while commits fail, the pending batch goes
// to the spill file (sample_spill.hpp) at each commit interval and intake goes on; the file is
// committed first when the database returns (a slice of at most 1 s per commit, the pending batch
// queued behind it in the file until it is empty), and at start when an earlier run left one.
// Meanwhile the duplicate check does not read the database (the insert, which counts duplicates,
// decides). A database unreachable at start is the same outage (IngestWorker::restore()): the
// commit path fails from the start, and restore() runs as its first successful step; the records
// an earlier run left stay ahead of this run's in the file and are committed by restore().
//
// Retention is the one thing the owner decides for it: only the spacecraft's owner deletes, and
// only behind its filter (allow_retention()), because the owner triggers refits at its own
// data time, which may lag the stored samples (the reorder delay; a replay commits ahead of it),
// and another station far ahead (a backfill) must not delete the window the owner's refits will
// read. The refit thread's retention floor (set_retention_floor()) keeps the window of a due
// refit.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include "service/config/daemon_config.hpp"
#include "service/daemon/intake/ingest_queue.hpp"
#include "service/daemon/intake/sample_spill.hpp"
#include "service/daemon/intake/sample_validator.hpp"
#include "service/daemon/intake/storage_retry.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/daemon/ops/throttled_log.hpp"
#include "service/daemon/ownership/spacecraft_tracker.hpp"
#include "service/io/reference_field.hpp"
#include "storage/connection.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

// What the spacecraft's owner (OwnedSpacecraftTracker) adds to and learns from a commit of
// samples: its snapshots and filter states go into the transaction of the last sample chunk,
// so a stored state includes exactly the committed samples, and it reads committed samples back.
class CommitParticipant {
 public:
  // Something to write with the next commit.
  virtual bool has_writes() const = 0;
  // Inside the last chunk's transaction (throws storage::StorageError: all rolled back).
  virtual void write() = 0;
  // After that transaction committed.
  virtual void written() = 0;
  // Samples of these spacecraft are committed (any chunk, a spill file's too).
  virtual void samples_committed(std::span<const storage::StoredSample> rows) = 0;

 protected:
  ~CommitParticipant() = default;
};

class SampleIntake {
 public:
  // Reads and writes `samples` (on `db`, one thread's connection); on PostgreSQL opens the spill
  // file (an earlier run's, or a new one: throws SpillError). Counts in `counters`. Its storage
  // retries give up at `stop` (nullptr: none).
  SampleIntake(const DaemonConfig& config, DaemonCounters& counters,
               std::unique_ptr<ReferenceField> field, storage::Connection& db,
               storage::SampleWindowStore& samples, SpacecraftFleet& fleet,
               const StopDeadline* stop = nullptr);

  // At start: commits the records of a spill file an earlier run left (before anything else
  // reads the window), then every stored spacecraft's time base from its newest stored sample
  // (unless this run received newer ones meanwhile: the database was unreachable at start).
  // Throws storage::StorageError.
  void restore(CommitParticipant& owner);
  // The time base of a spacecraft from its stored window (its owner took it over without
  // having received it, or at restore()); a no-op when nothing is stored or what this run
  // received of it is newer.
  void restore_spacecraft(const std::string& sat_id);

  // A new frame starts (a hold needs samples from more than one frame to resolve).
  void begin_frame();
  // Validates and ingests one sample of the frame.
  void ingest(const mag_sample_t& s, const std::string& batch_sat_id, int64_t receive_utime);
  // Spacecraft new to this process since the last call, received or restored (their lease
  // rows are ensured).
  std::vector<std::string> take_new_spacecraft();
  bool has_new_spacecraft() const { return !new_spacecraft_.empty(); }

  // The pending batch reached commit_every_samples.
  bool batch_full() const {
    return static_cast<int64_t>(pending_.size()) >= config_.storage.commit_every_samples;
  }
  // Since when the oldest pending sample waits (commit_every_ms).
  std::chrono::steady_clock::time_point first_pending_time() const { return first_pending_time_; }

  // One attempt (none during the retry backoff) to commit the pending batch, the spill file's
  // slice first, with the owner's writes in the last transaction. True when it went through.
  // Throws StorageOutage when storage stays broken.
  bool try_commit(CommitParticipant& owner);
  // One attempt (none during the retry backoff) of `op`, a storage step of the commit path
  // (try_commit(), or a restore that could not reach the database at start): true when it went
  // through; while it fails the intake is in the outage state (commit_failing(): batches
  // spilled). Throws StorageOutage when storage stays broken.
  template <typename Op>
  bool try_commit_step(Op&& op) {
    if (!commit_retry_.due()) return false;
    commit_retry_.attempting();
    try {
      op();
    } catch (const storage::StorageError& e) {
      commit_retry_.failed(e);  // throws StorageOutage when storage stays broken
      return false;
    }
    commit_retry_.succeeded();
    return true;
  }
  // A storage step of the commit path failed outside try_commit_step() (the first restore, at
  // start): the outage state begins. Throws StorageOutage when `e` is permanent.
  void commit_step_failed(const storage::StorageError& e) { commit_retry_.failed(e); }
  // Samples not committed yet (pending or spilled).
  bool uncommitted() const { return !pending_.empty() || spill_held() > 0; }
  int64_t spill_held() const { return spill_ ? spill_->held_samples() : 0; }
  // A failed commit is waiting for its retry.
  bool commit_failing() const { return commit_retry_.failing(); }
  bool commit_due() const { return commit_retry_.due(); }
  std::chrono::steady_clock::time_point next_commit_attempt() const {
    return commit_retry_.next_attempt();
  }
  // Pending at [storage] max_pending_samples and no spill file that takes them (SQLite, or the
  // spill full): take no more frames until a commit succeeds.
  bool backlogged() const {
    return static_cast<int64_t>(pending_.size()) >= config_.storage.max_pending_samples &&
           (!spill_ || spill_full_);
  }
  // The pending batch goes to the spill file (all of it, or only once it is at
  // max_pending_samples); false when it did not (full, or no spill). The rows of a commit in
  // doubt stay in memory, until it is resolved, unless `at_exit`: they go too (the next start's
  // spill commit finds them stored, if they were).
  bool spill_pending(bool at_any_size, bool at_exit = false);

  // At shutdown, before the last commit: a spacecraft that never got a time base takes it from
  // its held samples, which are then stored; every other sample still held for corroboration of
  // its time is rejected as time_jump_unconfirmed, so it is counted.
  void settle_held();
  // The first samples of a new spacecraft held since before `now` - kFirstHoldMax_s give it its
  // time base and are stored.
  void release_first_holds(std::chrono::steady_clock::time_point now);
  int64_t held_samples();

  // The owner's filter of sat_id has taken the stored samples up to filtered_utime: retention
  // may delete behind it (kNoTime: this daemon no longer owns it, nothing is deleted).
  void allow_retention(const std::string& sat_id, int64_t filtered_utime);
  // From any thread: retention never deletes samples at or after this time (the oldest window
  // start of a refit that is due but not finished). INT64_MAX = no floor.
  void set_retention_floor(int64_t utime) { retention_floor_.store(utime); }
  // Retention, when due: every kRetentionEvery_s of wall time, and (with `by_data_time`) every
  // kRetentionEveryData_utime of the owners' filter time (a fast replay keeps its windows as a
  // live feed would). Not while commits fail.
  void run_retention_if_due(bool by_data_time);
  // The next run_retention_if_due(true) runs (end of a replay).
  void retention_at_next_commit() {
    last_retention_data_utime_ = std::numeric_limits<int64_t>::min() / 2;
  }

  // Other stations are live (the last lease round): a received seq gap may have been filled by
  // one of them, so the owner counts the union's gaps instead.
  void set_other_stations_live(bool live) { other_stations_live_ = live; }

  int64_t pending_samples() const { return static_cast<int64_t>(pending_.size()); }
  // Newest accepted sample of any spacecraft.
  int64_t data_clock_utime() const { return data_clock_utime_; }

 private:
  // The per-spacecraft checks and the store of a sample on its spacecraft's time base; true
  // when it moved the base forward (the caller resolves the held samples then).
  bool accept_sample(const std::string& sat, ReceivedSpacecraft& t, const mag_sample_t& s,
                     int64_t receive_utime);
  void hold_sample(const std::string& sat, ReceivedSpacecraft& t, const mag_sample_t& s,
                   int64_t receive_utime);
  // Re-examines t's held samples after its time base moved (see spacecraft_tracker.hpp).
  void resolve_held(const std::string& sat, ReceivedSpacecraft& t);
  // t has no time base: takes it from t's held samples (likeliest_held_utime) and resolves them.
  void base_from_held(const std::string& sat, ReceivedSpacecraft& t);
  void reject_sample(RejectReason r, const std::string& sat, const mag_sample_t& s);
  // A row of (sat_id, utime) is pending or stored. O(1) for the pending batch: pending_index_.
  bool is_duplicate(const std::string& sat_id, const ReceivedSpacecraft& t, int64_t utime);
  // Extends pending_index_ over the rows of pending_ added since it was last used.
  void index_pending();
  // pending_ lost rows at its front or was cleared: the index starts again.
  void reset_pending_index();
  void count_missing(ReceivedSpacecraft& t, int64_t seq);
  // Counts committed `rows` per spacecraft (minus duplicate_rows_, indices into them) and
  // lowers their retained_from_utime.
  void count_stored(std::span<const storage::StoredSample> rows, bool counted);
  ReceivedSpacecraft& spacecraft(const std::string& sat_id);
  void commit_pending(CommitParticipant& owner);
  // Commits the spill file's samples, chunk by chunk, until it is empty or `until` (throws
  // storage::StorageError; what was committed stays committed). `recovered`: only the records
  // an earlier run left (counted apart), which are ahead of this run's.
  void commit_spill(
      CommitParticipant& owner, bool recovered,
      std::chrono::steady_clock::time_point until = std::chrono::steady_clock::time_point::max());
  void update_spill_gauges();
  void run_retention();
  // The bookkeeping of a committed chunk of the pending batch (its first rows), or of the spill
  // file (spill_chunk_: `spill_recovered` for an earlier run's records).
  void pending_chunk_committed(CommitParticipant& owner,
                               std::span<const storage::StoredSample> rows,
                               const storage::InsertStats& stats, bool with_owner_writes);
  void spill_chunk_committed(CommitParticipant& owner, const storage::InsertStats& stats,
                             bool spill_recovered);
  // Before the next attempt after a commit in doubt (PostgreSQL: no reply to its COMMIT): asks
  // the database whether it took effect, and if so does its bookkeeping (its samples then
  // count as stored, not as duplicates of themselves). Throws storage::StorageError (transient)
  // while the server cannot tell: the attempt fails as the commit did.
  void resolve_commit_in_doubt(CommitParticipant& owner);

  const DaemonConfig& config_;
  DaemonCounters& counters_;
  std::unique_ptr<ReferenceField> field_;
  ValidatorOptions validator_;
  storage::Connection& db_;
  storage::SampleWindowStore& samples_;
  SpacecraftFleet& fleet_;
  ThrottledLog warnings_;
  StorageRetry commit_retry_;
  StorageRetry read_retry_;

  std::vector<storage::StoredSample> pending_;
  std::unique_ptr<SampleSpill> spill_;  // PostgreSQL only (DaemonConfig::spill_path())
  bool spill_full_ = false;             // refused a batch: back-pressure until it is drained
  // Records at the front of the spill file that an earlier run left, not committed yet
  // (restore() commits them; received and counted by that run, not this one).
  int64_t spill_recovered_held_ = 0;
  bool spill_recovery_logged_ = false;              // restore() said it commits them (once)
  std::vector<storage::StoredSample> spill_chunk_;  // reused by commit_spill()
  std::vector<storage::StoredSample> read_rows_;    // reused by restore_spacecraft()
  std::vector<size_t> duplicate_rows_;  // of the last insert (reused: no allocation per batch)
  // A commit in doubt (storage::StorageError::in_doubt_transaction(), 0: none): a chunk of
  // the pending batch (its first `rows` rows, which spill_pending() keeps in memory until it is
  // resolved), or spill_chunk_ of the spill file.
  struct CommitInDoubt {
    int64_t transaction_id = 0;
    enum class Chunk { kPending, kSpill, kSpillRecovered } chunk = Chunk::kPending;
    size_t rows = 0;
    storage::InsertStats stats;
    bool with_owner_writes = false;
  } in_doubt_;
  // pending_[0, pending_indexed_) by a hash of (sat_id, utime) -> row; built only when a
  // duplicate check needs it (out-of-order samples), so in-order ingest pays nothing.
  std::unordered_multimap<uint64_t, uint32_t> pending_index_;
  size_t pending_indexed_ = 0;
  std::chrono::steady_clock::time_point first_pending_time_{};
  std::vector<std::string> new_spacecraft_;
  // Spacecraft without a time base whose first samples are held, and since when (wall time),
  // in that order; one entry per spacecraft (its first hold), dropped once due.
  std::vector<std::pair<std::string, std::chrono::steady_clock::time_point>> first_holds_;
  int64_t data_clock_utime_ = std::numeric_limits<int64_t>::min();
  int64_t frame_counter_ = 0;     // frames begun (a hold needs more than one to resolve)
  int64_t frame_wall_utime_ = 0;  // this daemon's wall clock when the frame began
  bool other_stations_live_ = false;

  // Retention: spacecraft whose edge advanced, the newest edge of any (the data-time cadence).
  std::vector<std::string> retention_dirty_;
  std::chrono::steady_clock::time_point last_retention_time_{};
  int64_t last_retention_data_utime_ = std::numeric_limits<int64_t>::min() / 2;
  int64_t retention_clock_utime_ = std::numeric_limits<int64_t>::min() / 2;
  std::atomic<int64_t> retention_floor_{std::numeric_limits<int64_t>::max()};
};

}  // namespace magcal
