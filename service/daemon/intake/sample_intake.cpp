#include "service/daemon/intake/sample_intake.hpp"

#include <algorithm>
#include <limits>

#include <spdlog/spdlog.h>

#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"

namespace magcal {
namespace {

constexpr int64_t kNoTime = ReceivedSpacecraft::kNoTime;
constexpr double kRetentionEvery_s = 2.0;                   // wall time...
constexpr int64_t kRetentionEveryData_utime = 600'000'000;  // ...or data time
constexpr int kRetentionChunkRows = 2000;
// A spacecraft's old samples are deleted once its cutoff has moved this far (data time) past
// what is stored: a live fleet of 1 000 spacecraft would otherwise run 500 DELETEs a second,
// each of one sample (one per 10 s each). The window keeps at most this much more.
constexpr int64_t kRetentionStep_utime = 600'000'000;
// A commit drains the spill file for at most this long, then the worker takes frames again: a
// large spill (1 GiB: minutes of inserts) must not stall intake or the systemd watchdog.
constexpr double kSpillDrainSlice_s = 1.0;

ValidatorOptions validator_options(const DaemonConfig& c) {
  ValidatorOptions v;
  v.range_nT = c.sensor.range_nT;
  v.min_position_m = c.service.min_position_km * 1e3;
  v.max_position_m = c.service.max_position_km * 1e3;
  v.whitelist = c.service.whitelist;
  std::sort(v.whitelist.begin(), v.whitelist.end());
  return v;
}

// The key of a pending row in SampleIntake::pending_index_ (equal keys are compared in full).
uint64_t pending_key(const std::string& sat_id, int64_t utime) {
  return std::hash<std::string>{}(sat_id) ^ (static_cast<uint64_t>(utime) * 0x9E3779B97F4A7C15ULL);
}

}  // namespace

void SampleIntake::begin_frame() {
  ++frame_counter_;
  frame_wall_utime_ = now_utime();
}

SampleIntake::SampleIntake(const DaemonConfig& config, DaemonCounters& counters,
                           std::unique_ptr<ReferenceField> field, storage::Connection& db,
                           storage::SampleWindowStore& samples, SpacecraftFleet& fleet,
                           const StopDeadline* stop)
    : config_(config),
      counters_(counters),
      field_(std::move(field)),
      validator_(validator_options(config)),
      db_(db),
      samples_(samples),
      fleet_(fleet),
      commit_retry_("commit", config.storage_max_failure_s(), counters,
                    config.storage_max_failure_key(), stop),
      read_retry_("duplicate check", config.storage_max_failure_s(), counters,
                  config.storage_max_failure_key(), stop) {
  pending_.reserve(static_cast<size_t>(config.storage.commit_every_samples));
  if (const std::string path = config.spill_path(); !path.empty()) {
    spill_ = std::make_unique<SampleSpill>(path, db_.name(), config.storage.spill_max_bytes);
    spill_recovered_held_ = spill_->held_samples();
    if (spill_recovered_held_ > 0 && !spill_->found_database().empty() &&
        spill_->found_database() != db_.name()) {
      throw SpillForAnotherDatabase(fmt::format(
          "spill file {} holds {} samples received for database {}, not for [storage] db_path "
          "{}: start magcald once with that db_path to commit them there, or move the file away "
          "(it is kept as it is; nothing was committed)",
          path, spill_recovered_held_, spill_->found_database(), db_.name()));
    }
    if (spill_->dropped_records() > 0) {
      counters_.spill_dropped.fetch_add(spill_->dropped_records());
      spdlog::error(
          "spill file {}: its torn or corrupt end was cut off (the process stopped "
          "during a write); its {} complete samples are kept",
          path, spill_->held_samples());
    }
    update_spill_gauges();
  }
}

void SampleIntake::restore(CommitParticipant& owner) {
  if (spill_recovered_held_ > 0) {
    // Before the time bases are rebuilt (and the filters re-run): they include these samples.
    const int64_t held = spill_recovered_held_;
    // Once: while the database stays unreachable restore() is retried on the commit backoff.
    if (!spill_recovery_logged_) {
      spill_recovery_logged_ = true;
      spdlog::warn(
          "spill file {} (written for {}) holds {} samples an earlier run received during "
          "a database outage: committing them",
          spill_->path(), spill_->found_database(), held);
    }
    const int64_t recovered_before = counters_.spill_recovered.load();
    resolve_commit_in_doubt(owner);
    commit_spill(owner, true);
    const int64_t committed = counters_.spill_recovered.load() - recovered_before;
    spdlog::info("spill file {}: {} samples committed ({} already stored); {}", spill_->path(),
                 committed, held - committed,
                 spill_->held_samples() == 0
                     ? std::string("file removed")
                     : fmt::format("the {} this run spilled follow", spill_->held_samples()));
  }
  for (const auto& sat : samples_.spacecraft()) restore_spacecraft(sat);
}

void SampleIntake::restore_spacecraft(const std::string& sat) {
  const auto newest = samples_.newest_utime(sat);
  if (!newest) return;
  ReceivedSpacecraft& t = spacecraft(sat);  // (its lease row ensured: stored before leases were)
  t.stored_bound_utime = std::max(t.stored_bound_utime, *newest);
  data_clock_utime_ = std::max(data_clock_utime_, *newest);
  // Received since the start, newer than what is stored (the database was unreachable then):
  // that time base and seq stream go on.
  if (t.newest_utime != kNoTime && t.newest_utime >= *newest) return;
  t.newest_utime = *newest;
  samples_.read_window(sat, *newest, saturating_add(*newest, 1), read_rows_);
  if (!read_rows_.empty()) t.received_seq.last_seq = read_rows_.back().seq;
  // First samples held for corroboration meanwhile: now on (or off) a time base.
  if (!t.held.empty()) resolve_held(sat, t);
}

ReceivedSpacecraft& SampleIntake::spacecraft(const std::string& sat_id) {
  bool created = false;
  ReceivedSpacecraft& t = fleet_.get(sat_id, &created);
  if (created) new_spacecraft_.push_back(sat_id);  // its lease row, at once
  return t;
}

std::vector<std::string> SampleIntake::take_new_spacecraft() {
  std::vector<std::string> out;
  out.swap(new_spacecraft_);
  return out;
}

void SampleIntake::count_missing(ReceivedSpacecraft& t, int64_t seq) {
  const int64_t missing = t.received_seq.observe(seq);
  // In a fleet another station may have delivered it: the owner counts the union's gaps.
  if (missing == 0 || other_stations_live_) return;
  counters_.missing_by_seq.fetch_add(missing, std::memory_order_relaxed);
  t.counters->missing.fetch_add(missing, std::memory_order_relaxed);
}

void SampleIntake::count_stored(std::span<const storage::StoredSample> rows, bool counted) {
  // Rows come in runs of one spacecraft (a batch, a recorder dump): one lookup per run.
  size_t dup = 0;
  size_t run_start = 0;
  int64_t run_stored = 0;
  int64_t run_oldest = std::numeric_limits<int64_t>::max();
  auto flush_run = [&](size_t at) {
    if (run_start < rows.size()) {
      if (SpacecraftTracker* found = fleet_.find(rows[run_start].sat_id)) {
        ReceivedSpacecraft& t = *found;
        if (counted && run_stored > 0) {
          t.counters->stored.fetch_add(run_stored, std::memory_order_relaxed);
        }
        if (t.retained_from_utime != kNoTime) {
          t.retained_from_utime = std::min(t.retained_from_utime, run_oldest);
        }
      }
    }
    run_stored = 0;
    run_oldest = std::numeric_limits<int64_t>::max();
    run_start = at;
  };
  for (size_t i = 0; i < rows.size(); ++i) {
    if (rows[i].sat_id != rows[run_start].sat_id) flush_run(i);
    run_oldest = std::min(run_oldest, rows[i].utime);
    if (dup < duplicate_rows_.size() && duplicate_rows_[dup] == i) {
      ++dup;  // a duplicate the in-memory check could not see: counted as rejected instead
      continue;
    }
    ++run_stored;
  }
  flush_run(rows.size());
}

void SampleIntake::index_pending() {
  for (; pending_indexed_ < pending_.size(); ++pending_indexed_) {
    const auto& p = pending_[pending_indexed_];
    pending_index_.emplace(pending_key(p.sat_id, p.utime), static_cast<uint32_t>(pending_indexed_));
  }
}

void SampleIntake::reset_pending_index() {
  pending_index_.clear();
  pending_indexed_ = 0;
}

bool SampleIntake::is_duplicate(const std::string& sat_id, const ReceivedSpacecraft& t,
                                int64_t utime) {
  // Only reached for samples not newer than the spacecraft's newest (recorder playback, held
  // samples accepted in arrival order). Nothing stored or pending is newer than the bound.
  if (utime > t.stored_bound_utime) return false;
  index_pending();
  const auto [first, last] = pending_index_.equal_range(pending_key(sat_id, utime));
  for (auto it = first; it != last; ++it) {
    const auto& p = pending_[it->second];
    if (p.utime == utime && p.sat_id == sat_id) return true;
  }
  if (spill_) {
    // PostgreSQL: while the database is away the insert decides (ON CONFLICT, counted as
    // duplicate): a read retried in place would stop intake for the whole outage.
    if (commit_retry_.failing()) return false;
    try {
      return samples_.count_in_window(sat_id, utime, utime + 1) > 0;
    } catch (const storage::StorageError&) {
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      return false;
    }
  }
  // Reads work through most faults (WAL readers never wait for the writer); one that fails is
  // retried in place: the sample must not be taken before its answer.
  return read_retry_.run_blocking(
      [&] { return samples_.count_in_window(sat_id, utime, utime + 1) > 0; });
}

void SampleIntake::reject_sample(RejectReason r, const std::string& sat, const mag_sample_t& s) {
  counters_.reject(r);
  warnings_.warn(to_string(r), fmt::format("rejected sample ({}): sat '{}' utime {} seq {}",
                                           to_string(r), sat, s.utime, s.seq));
}

void SampleIntake::ingest(const mag_sample_t& s, const std::string& batch_sat_id,
                          int64_t receive_utime) {
  const auto reason = check_sample(s, batch_sat_id, validator_);
  const std::string& sat = sample_sat_id(s, batch_sat_id);
  if (reason) {
    if (*reason != RejectReason::kInvalidSatId && *reason != RejectReason::kBatchSatMismatch &&
        *reason != RejectReason::kUnknownSpacecraft) {
      // The frame was received: it is not missing, whatever is wrong with it.
      if (SpacecraftTracker* t = fleet_.find(sat)) count_missing(*t, s.seq);
    }
    reject_sample(*reason, sat, s);
    return;
  }
  const size_t known = new_spacecraft_.size();
  ReceivedSpacecraft& t = spacecraft(sat);
  if (new_spacecraft_.size() != known) {
    spdlog::info("new spacecraft '{}' (first sample {})", sat, format_iso8601_utc(s.utime));
  }
  count_missing(t, s.seq);
  // Telemetry cannot come from the future (beyond clock skew): a corrupt time tag.
  const int64_t now = receive_utime > 0 ? receive_utime : now_utime();
  // (This daemon's clock, whatever the frame's receive time says: the lease rounds compare it.)
  t.received_wall_utime = frame_wall_utime_ > 0 ? frame_wall_utime_ : now_utime();
  if (s.utime > saturating_add(now, config_.max_future_utime())) {
    reject_sample(RejectReason::kFutureTime, sat, s);
    return;
  }
  if (t.on_time_base(s.utime, config_.max_time_jump_utime())) {
    // A base moved forward may put held samples on it.
    if (accept_sample(sat, t, s, receive_utime) && !t.held.empty()) resolve_held(sat, t);
  } else {
    hold_sample(sat, t, s, receive_utime);
  }
}

bool SampleIntake::accept_sample(const std::string& sat, ReceivedSpacecraft& t,
                                 const mag_sample_t& s, int64_t receive_utime) {
  if (t.newest_utime != kNoTime) {
    if (s.utime <= saturating_sub(t.newest_utime, config_.window_utime())) {
      reject_sample(RejectReason::kOlderThanWindow, sat, s);
      return false;
    }
    if (s.utime <= t.newest_utime && is_duplicate(sat, t, s.utime)) {
      reject_sample(RejectReason::kDuplicate, sat, s);
      return false;
    }
  }
  const auto sample = to_reference_sample(s, *field_);
  if (!sample) {
    reject_sample(RejectReason::kReferenceFailed, sat, s);
    return false;
  }
  // Its spacecraft's owner (this daemon or another) filters it once it is stored.
  if (pending_.empty()) first_pending_time_ = std::chrono::steady_clock::now();
  fill_stored_sample(s, sat, *sample, receive_utime, pending_.emplace_back());
  t.stored_bound_utime = std::max(t.stored_bound_utime, s.utime);
  const bool advanced = s.utime > t.newest_utime;
  if (advanced) {
    t.newest_utime = s.utime;
    ++t.advances;
  }
  data_clock_utime_ = std::max(data_clock_utime_, s.utime);
  return advanced;
}

void SampleIntake::hold_sample(const std::string& sat, ReceivedSpacecraft& t, const mag_sample_t& s,
                               int64_t receive_utime) {
  if (t.holds_utime(s.utime)) {
    reject_sample(RejectReason::kDuplicate, sat, s);  // a repeat cannot corroborate itself
    return;
  }
  if (t.held.size() >= static_cast<size_t>(ReceivedSpacecraft::kHeldCapacity)) {
    reject_sample(RejectReason::kTimeJump, sat, t.held.front().sample);
    t.held.erase(t.held.begin());
  }
  if (t.held.empty() && t.newest_utime != kNoTime) {  // (a new spacecraft's first samples: normal)
    warnings_.warn("time_hold",
                   fmt::format("{}: sample at {} held: {} s past the newest sample (waiting for {} "
                               "more to corroborate it)",
                               sat, format_iso8601_utc(s.utime),
                               saturating_sub(s.utime, t.newest_utime) / 1000000,
                               ReceivedSpacecraft::kCorroborating));
  }
  if (t.held.empty() && t.newest_utime == kNoTime) {
    first_holds_.emplace_back(sat, std::chrono::steady_clock::now());
  }
  t.hold(s, receive_utime, frame_counter_);
  const int64_t base = t.corroborated_utime(config_.max_time_jump_utime());
  if (base == kNoTime) return;
  if (t.newest_utime != kNoTime) {
    spdlog::warn("{}: time jump of {} s to {} corroborated by {} samples: accepted", sat,
                 saturating_sub(base, t.newest_utime) / 1000000, format_iso8601_utc(base),
                 t.held.size());
  }
  t.newest_utime = base;
  resolve_held(sat, t);
}

void SampleIntake::resolve_held(const std::string& sat, ReceivedSpacecraft& t) {
  const int64_t max_jump = config_.max_time_jump_utime();
  size_t keep = 0;
  // In place (accept_sample() never adds to the hold): arrival order, no allocation. A sample
  // accepted here may advance the base: the rest of the loop sees the new one.
  for (size_t i = 0; i < t.held.size(); ++i) {
    HeldSample& h = t.held[i];
    if (t.on_time_base(h.sample.utime, max_jump)) {
      accept_sample(sat, t, h.sample, h.receive_utime);
    } else if (t.advances - h.advances_at_hold >= ReceivedSpacecraft::kCorroborating) {
      reject_sample(RejectReason::kTimeJump, sat, h.sample);
    } else {
      if (keep != i) t.held[keep] = std::move(h);
      ++keep;
    }
  }
  t.held.erase(t.held.begin() + static_cast<std::ptrdiff_t>(keep), t.held.end());
  if (t.held.empty()) t.held.shrink_to_fit();  // a hold is rare: give its memory back
}

void SampleIntake::base_from_held(const std::string& sat, ReceivedSpacecraft& t) {
  const int64_t base = t.likeliest_held_utime(config_.max_time_jump_utime());
  if (base == kNoTime) return;
  spdlog::info("{}: time base {} from its {} held first sample(s), uncorroborated (no more came)",
               sat, format_iso8601_utc(base), t.held.size());
  t.newest_utime = base;
  resolve_held(sat, t);
}

void SampleIntake::release_first_holds(std::chrono::steady_clock::time_point now) {
  // first_holds_ is in the order of its times: only its front can be due (O(1) per call).
  const auto max_age = std::chrono::duration<double>(ReceivedSpacecraft::kFirstHoldMax_s);
  size_t due = 0;
  while (due < first_holds_.size() && now - first_holds_[due].second >= max_age) {
    const std::string& sat = first_holds_[due++].first;
    SpacecraftTracker* t = fleet_.find(sat);
    // (Corroborated since, or settled: nothing to do.)
    if (t && t->newest_utime == kNoTime && !t->held.empty()) base_from_held(sat, *t);
  }
  if (due > 0)
    first_holds_.erase(first_holds_.begin(),
                       first_holds_.begin() + static_cast<std::ptrdiff_t>(due));
}

void SampleIntake::settle_held() {
  fleet_.for_each([&](const std::string& sat, ReceivedSpacecraft& t) {
    if (t.newest_utime == kNoTime) base_from_held(sat, t);
    for (const auto& h : t.held) reject_sample(RejectReason::kJumpUnconfirmed, sat, h.sample);
    t.held.clear();
    t.held.shrink_to_fit();
  });
  first_holds_.clear();
}

int64_t SampleIntake::held_samples() {
  int64_t n = 0;
  fleet_.for_each(
      [&](const std::string&, ReceivedSpacecraft& t) { n += static_cast<int64_t>(t.held.size()); });
  return n;
}

bool SampleIntake::try_commit(CommitParticipant& owner) {
  // On a failure the samples (and the owner's writes) stay pending.
  if (!try_commit_step([&] { commit_pending(owner); })) return false;
  spill_full_ = false;
  return true;
}

void SampleIntake::commit_pending(CommitParticipant& owner) {
  // A backlog left by a storage fault goes in transactions of commit_every_samples: each holds
  // the write lock briefly, and on a nearly full disk every chunk that fits is stored. The
  // owner's writes go with the last chunk (its snapshots are published once stored; a filter
  // state then includes exactly the committed samples).
  const auto chunk = static_cast<size_t>(config_.storage.commit_every_samples);
  resolve_commit_in_doubt(owner);
  // Spilled samples are older than the pending ones, and the owner's states include them. Until
  // the file is drained the pending batch queues behind it in the file (one order, and memory
  // stays bounded); the owner's writes wait.
  if (spill_ && spill_->held_samples() > 0) {
    commit_spill(owner, false,
                 std::chrono::steady_clock::now() +
                     std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                         std::chrono::duration<double>(kSpillDrainSlice_s)));
    if (spill_->held_samples() > 0) {
      spill_pending(true);
      return;
    }
  }
  size_t done = 0;
  try {
    while (done < pending_.size() || owner.has_writes()) {
      const size_t n = std::min(chunk, pending_.size() - done);
      const bool last = done + n == pending_.size();
      const auto rows = std::span<const storage::StoredSample>(pending_).subspan(done, n);
      storage::InsertStats stats;
      {
        const auto t0 = std::chrono::steady_clock::now();
        // Every attempt is timed, a failed one too (a lock wait shows as a long commit).
        struct ObserveOnExit {
          CommitLatencyHistogram& histogram;
          std::chrono::steady_clock::time_point t0;
          ~ObserveOnExit() {
            histogram.observe(
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
          }
        } observe{counters_.commit_seconds, t0};
        storage::Transaction tx(db_);
        stats = samples_.insert_batch(rows, &duplicate_rows_, config_.station.id);
        if (last) owner.write();
        try {
          tx.commit();
        } catch (const storage::StorageError& e) {
          if (e.in_doubt_transaction() != 0) {
            in_doubt_ = {e.in_doubt_transaction(), CommitInDoubt::Chunk::kPending, n, stats, last};
          }
          throw;
        }
      }
      pending_chunk_committed(owner, rows, stats, last);
      done += n;
    }
  } catch (const storage::StorageError&) {
    // What was committed leaves the batch; the rest stays pending for the retry.
    pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(done));
    reset_pending_index();
    throw;
  }
  pending_.clear();
  reset_pending_index();
}

void SampleIntake::pending_chunk_committed(CommitParticipant& owner,
                                           std::span<const storage::StoredSample> rows,
                                           const storage::InsertStats& stats,
                                           bool with_owner_writes) {
  owner.samples_committed(rows);
  count_stored(rows, true);
  counters_.stored.fetch_add(stats.inserted, std::memory_order_relaxed);
  // Duplicates the in-memory check could not see (e.g. within one frame).
  if (stats.duplicates > 0) counters_.reject(RejectReason::kDuplicate, stats.duplicates);
  if (with_owner_writes) owner.written();
}

void SampleIntake::spill_chunk_committed(CommitParticipant& owner,
                                         const storage::InsertStats& stats, bool spill_recovered) {
  spill_->commit_read();
  owner.samples_committed(spill_chunk_);
  if (spill_recovered) {
    // Received, counted and checked by the run that spilled them.
    spill_recovered_held_ -= static_cast<int64_t>(spill_chunk_.size());
    counters_.spill_recovered.fetch_add(stats.inserted, std::memory_order_relaxed);
  } else {
    count_stored(spill_chunk_, true);
    counters_.stored.fetch_add(stats.inserted, std::memory_order_relaxed);
    if (stats.duplicates > 0) counters_.reject(RejectReason::kDuplicate, stats.duplicates);
  }
  update_spill_gauges();
}

void SampleIntake::resolve_commit_in_doubt(CommitParticipant& owner) {
  if (in_doubt_.transaction_id == 0) return;
  const bool committed = db_.commit_outcome(in_doubt_.transaction_id) ==
                         storage::Connection::CommitOutcome::kCommitted;
  spdlog::info("the database commit without a reply (transaction {}) {}", in_doubt_.transaction_id,
               committed ? "did commit: its samples are stored" : "did not commit: retrying it");
  const CommitInDoubt doubt = std::exchange(in_doubt_, {});
  if (!committed) return;
  if (doubt.chunk == CommitInDoubt::Chunk::kPending) {
    // (duplicate_rows_ is still that insert's: nothing was inserted since.)
    pending_chunk_committed(owner,
                            std::span<const storage::StoredSample>(pending_).first(doubt.rows),
                            doubt.stats, doubt.with_owner_writes);
    pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(doubt.rows));
    reset_pending_index();
  } else {
    // (spill_chunk_ is still the chunk read for it: a read again returns the same records.)
    spill_chunk_committed(owner, doubt.stats, doubt.chunk == CommitInDoubt::Chunk::kSpillRecovered);
  }
}

bool SampleIntake::spill_pending(bool at_any_size, bool at_exit) {
  if (!spill_ || spill_full_ || pending_.empty()) return false;
  if (!at_any_size && static_cast<int64_t>(pending_.size()) < config_.storage.max_pending_samples) {
    return false;
  }
  // The rows of a commit in doubt stay in memory until it is resolved: they may be stored.
  const size_t keep =
      !at_exit && in_doubt_.transaction_id != 0 && in_doubt_.chunk == CommitInDoubt::Chunk::kPending
          ? in_doubt_.rows
          : 0;
  if (keep >= pending_.size()) return false;
  const auto to_spill = std::span<const storage::StoredSample>(pending_).subspan(keep);
  bool appended = false;
  try {
    appended = spill_->append(to_spill);
  } catch (const SpillError& e) {
    spdlog::error("{}", e.what());
  }
  if (!appended) {
    spill_full_ = true;  // until a commit succeeds
    warnings_.warn(
        "spill_full",
        fmt::format("spill file {} cannot take {} more samples (its size {} bytes, "
                    "[storage] spill_max_bytes {}): they stay in memory, and at "
                    "max_pending_samples intake stops until the database takes them (a "
                    "live feed then overflows its receive queue, counted as "
                    "queue_overflow)",
                    spill_->path(), to_spill.size(), spill_->bytes(), spill_->max_bytes()));
    return false;
  }
  counters_.spilled.fetch_add(static_cast<int64_t>(to_spill.size()), std::memory_order_relaxed);
  warnings_.warn(
      "spill",
      fmt::format("{}: {} pending samples spilled to {} ({} held there, {} bytes)",
                  commit_retry_.failing() ? "database commit failing" : "queued behind the spill",
                  to_spill.size(), spill_->path(), spill_->held_samples(), spill_->bytes()));
  pending_.erase(pending_.begin() + static_cast<std::ptrdiff_t>(keep), pending_.end());
  if (at_exit && in_doubt_.chunk == CommitInDoubt::Chunk::kPending) in_doubt_ = {};
  // What stays (a commit in doubt) waits for its resolution, not for a commit interval: the
  // next spill is due an interval from now, one append for the interval's samples.
  if (keep > 0) first_pending_time_ = std::chrono::steady_clock::now();
  reset_pending_index();
  update_spill_gauges();
  return true;
}

void SampleIntake::commit_spill(CommitParticipant& owner, bool recovered,
                                std::chrono::steady_clock::time_point until) {
  const auto chunk = static_cast<size_t>(config_.storage.commit_every_samples);
  // insert_batch sorts each chunk by (sat_id, utime), the fleet's one key order.
  while (std::chrono::steady_clock::now() < until && (!recovered || spill_recovered_held_ > 0) &&
         spill_->read_chunk(recovered ? std::min<size_t>(chunk, spill_recovered_held_) : chunk,
                            spill_chunk_) > 0) {
    storage::Transaction tx(db_);
    const storage::InsertStats stats =
        samples_.insert_batch(spill_chunk_, &duplicate_rows_, config_.station.id);
    try {
      tx.commit();
    } catch (const storage::StorageError& e) {
      if (e.in_doubt_transaction() != 0) {
        in_doubt_ = {
            e.in_doubt_transaction(),
            recovered ? CommitInDoubt::Chunk::kSpillRecovered : CommitInDoubt::Chunk::kSpill,
            spill_chunk_.size(), stats, false};
      }
      throw;
    }
    spill_chunk_committed(owner, stats, recovered);
  }
}

void SampleIntake::update_spill_gauges() {
  // This run's samples apart (in flight: received = stored + rejected + ... + these).
  counters_.spill_held.store(spill_->held_samples() - spill_recovered_held_,
                             std::memory_order_relaxed);
  counters_.spill_held_earlier.store(spill_recovered_held_, std::memory_order_relaxed);
  counters_.spill_bytes.store(spill_->bytes(), std::memory_order_relaxed);
}

void SampleIntake::allow_retention(const std::string& sat_id, int64_t filtered_utime) {
  SpacecraftTracker* found = fleet_.find(sat_id);
  if (found == nullptr) return;
  ReceivedSpacecraft& t = *found;
  t.retention_edge_utime = filtered_utime;
  if (filtered_utime == kNoTime) return;
  retention_clock_utime_ = std::max(retention_clock_utime_, filtered_utime);
  if (!t.retention_due) {
    t.retention_due = true;
    retention_dirty_.push_back(sat_id);
  }
}

void SampleIntake::run_retention_if_due(bool by_data_time) {
  if (retention_dirty_.empty() || commit_retry_.failing()) return;
  const bool wall_due =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - last_retention_time_)
          .count() >= kRetentionEvery_s;
  const bool data_due = by_data_time && retention_clock_utime_ - last_retention_data_utime_ >=
                                            kRetentionEveryData_utime;
  if (wall_due || data_due) run_retention();
}

void SampleIntake::run_retention() {
  last_retention_time_ = std::chrono::steady_clock::now();
  last_retention_data_utime_ = retention_clock_utime_;
  const int64_t window = config_.window_utime();
  const auto margin = static_cast<int64_t>(config_.storage.retention_margin_hours * 3.6e9);
  const int64_t floor = retention_floor_.load();
  std::vector<std::string> failed;
  for (const auto& sat : retention_dirty_) {
    SpacecraftTracker* found = fleet_.find(sat);
    if (found == nullptr) continue;
    ReceivedSpacecraft& t = *found;
    t.retention_due = false;  // due again when its owner's filter moves on
    // Behind the owner's filter only (file comment); nothing while not owned here.
    if (t.retention_edge_utime == kNoTime || t.newest_utime == kNoTime) continue;
    const int64_t edge = std::min(t.newest_utime, t.retention_edge_utime);
    const int64_t cutoff = std::min(saturating_sub(edge, window + margin), floor);
    try {
      // Nothing stored before the cutoff (a window still filling), or less than a step: no
      // transaction.
      if (t.retained_from_utime == kNoTime) {
        t.retained_from_utime = samples_.oldest_utime(sat).value_or(cutoff);
      }
      if (saturating_sub(cutoff, t.retained_from_utime) < kRetentionStep_utime) continue;
      samples_.delete_before(sat, cutoff, kRetentionChunkRows);
      t.retained_from_utime = cutoff;  // (samples stored older since lower it: count_stored)
    } catch (const storage::StorageError& e) {
      // Nothing is lost by deleting later: kept for the next round.
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      spdlog::error("database: retention of '{}' failed, retried later: {}", sat, e.what());
      t.retention_due = true;
      failed.push_back(sat);
    }
  }
  retention_dirty_.swap(failed);
}

}  // namespace magcal
