// OwnedSpacecraftTracker's filters: the union of all stations' stored samples read back in time
// order and run through each owned spacecraft's UKF, with its snapshots and refit triggers. A
// pass stops where a refit falls due (refits_waiting()): the worker commits, asks for the
// refits, and the pass resumes at the next sample.
#include <algorithm>
#include <limits>

#include <spdlog/spdlog.h>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ownership/owned_spacecraft_tracker.hpp"

namespace magcal {
namespace {

constexpr int64_t kNoTime = OwnedSpacecraft::kNoTime;
// While other stations are live, the owner looks for their samples this often (wall time).
constexpr double kUnionPoll_s = 1.0;
// Spacecraft whose new samples one statement reads (SampleWindowStore::read_windows).
constexpr size_t kUnionReadsPerStatement = 64;

}  // namespace

void OwnedSpacecraftTracker::track_owned(bool drain) {
  const auto now = std::chrono::steady_clock::now();
  // Every kUnionPoll_s: while other stations are live, every owned spacecraft (their samples);
  // alone, those with samples still behind the reorder horizon once it has been quiet for the
  // reorder delay (the end of a pass: before that a read takes nothing new). Otherwise this
  // station's commits say when.
  const bool due_poll = !drain && now >= next_union_poll_;
  if (due_poll) {
    next_union_poll_ = now + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                 std::chrono::duration<double>(kUnionPoll_s));
  }
  const bool poll_all = drain || (due_poll && live_stations_ > 1);
  const int64_t quiet_since_utime = saturating_sub(now_utime(), config_.reorder_delay_utime());
  auto due = [&](const OwnedSpacecraft& t) {
    return t.union_due || poll_all ||
           (due_poll && t.union_newest_utime != kNoTime &&
            (t.filtered_utime == kNoTime || t.union_newest_utime > t.filtered_utime) &&
            t.union_grew_wall_utime <= quiet_since_utime);
  };
  union_due_sats_.clear();
  fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
    if (t.owned && due(t)) union_due_sats_.push_back(&sat);  // (map keys: stable)
  });
  pass_ = Pass{};
  pass_.drain = drain;
  stop_ = RefitStop{};
  run_pass();
}

void OwnedSpacecraftTracker::read_pass_batch() {
  const size_t begin = pass_.sat;
  const size_t n = std::min(kUnionReadsPerStatement, union_due_sats_.size() - begin);
  // Their samples after the filter.
  union_requests_.clear();
  for (size_t i = begin; i < begin + n; ++i) {
    OwnedSpacecraft& t = *fleet_.find(*union_due_sats_[i]);
    t.union_due = false;  // (again once a commit meanwhile stores more of it)
    const int64_t from = t.filtered_utime == kNoTime ? std::numeric_limits<int64_t>::min() / 2
                                                     : t.filtered_utime + 1;
    union_requests_.push_back({*union_due_sats_[i], from, std::numeric_limits<int64_t>::max()});
  }
  samples_.read_windows(union_requests_, union_rows_, union_row_ends_);
  pass_.batch_begin = begin;
  pass_.batch_end = begin + n;
}

void OwnedSpacecraftTracker::run_pass() {
  try {
    for (; pass_.sat < union_due_sats_.size(); ++pass_.sat, pass_.sat_started = false) {
      if (pass_.sat == pass_.batch_end) read_pass_batch();
      const std::string& sat = *union_due_sats_[pass_.sat];
      if (!track_union(sat, *fleet_.find(sat))) return;  // stopped at a refit
    }
  } catch (const storage::StorageError& e) {
    // The filters wait where they are (a database outage): read again once commits go through.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    fleet_.for_each([](const std::string&, OwnedSpacecraft& t) { t.union_due = t.owned; });
    warnings_.warn("track", fmt::format("database: the owned filters could not read the stored "
                                        "samples, retried: {}",
                                        e.what()));
  }
  pass_.sat = union_due_sats_.size();
  stop_ = RefitStop{};
}

bool OwnedSpacecraftTracker::track_union(const std::string& sat, OwnedSpacecraft& t) {
  const size_t i = pass_.sat - pass_.batch_begin;
  const size_t rows_end = union_row_ends_[i];
  if (!pass_.sat_started) {
    pass_.sat_started = true;
    pass_.row = i == 0 ? 0 : union_row_ends_[i - 1];
    // An accepted refit posted meanwhile applies before the samples committed since.
    apply_reanchors_if_posted();
    if (!t.owned || pass_.row == rows_end) return true;
    const int64_t now = now_utime();
    const int64_t newest = union_rows_[rows_end - 1].utime;
    if (newest > t.union_newest_utime) {
      t.union_newest_utime = newest;
      t.union_grew_wall_utime = now;
    }
    // Samples of another station may still come for the last reorder_delay of data time; once
    // none came for that long in wall time, the pass is over.
    const bool quiet = now - t.union_grew_wall_utime >= config_.reorder_delay_utime();
    pass_.horizon_utime =
        pass_.drain || quiet ? newest : saturating_sub(newest, config_.reorder_delay_utime());
    pass_.state_was_due = t.state_due;
  }
  for (; pass_.row < rows_end; ++pass_.row) {
    const storage::StoredSample& row = union_rows_[pass_.row];
    if (row.utime > pass_.horizon_utime) break;
    if (!t.owned) return true;  // lost during a commit for a refit
    if (t.deferred_reanchor_utime != kNoTime && row.utime > t.deferred_reanchor_utime) {
      apply_deferred_reanchor(sat, t);
    }
    const CalibrationSample sample = calibration_sample_from_stored(row);
    if (!t.update_filter(sample)) {
      warnings_.warn("no_temperature",
                     fmt::format("{}: sample at {} without a temperature (none within {} s): "
                                 "stored, not used by the UKF, whose anchor refit models the "
                                 "temperature",
                                 sat, format_iso8601_utc(row.utime),
                                 TemperatureCorrection::kTemperatureHoldMax_utime / 1000000));
    }
    t.state_dirty = true;
    counters_.ukf_updates.fetch_add(1, std::memory_order_relaxed);
    t.filtered_utime = row.utime;
    ++t.n_samples;
    if (const int64_t missing = t.union_seq.observe(row.seq); missing > 0 && live_stations_ > 1) {
      // No station delivered them (or one did too late for the filter).
      counters_.missing_by_seq.fetch_add(missing, std::memory_order_relaxed);
      t.counters->missing.fetch_add(missing, std::memory_order_relaxed);
    }
    maybe_snapshot(sat, t, row.utime);
    if (stop_for_refits(sat, t)) return false;  // resume_tracking() goes on after this row
    // A replay waits for the refits it triggers: their re-anchor applies from the next sample.
    apply_reanchors_if_posted();
    pass_.state_was_due = pass_.state_was_due || t.state_due;
  }
  if (!t.owned) return true;
  // A state due here (a snapshot, a re-anchor) but stored by a commit for a refit above goes in
  // again with every sample read now: a restart then re-runs none of them.
  if (pass_.state_was_due) mark_state_due(sat, t);
  // Its retention follows the filter.
  retention_edge(sat, t.filtered_utime);
  return true;
}

bool OwnedSpacecraftTracker::stop_for_refits(const std::string& sat_id, OwnedSpacecraft& t) {
  stop_.early = t.next_early_refit_samples > 0 && t.n_samples >= t.next_early_refit_samples &&
                t.ukf.initialized() && t.filtered_utime != kNoTime;
  stop_.scheduled_utimes.clear();
  if (data_schedule_ && t.data_refits && t.filtered_utime != kNoTime) {
    const int64_t skipped_before = t.data_refits->skipped();
    stop_.scheduled_utimes = t.data_refits->advance(t.filtered_utime);
    if (t.data_refits->skipped() != skipped_before) {
      warnings_.warn("refits_skipped",
                     fmt::format("{}: data clock jumped to {}: {} scheduled refits skipped, only "
                                 "the latest runs",
                                 sat_id, format_iso8601_utc(t.filtered_utime),
                                 t.data_refits->skipped() - skipped_before));
    }
  }
  stop_.waiting = stop_.early || !stop_.scheduled_utimes.empty();
  if (stop_.waiting) stop_.sat_id = sat_id;
  return stop_.waiting;
}

std::vector<DueRefit> OwnedSpacecraftTracker::refits_after_commit(bool committed) {
  std::vector<DueRefit> due;
  SpacecraftTracker* t = fleet_.find(stop_.sat_id);
  // The early refit first (the order a filter meets them); during an outage it is asked again
  // with the next samples.
  if (stop_.early && committed && t != nullptr) {
    if (auto refit = early_refit(stop_.sat_id, *t)) due.push_back(std::move(*refit));
  }
  for (const int64_t t_ref : stop_.scheduled_utimes) {
    (committed ? due : deferred_refits_)
        .push_back({stop_.sat_id, t_ref, storage::RefitTrigger::kScheduled});
  }
  if (!committed && !stop_.scheduled_utimes.empty()) {
    warnings_.warn("refit_deferred",
                   fmt::format("{}: refit due at {} waits until the database takes the held "
                               "samples",
                               stop_.sat_id, format_iso8601_utc(stop_.scheduled_utimes.back())));
  }
  return due;
}

void OwnedSpacecraftTracker::resume_tracking() {
  stop_ = RefitStop{};
  if (pass_.sat >= union_due_sats_.size()) return;
  OwnedSpacecraft& t = *fleet_.find(*union_due_sats_[pass_.sat]);
  // The rest of the row it stopped at.
  apply_reanchors_if_posted();
  pass_.state_was_due = pass_.state_was_due || t.state_due;
  ++pass_.row;
  run_pass();
}

std::vector<DueRefit> OwnedSpacecraftTracker::take_deferred_refits() {
  return std::exchange(deferred_refits_, {});
}

std::optional<DueRefit> OwnedSpacecraftTracker::early_refit(const std::string& sat_id,
                                                            OwnedSpacecraft& t) {
  // The refit reads what is committed; so does its key below.
  const EarlyRefitPlan plan = config_.early_refits();
  const int64_t n = plan.latest_within(t.n_samples);
  std::optional<int64_t> first_utime, t_ref;
  try {
    first_utime = samples_.utime_at_rank(sat_id, 0);
    t_ref = samples_.utime_at_rank(sat_id, n - 1);
    if (!t_ref) {
      // Fewer stored than counted (duplicates only the insert saw): due once they are.
      t.n_samples = samples_.count(sat_id);
      return std::nullopt;
    }
  } catch (const storage::StorageError& e) {
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    warnings_.warn("early_refit", fmt::format("{}: early refit not requested, retried with its "
                                              "next samples: {}",
                                              sat_id, e.what()));
    return std::nullopt;
  }
  t.next_early_refit_samples = plan.next_after(n);
  if (*t_ref - *first_utime >= config_.window_utime()) {
    t.next_early_refit_samples = 0;  // a full window: the schedule's from now on
    return std::nullopt;
  }
  return DueRefit{
      sat_id, *t_ref,
      n == plan.min_samples ? storage::RefitTrigger::kFirst : storage::RefitTrigger::kEarly};
}

}  // namespace magcal
