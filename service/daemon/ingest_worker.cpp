#include "service/daemon/ingest_worker.hpp"

#include <thread>

#include <spdlog/spdlog.h>

namespace magcal {

IngestWorker::IngestWorker(const DaemonConfig& config, DaemonCounters& counters,
                           std::unique_ptr<ReferenceField> field, Hooks hooks,
                           const StopDeadline* stop)
    : config_(config),
      storage_(config_.storage_capabilities()),
      hooks_(std::move(hooks)),
      // (A server unreachable now: restore() says.)
      db_(storage::open_database(config.storage.db_path, config.database_options())),
      samples_(db_->make_sample_window_store()),
      fleet_(config.ukf.filter, &counters),
      intake_(config_, counters, std::move(field), *db_, *samples_, fleet_, stop),
      owner_(config_, counters, *db_, *samples_, fleet_, hooks_.on_snapshot) {}

IngestWorker::~IngestWorker() = default;

bool IngestWorker::restore() {
  try {
    restore_from_database();
    return true;
  } catch (const storage::StorageError& e) {
    // A start error, unless the engine makes an unreachable server an outage that began before
    // the start and the error is transient (a permanent one: a missing database or role,
    // authentication, a foreign schema).
    if (!storage_.unreachable_at_start_is_outage || !e.transient()) throw;
    const std::string spill = config_.spill_path();
    // (The error names the database.)
    spdlog::warn(
        "database unreachable at start: magcald receives anyway, holds the samples{} and "
        "commits them once it answers (retried as a failing commit; [storage] {} = {:.0f} s, "
        "then exit 3): {}",
        spill.empty() ? "" : " (each commit interval's batch spilled to " + spill + ")",
        config_.storage_max_failure_key(), config_.storage_max_failure_s(), e.what());
    intake_.commit_step_failed(e);
    return false;
  }
}

void IngestWorker::restore_from_database() {
  intake_.restore(owner_);
  restored_ = true;  // (the lease round may commit: commit() must not restore again)
  // A daemon alone takes every spacecraft now; after a restart its own leases at once.
  lease_round();
  if (fleet_.size() > 0) {
    spdlog::info("restored {} spacecraft from {} ({} owned here, of {} live station(s))",
                 fleet_.size(), db_->name(), owner_.owned_count(), owner_.live_stations());
  }
}

bool IngestWorker::try_restore() {
  return restored_ || intake_.try_commit_step([this] {
    try {
      restore_from_database();
    } catch (const storage::StorageError& e) {
      // (Not a StorageError: past the commit path's retry, which would call it an outage.)
      if (!e.transient()) {
        throw RefusedAtFirstContact(fmt::format(
            "database {} refused magcald when it first answered (unreachable at start; at start "
            "this is a start error, exit 2): {}",
            db_->name(), e.what()));
      }
      throw;
    }
  });
}

void IngestWorker::lease_round() {
  owner_.register_spacecraft(intake_.take_new_spacecraft());
  // Over its share, a station hands over the excess once its snapshots and states are
  // committed (one attempt: never waits through an outage).
  if (owner_.begin_lease_round()) owner_.hand_over_excess(commit_once());
  owner_.end_lease_round();
  // Not received here (yet): its time base from the stored window, before its filter starts.
  for (const auto& sat : owner_.acquired_unreceived()) {
    try {
      intake_.restore_spacecraft(sat);
    } catch (const storage::StorageError& e) {
      owner_.takeover_failed(sat, e);
    }
  }
  owner_.take_over_acquired();
  intake_.set_other_stations_live(owner_.live_stations() > 1);
}

void IngestWorker::maintain_leases() {
  lease_round();
}

void IngestWorker::leave_fleet() {
  save_filter_states();  // commits first
  // Storage failing (an outage): the leases and the heartbeat run out by themselves; never
  // reached: none was taken.
  if (!restored_ || uncommitted()) return;
  owner_.release_all();
}

void IngestWorker::track_all_now() {
  if (!restored_) return;  // nothing owned
  // A replay can end before its next lease round (every lease_s / 3; a fast replay takes
  // seconds): the free leases of the spacecraft it received are taken now, up to its share
  // (which the other stations' spacecraft, registered since its last round, may have raised),
  // so that their filters run before it stops, not at some daemon's next start.
  if (replay_ended_.load()) {
    do {
      lease_round();
    } while (owner_.next_lease_round() == std::chrono::steady_clock::time_point{});  // more
  }
  filter(true);
  intake_.retention_at_next_commit();
}

void IngestWorker::process(const IngestItem& item) {
  intake_.begin_frame();
  for (size_t i = 0; i < item.samples.size(); ++i) {
    intake_.ingest(item.samples[i], item.batch_sat_id, item.receive_utime);
    // A new spacecraft gets its lease row (and, when this daemon's share allows, its owner
    // here) at the next commit, before its first samples are read back.
    if (intake_.has_new_spacecraft()) owner_.register_spacecraft(intake_.take_new_spacecraft());
    if (intake_.batch_full()) {
      try {
        commit();
      } catch (...) {
        ingest_without_commit(item, i + 1);
        throw;
      }
    }
  }
}

void IngestWorker::ingest_without_commit(const IngestItem& item, size_t first) {
  for (size_t i = first; i < item.samples.size(); ++i) {
    intake_.ingest(item.samples[i], item.batch_sat_id, item.receive_utime);
  }
}

void IngestWorker::commit_if_due() {
  owner_.apply_reanchors_if_posted();
  const auto now = std::chrono::steady_clock::now();
  intake_.release_first_holds(now);
  if (intake_.has_new_spacecraft()) owner_.register_spacecraft(intake_.take_new_spacecraft());
  // Not reached since start: the restore goes first, tried on the commit path's cadence also
  // with nothing to commit (a station between passes); meanwhile no lease, no filter.
  const bool restored = try_restore();
  if (restored && now >= owner_.next_lease_round()) lease_round();
  if (uncommitted()) {
    const double age_ms =
        std::chrono::duration<double, std::milli>(now - intake_.first_pending_time()).count();
    if (age_ms >= config_.storage.commit_every_ms || intake_.pending_samples() == 0) commit();
  }
  if (restored && !intake_.commit_failing()) filter(false);
  run_retention_if_due(false);
}

void IngestWorker::commit() {
  // Commits failing (an outage where the engine spills): the batch goes to the spill file at
  // once, written and fdatasync'ed, so a crash during an outage loses no more than one commit
  // interval, as outside one (memory is no safe place to wait out an outage); intake goes on.
  if (intake_.commit_failing()) intake_.spill_pending(true);
  if (!try_restore()) return;
  // The round (file comment): the samples, then what the owned filters made of them (snapshots,
  // states), so that after commit() everything they produced from committed samples is stored
  // too (not while the spill drains: one slice per call).
  for (int round = 0; round < 2; ++round) {
    if (!uncommitted() || (round > 0 && intake_.spill_held() > 0)) break;
    if (!commit_pending()) return;  // failing: everything stays pending
    if (std::chrono::steady_clock::now() >= owner_.next_lease_round()) lease_round();
    filter(false);
  }
  // Retention by data time too, so a fast replay keeps its windows as a live feed would.
  run_retention_if_due(true);
}

bool IngestWorker::commit_pending() {
  if (!intake_.try_commit(owner_)) return false;
  // Their samples are committed now; requested before retention runs (their floor).
  if (!uncommitted()) request_refits(owner_.take_deferred_refits());
  return true;
}

bool IngestWorker::commit_once() {
  if (intake_.commit_failing()) intake_.spill_pending(true);
  if (!try_restore()) return false;
  if (uncommitted() && !commit_pending()) return false;
  run_retention_if_due(true);
  return !uncommitted();
}

bool IngestWorker::commit_for_refit() {
  if (!storage_.commit_may_block) return commit_once();
  while (uncommitted()) {
    await_commit_attempt();
    commit_once();
  }
  return true;
}

void IngestWorker::filter(bool drain) {
  owner_.track_owned(drain);
  while (owner_.refits_waiting()) {
    // A refit reads the committed window: everything up to the sample its filter stopped at
    // is committed first.
    const bool committed = commit_for_refit();
    request_refits(owner_.refits_after_commit(committed));
    owner_.resume_tracking();
  }
}

void IngestWorker::request_refits(const std::vector<DueRefit>& refits) {
  if (!hooks_.on_refit_due) return;
  for (const auto& r : refits) hooks_.on_refit_due(r.sat_id, r.t_ref_utime, r.trigger);
}

void IngestWorker::run_retention_if_due(bool by_data_time) {
  for (const auto& [sat, utime] : owner_.take_retention_edges()) {
    intake_.allow_retention(sat, utime);
  }
  intake_.run_retention_if_due(by_data_time);
}

void IngestWorker::flush() {
  while (uncommitted()) {
    await_commit_attempt();
    commit();
  }
}

void IngestWorker::await_commit_attempt() {
  if (!intake_.commit_due()) std::this_thread::sleep_until(intake_.next_commit_attempt());
}

void IngestWorker::flush_at_stop() {
  if (storage_.spill_during_outage && uncommitted()) {
    commit();
    if (intake_.commit_failing() &&
        (intake_.pending_samples() == 0 || intake_.spill_pending(true, /*at_exit=*/true))) {
      owner_.drop_unstored_writes();
      return;
    }
  }
  flush();
}

int64_t IngestWorker::spill_all_pending() {
  const int64_t n = intake_.pending_samples();
  return intake_.spill_pending(true, /*at_exit=*/true) ? n : 0;
}

void IngestWorker::save_filter_states() {
  // A saved state must not include samples that are not stored: after a crash they come again
  // (re-replay, recorder dump) and the restored filter would use them twice.
  commit();
  // Storage failing: saved once the commit goes through (never reached: nothing to save).
  if (!restored_ || uncommitted()) return;
  owner_.save_dirty_states();
}

}  // namespace magcal
