#include "service/daemon/ownership/owned_spacecraft_tracker.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include <spdlog/spdlog.h>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/temperature_model.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/station_settings.hpp"

namespace magcal {
namespace {

constexpr int64_t kNoTime = OwnedSpacecraft::kNoTime;
// Jobs of a spacecraft looked at for a refit still running elsewhere (newest first).
constexpr int kRecentJobs = 8;

// This process's id in the stations table: random per start.
std::string random_instance_id() {
  std::random_device rd;
  const uint64_t id =
      (static_cast<uint64_t>(rd()) << 32) ^ rd() ^ static_cast<uint64_t>(::getpid());
  return fmt::format("{:016x}", id);
}

int64_t snapshot_period_utime(const DaemonConfig& c) {
  return std::max<int64_t>(1, static_cast<int64_t>(c.ukf.snapshot_every_s * 1e6));
}

// Snapshots fall on multiples of the period in data time (UTC-aligned: every minute on the
// minute by default), so that every owner of a spacecraft, after a restart or a takeover, keeps
// one series: the first boundary after `utime`.
int64_t next_snapshot_boundary(int64_t utime, const DaemonConfig& c) {
  const int64_t period = snapshot_period_utime(c);
  const int64_t floor = utime >= 0 ? utime / period : (utime - period + 1) / period;
  return saturating_add(floor * period, period);
}

}  // namespace

OwnedSpacecraftTracker::OwnedSpacecraftTracker(const DaemonConfig& config, DaemonCounters& counters,
                                               storage::Connection& db,
                                               storage::SampleWindowStore& samples,
                                               SpacecraftFleet& fleet, SnapshotHook on_snapshot)
    : config_(config),
      counters_(counters),
      on_snapshot_(std::move(on_snapshot)),
      db_(db),
      samples_(samples),
      history_(db.make_calibration_history()),
      filter_states_(db.make_filter_state_store()),
      jobs_(db.make_refit_job_log()),
      leases_(db.make_lease_store()),
      fleet_(fleet),
      instance_(random_instance_id()),
      settings_watch_(config.station.id, station_settings(config.result_settings()), counters) {
  if (config.data_clock()) {
    const auto minute = parse_daily_time_utc(config.refit.daily_at_utc);
    data_schedule_ = RefitSchedule{minute.value_or(120), config.refit.every_hours};
  }
}

bool OwnedSpacecraftTracker::refit_running_elsewhere(const std::string& sat_id) {
  for (const auto& j : jobs_->recent(sat_id, kRecentJobs)) {
    if (j.outcome == storage::job_outcome::kRunning && !j.claimed_by.empty() &&
        j.claimed_by != config_.station.id) {
      return true;
    }
  }
  return false;
}

void OwnedSpacecraftTracker::register_spacecraft(std::vector<std::string> sat_ids) {
  if (sat_ids.empty()) return;
  unregistered_.insert(unregistered_.end(), std::make_move_iterator(sat_ids.begin()),
                       std::make_move_iterator(sat_ids.end()));
  next_lease_round_ = {};  // its lease row, and maybe its owner here, at once
}

size_t OwnedSpacecraftTracker::owned_count() {
  size_t owned = 0;
  fleet_.for_each([&](const std::string&, OwnedSpacecraft& t) { owned += t.owned ? 1 : 0; });
  return owned;
}

void OwnedSpacecraftTracker::take_over(const std::string& sat, SpacecraftTracker& record,
                                       int64_t epoch) {
  OwnedSpacecraft& t = record;
  t.ukf = MagnetometerUkf(fleet_.options());
  t.temperature = TemperatureCorrection{};
  t.anchor_calibration_id = 0;
  t.deferred_reanchor_id = 0;
  t.deferred_reanchor_utime = kNoTime;
  t.state_dirty = t.state_due = false;
  // Before the state is read: a refit that ends after that read is caught by the poll.
  if (refit_running_elsewhere(sat)) refits_elsewhere_.push_back(sat);
  restore_filter(sat, t);
  const FilterState& st = t.ukf.state();
  // The filter goes on after its state's last sample (track_union()); with no state, from the
  // oldest stored one.
  t.filtered_utime = st.has_time ? st.last_utime : kNoTime;
  const auto newest = samples_.newest_utime(sat);
  t.union_newest_utime = newest.value_or(kNoTime);
  t.union_grew_wall_utime = now_utime();
  t.union_due = true;
  t.union_seq = SeqGapCounter{};
  // The next early refit follows from the database: the latest refit's sample count; the
  // samples counted are those the state has taken.
  const auto latest_refit = history_->latest_refit(sat);
  t.n_samples = t.filtered_utime == kNoTime
                    ? 0
                    : samples_.count_in_window(sat, std::numeric_limits<int64_t>::min() / 2,
                                               saturating_add(t.filtered_utime, 1));
  t.next_early_refit_samples =
      config_.early_refits().next_after(latest_refit ? latest_refit->n_samples : 0);
  // The snapshot after the state's last sample (snapshots are committed with the state), on
  // the grid every owner uses.
  t.next_snapshot_utime =
      t.filtered_utime == kNoTime ? kNoTime : next_snapshot_boundary(t.filtered_utime, config_);
  t.data_refits.reset();
  if (data_schedule_) {
    t.data_refits.emplace(*data_schedule_);
    // Its clock resumes after the last scheduled refit that ran to its end (or at its oldest
    // stored sample before any): a later due time had its samples committed, but its refit
    // was interrupted or never started, so the filter's next sample runs it (file comment).
    if (newest) {
      const int64_t resume = jobs_->newest_finished_scheduled_utime(sat).value_or(
          samples_.oldest_utime(sat).value_or(*newest));
      t.data_refits->advance(std::min(resume, *newest));
    }
  }
  t.owned = true;
  t.lease_epoch = epoch;
  {
    std::lock_guard lock(owned_mutex_);
    owned_names_.insert(sat);
  }
  t.counters->owned.store(true, std::memory_order_relaxed);
  spdlog::info("{}: owned here (lease epoch {}); its UKF goes on from {}", sat, epoch,
               t.filtered_utime == kNoTime ? std::string("its first stored sample")
                                           : format_iso8601_utc(t.filtered_utime));
}

void OwnedSpacecraftTracker::give_up(const std::string& sat, OwnedSpacecraft& t) {
  t.owned = false;
  t.lease_epoch = 0;
  t.state_due = t.state_dirty = false;
  t.data_refits.reset();
  t.next_early_refit_samples = 0;
  t.ukf = MagnetometerUkf(fleet_.options());  // nothing of the old filter is used again
  std::erase(states_due_, sat);
  std::erase(refits_elsewhere_, sat);
  std::erase_if(pending_snapshots_, [&](const PendingSnapshot& p) { return p.sat_id == sat; });
  retention_edge(sat, kNoTime);  // its new owner deletes behind its own filter
  {
    std::lock_guard lock(owned_mutex_);
    owned_names_.erase(sat);
  }
  t.counters->owned.store(false, std::memory_order_relaxed);
}

bool OwnedSpacecraftTracker::owns(const std::string& sat_id) const {
  std::lock_guard lock(owned_mutex_);
  return owned_names_.count(sat_id) > 0;
}

OwnedSpacecraftTracker::~OwnedSpacecraftTracker() {
  if (lease_round_failing_) counters_.storage_path_recovered();
}

void OwnedSpacecraftTracker::restore_filter(const std::string& sat, OwnedSpacecraft& t) {
  const auto reanchor_id = jobs_->newest_reanchor_calibration_id(sat);
  std::optional<int64_t> anchor_id = 0;  // none (the filter starts afresh)
  if (const auto stored = filter_states_->load(sat, "ukf")) {
    FilterState st;
    if (const std::string why = filter_state_from_stored(*stored, st); why.empty()) {
      // Started or still collecting: the state holds every sample up to last_utime (in x
      // and P, or in the start's moments); the filter goes on after it.
      t.ukf.restore(st);
      anchor_id = stored->anchor_calibration_id;
    } else {
      spdlog::warn("{}: stored filter state unreadable ({}); re-running the UKF over the window",
                   sat, why);
    }
  }
  // The samples after the state were filtered with the temperature model of the refit it is
  // anchored on: so are they now. (A state saved before schema 4 does not say which refit it
  // has: taken as the newest, it was saved at a clean stop, after the re-anchor.)
  t.anchor_calibration_id = anchor_id.value_or(reanchor_id.value_or(0));
  if (t.anchor_calibration_id > 0) {
    if (const auto rec = history_->get(t.anchor_calibration_id))
      t.temperature.take_from(result_from_record(*rec), rec->id);
  }
  if (reanchor_id) catch_up_reanchor(sat, t, *reanchor_id);
}

void OwnedSpacecraftTracker::catch_up_reanchor(const std::string& sat, OwnedSpacecraft& t,
                                               int64_t reanchor_id) {
  if (reanchor_id <= t.anchor_calibration_id) return;
  // An accepted refit the filter was not re-anchored on (its previous owner died, or handed it
  // over, before it stored the re-anchored state): applied after the samples up to the refit's
  // time, where the uninterrupted filter took it (the refit's estimate includes them:
  // re-anchoring before them would count them twice).
  t.deferred_reanchor_id = reanchor_id;
  if (const auto rec = history_->get(reanchor_id)) {
    spdlog::info(
        "{}: the UKF state predates the accepted refit of {}: re-anchored on it from there", sat,
        format_iso8601_utc(rec->utime));
    t.deferred_reanchor_utime = rec->utime;
    const FilterState& st = t.ukf.state();
    if (st.has_time && st.last_utime >= rec->utime) apply_deferred_reanchor(sat, t);
  }
}

void OwnedSpacecraftTracker::apply_deferred_reanchor(const std::string& sat, OwnedSpacecraft& t) {
  const int64_t id = t.deferred_reanchor_id;
  t.deferred_reanchor_id = 0;
  t.deferred_reanchor_utime = kNoTime;
  if (const auto rec = history_->get(id)) reanchor(sat, t, result_from_record(*rec), rec->id);
}

void OwnedSpacecraftTracker::maybe_snapshot(const std::string& sat_id, OwnedSpacecraft& t,
                                            int64_t utime) {
  const int64_t period = snapshot_period_utime(config_);
  if (t.next_snapshot_utime == kNoTime) {
    t.next_snapshot_utime = next_snapshot_boundary(utime, config_);
    return;
  }
  // Every period once the filter has started; each snapshot carries the evidence of its own
  // period. While it still collects for its start from data it has no estimate at all, so
  // nothing is stored or published (a row would need a bias, and 0 +- prior is not one).
  if (utime < t.next_snapshot_utime || !t.ukf.state().has_time) return;
  t.next_snapshot_utime += (saturating_sub(utime, t.next_snapshot_utime) / period + 1) * period;
  if (!t.ukf.state().initialized) return;
  CalibrationResult snap = t.ukf.snapshot_and_reset_period();
  snap.utime = utime;
  if (snap.window_end_utime == 0) snap.window_end_utime = utime;
  if (snap.window_start_utime == 0) snap.window_start_utime = t.ukf.state().first_utime;
  // Online results get the batch gates (residual rms of the period, Fisher condition of the
  // accumulated information, bounds). An estimate that is not ok (still collecting for its
  // start, inconsistent, unobservable) is never accepted: operators must not act on it.
  GateVerdict verdict = evaluate_gates(snap, GateInputs{}, config_.gates);
  reject_unless_ok(snap, verdict);
  apply_verdict(snap, verdict);
  t.temperature.describe(snap);  // its bias is the bias at the anchor refit's T0
  pending_snapshots_.push_back(
      {sat_id, std::move(snap), t.temperature.refit_id, ++snapshots_made_});
  mark_state_due(sat_id, t);
}

void OwnedSpacecraftTracker::mark_state_due(const std::string& sat_id, OwnedSpacecraft& t) {
  if (t.state_due) return;
  t.state_due = true;
  states_due_.push_back(sat_id);
}

storage::FilterState OwnedSpacecraftTracker::stored_state(const std::string& sat_id,
                                                          const OwnedSpacecraft& t) const {
  storage::FilterState st = stored_filter_state(sat_id, "ukf", t.ukf.state());
  st.anchor_calibration_id = t.anchor_calibration_id;
  return st;
}

void OwnedSpacecraftTracker::write() {
  fence_owned_writes();
  // One call each (a few statements on PostgreSQL instead of a round trip per row).
  snapshot_records_.clear();
  for (const auto& p : pending_snapshots_) {
    storage::CalibrationRecord& rec =
        snapshot_records_.emplace_back(record_from_result(p.sat_id, p.result));
    rec.temperature_model_refit_id = p.temperature_model_refit_id;
  }
  history_->append_all(snapshot_records_);
  due_states_.clear();
  for (const auto& sat : states_due_) {
    if (const SpacecraftTracker* t = fleet_.find(sat)) due_states_.push_back(stored_state(sat, *t));
  }
  filter_states_->save_all(due_states_);
  written_snapshot_number_ = pending_snapshots_.empty() ? 0 : pending_snapshots_.back().number;
  written_states_ = states_due_;
}

void OwnedSpacecraftTracker::written() {
  for (const auto& sat : written_states_) {
    if (SpacecraftTracker* t = fleet_.find(sat)) t->state_due = t->state_dirty = false;
    std::erase(states_due_, sat);
  }
  written_states_.clear();
  // (In the order made: those written are a prefix.)
  const auto end =
      std::find_if(pending_snapshots_.begin(), pending_snapshots_.end(),
                   [&](const PendingSnapshot& p) { return p.number > written_snapshot_number_; });
  if (end != pending_snapshots_.begin()) {
    counters_.snapshots.fetch_add(static_cast<int64_t>(end - pending_snapshots_.begin()));
    if (on_snapshot_) {
      for (auto p = pending_snapshots_.begin(); p != end; ++p) on_snapshot_(p->sat_id, p->result);
    }
    pending_snapshots_.erase(pending_snapshots_.begin(), end);
  }
  written_snapshot_number_ = 0;
}

void OwnedSpacecraftTracker::samples_committed(std::span<const storage::StoredSample> rows) {
  const std::string* last = nullptr;
  for (const auto& row : rows) {
    if (last != nullptr && *last == row.sat_id) continue;
    last = &row.sat_id;
    if (SpacecraftTracker* t = fleet_.find(*last); t != nullptr && t->owned) t->union_due = true;
  }
}

void OwnedSpacecraftTracker::drop_unstored_writes() {
  if (!pending_snapshots_.empty()) {
    spdlog::warn(
        "{} UKF snapshots not stored: the database commit fails at shutdown (the "
        "spilled samples are committed at the next start)",
        pending_snapshots_.size());
  }
  pending_snapshots_.clear();
  // Not saved: the next start re-runs each filter over the samples newer than its state.
  for (const auto& sat : states_due_) {
    if (SpacecraftTracker* t = fleet_.find(sat)) t->state_due = false;
  }
  states_due_.clear();
}

void OwnedSpacecraftTracker::fence_owned_writes() {
  // Only while the lease is still this daemon's (on PostgreSQL its row stays locked until the
  // commit, so a takeover waits for it): a daemon that stalled past its lease writes nothing.
  std::vector<std::string> lost;
  std::vector<storage::LeaseStore::Held> held;  // checked in one statement
  auto check = [&](const std::string& sat) {
    const SpacecraftTracker* t = fleet_.find(sat);
    if (t == nullptr || !t->owned) {
      lost.push_back(sat);
    } else {
      held.push_back({sat, t->lease_epoch});
    }
  };
  for (const auto& p : pending_snapshots_) check(p.sat_id);
  for (const auto& sat : states_due_) check(sat);
  auto by_sat = [](const auto& a, const auto& b) { return a.sat_id < b.sat_id; };
  std::sort(held.begin(), held.end(), by_sat);
  held.erase(std::unique(held.begin(), held.end(),
                         [](const auto& a, const auto& b) { return a.sat_id == b.sat_id; }),
             held.end());
  for (auto& sat : leases_->not_held(config_.station.id, held)) lost.push_back(std::move(sat));
  std::sort(lost.begin(), lost.end());
  lost.erase(std::unique(lost.begin(), lost.end()), lost.end());
  for (const auto& sat : lost) {
    spdlog::warn(
        "{}: lease lost before its snapshots were stored: dropped (the new owner makes "
        "them)",
        sat);
    counters_.leases_lost.fetch_add(1, std::memory_order_relaxed);
    if (SpacecraftTracker* t = fleet_.find(sat)) give_up(sat, *t);
  }
}

void OwnedSpacecraftTracker::save_dirty_states() {
  std::vector<OwnedSpacecraft*> saved;
  try {
    storage::Transaction tx(db_);
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
      if (!t.owned || !t.state_dirty) return;
      // Lost: the next round gives it up.
      if (!leases_->holds(sat, config_.station.id, t.lease_epoch)) return;
      filter_states_->save(stored_state(sat, t));
      saved.push_back(&t);
    });
    tx.commit();
  } catch (const storage::StorageError& e) {
    // Still dirty: saved next time. Without it a restart re-runs the UKF over the stored window.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    spdlog::error("database: filter states not saved, retried later: {}", e.what());
    return;
  }
  for (OwnedSpacecraft* t : saved) t->state_dirty = false;
  if (!saved.empty()) spdlog::debug("saved {} filter states", saved.size());
}

void OwnedSpacecraftTracker::post_reanchor(const std::string& sat_id,
                                           const CalibrationResult& refit, int64_t calibration_id) {
  std::lock_guard lock(reanchor_mutex_);
  reanchors_.push_back({sat_id, refit, calibration_id});
  have_reanchors_.store(true, std::memory_order_release);
}

void OwnedSpacecraftTracker::apply_reanchors() {
  std::vector<Reanchor> due_reanchors;
  {
    std::lock_guard lock(reanchor_mutex_);
    due_reanchors.swap(reanchors_);
    have_reanchors_.store(false, std::memory_order_release);
  }
  for (const auto& r : due_reanchors) {
    // (A spacecraft handed over meanwhile: its new owner re-anchors from the database.)
    SpacecraftTracker* t = fleet_.find(r.sat_id);
    if (t != nullptr && t->owned) reanchor(r.sat_id, *t, r.refit, r.calibration_id);
  }
}

void OwnedSpacecraftTracker::reanchor(const std::string& sat, OwnedSpacecraft& t,
                                      const CalibrationResult& refit, int64_t calibration_id) {
  if (!refit.covariance.allFinite()) return;
  // estimation.md 3a: the online tracker continues from the accepted batch estimate.
  // reanchor() keeps the filter's time, counters and accumulated information (and starts a
  // filter still collecting for its start from data); the refit's effective noise seeds the
  // adaptive noise estimate (estimation.md 7). The seed is the residual rms of |B_cal| - |h|
  // under the 9-parameter model the filter uses, not the refit's noise_scale: when the refit
  // used its model extension, that scale describes a smaller (extended-model) residual, and a
  // filter seeded with it finds itself inconsistent and re-opens its covariance (measured:
  // noise 3.7 nT seeded vs 6.5 nT seen, NIS 3-5, then a 20 nT drift on the orbit normal).
  // A refit with a bias rate gives the bias at its window's end: moved to the filter's time, and
  // the filter predicts the bias with that rate from there (seed_bias_rate(); zero clears it).
  const CalibrationResult anchor =
      at_utime(refit, std::max(t.ukf.state().last_utime, refit.window_end_utime));
  t.ukf.reanchor(anchor.parameters.packed(), anchor.covariance, refit.model_error_covariance());
  t.ukf.seed_bias_rate(refit.bias_rate_nT_per_h, refit.bias_rate_covariance);
  // Its bias is the bias at the refit's T0 when the refit has a temperature model: from now on
  // the samples are corrected to T0 (and without one, no longer corrected).
  t.temperature.take_from(refit, calibration_id);
  if (std::isfinite(refit.residual_rms_nT) && refit.residual_rms_nT > 0.0) {
    t.ukf.seed_noise(refit.residual_rms_nT);
  }
  t.anchor_calibration_id = calibration_id;
  t.state_dirty = true;
  mark_state_due(sat, t);  // stored with the next commit
  spdlog::info("{}: UKF re-anchored on the accepted {} refit of {}", sat, refit.method,
               format_iso8601_utc(refit.utime));
}

}  // namespace magcal
