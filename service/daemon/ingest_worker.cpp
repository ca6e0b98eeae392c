#include "service/daemon/ingest_worker.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <span>
#include <thread>

#include <spdlog/spdlog.h>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"

namespace magcal {
namespace {

constexpr int64_t kNoTime = SpacecraftTracker::kNoTime;
constexpr double kRetentionEvery_s = 2.0;                   // wall time...
constexpr int64_t kRetentionEveryData_utime = 600'000'000;  // ...or data time
constexpr int kRetentionChunkRows = 2000;
// While other stations are live, the owner looks for their samples this often (wall time).
constexpr double kUnionPoll_s = 1.0;
// Takeovers per lease round: each reads the spacecraft's state, history and job log (a few ms
// on PostgreSQL), so a daemon taking over hundreds of spacecraft keeps receiving in between;
// the rest follow at the next rounds.
constexpr size_t kMaxTakeoversPerRound = 256;

// This process's id in the stations table: random per start.
std::string random_instance_id() {
  std::random_device rd;
  const uint64_t id =
      (static_cast<uint64_t>(rd()) << 32) ^ rd() ^ static_cast<uint64_t>(::getpid());
  return fmt::format("{:016x}", id);
}

// How much `station` prefers to own `sat_id` (rendezvous hashing): the daemons of a fleet try
// different spacecraft first, and a handover gives back those it prefers least.
uint64_t ownership_preference(const std::string& sat_id, const std::string& station) {
  const uint64_t h = std::hash<std::string>{}(sat_id)*0x9E3779B97F4A7C15ULL;
  return h ^ (std::hash<std::string>{}(station) + 0x7F4A7C15ULL + (h << 6) + (h >> 2));
}
// A commit drains the spill file for at most this long, then the worker takes frames again: a
// large spill (1 GiB: minutes of inserts) must not stall intake or the systemd watchdog.
constexpr double kSpillDrainSlice_s = 1.0;

int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

ValidatorOptions validator_options(const DaemonConfig& c) {
  ValidatorOptions v;
  v.range_nT = c.sensor.range_nT;
  v.min_position_m = c.service.min_position_km * 1e3;
  v.max_position_m = c.service.max_position_km * 1e3;
  v.whitelist = c.service.whitelist;
  std::sort(v.whitelist.begin(), v.whitelist.end());
  return v;
}

// The key of a pending row in IngestWorker::pending_index_ (equal keys are compared in full).
uint64_t pending_key(const std::string& sat_id, int64_t utime) {
  return std::hash<std::string>{}(sat_id) ^ (static_cast<uint64_t>(utime) * 0x9E3779B97F4A7C15ULL);
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

IngestWorker::IngestWorker(const DaemonConfig& config, DaemonCounters& counters,
                           std::unique_ptr<ReferenceField> field, Hooks hooks)
    : config_(config),
      counters_(counters),
      field_(std::move(field)),
      hooks_(std::move(hooks)),
      validator_(validator_options(config)),
      db_(storage::open_database(
          config.storage.db_path,
          storage::OpenOptions{.busy_timeout_ms = config.storage.busy_timeout_ms})),
      samples_(db_->make_sample_window_store()),
      history_(db_->make_calibration_history()),
      filter_states_(db_->make_filter_state_store()),
      jobs_(db_->make_refit_job_log()),
      leases_(db_->make_lease_store()),
      instance_(random_instance_id()),
      fleet_(config.ukf.filter),
      commit_retry_("commit", config.storage_max_failure_s(), counters,
                    config.storage_max_failure_key()),
      read_retry_("duplicate check", config.storage_max_failure_s(), counters,
                  config.storage_max_failure_key()) {
  pending_.reserve(static_cast<size_t>(config.storage.commit_every_samples));
  if (const std::string path = config.spill_path(); !path.empty()) {
    spill_ = std::make_unique<SampleSpill>(path, db_->name(), config.storage.spill_max_bytes);
    if (spill_->dropped_records() > 0) {
      counters_.spill_dropped.fetch_add(spill_->dropped_records());
      spdlog::error(
          "spill file {}: its torn or corrupt end was cut off (the process stopped "
          "during a write); its {} complete samples are kept",
          path, spill_->held_samples());
    }
    update_spill_gauges();
  }
  if (config.data_clock()) {
    const auto minute = parse_daily_time_utc(config.refit.daily_at_utc);
    data_schedule_ = RefitSchedule{minute.value_or(120), config.refit.every_hours};
  }
}

IngestWorker::~IngestWorker() = default;

void IngestWorker::restore() {
  if (spill_ && spill_->held_samples() > 0) {
    // Before the trackers are rebuilt: they, and the filter re-run, then include these samples.
    const int64_t held = spill_->held_samples();
    spdlog::warn(
        "spill file {} (written for {}) holds {} samples an earlier run received during "
        "a database outage: committing them",
        spill_->path(), spill_->found_database(), held);
    commit_spill(true);
    spdlog::info("spill file {}: {} samples committed ({} already stored); file removed",
                 spill_->path(), counters_.spill_recovered.load(),
                 held - counters_.spill_recovered.load());
  }
  for (const auto& sat : samples_->spacecraft()) {
    const auto newest = samples_->newest_utime(sat);
    if (!newest) continue;
    restore_received(sat, tracker(sat, nullptr), *newest);
  }
  counters_.n_spacecraft.store(static_cast<int32_t>(fleet_.size()));
  // A daemon alone takes every spacecraft now; after a restart its own leases at once.
  maintain_leases();
  if (fleet_.size() > 0) {
    size_t owned = 0;
    fleet_.for_each([&](const std::string&, SpacecraftTracker& t) { owned += t.owned ? 1 : 0; });
    spdlog::info("restored {} spacecraft from {} ({} owned here, of {} live station(s))",
                 fleet_.size(), db_->name(), owned, live_stations_);
  }
}

void IngestWorker::restore_received(const std::string& sat, SpacecraftTracker& t,
                                    int64_t newest_utime) {
  t.newest_utime = newest_utime;
  t.stored_bound_utime = newest_utime;
  samples_->read_window(sat, newest_utime, saturating_add(newest_utime, 1), union_rows_);
  if (!union_rows_.empty()) t.received_seq.last_seq = union_rows_.back().seq;
  data_clock_utime_ = std::max(data_clock_utime_, newest_utime);
}

void IngestWorker::take_over(const std::string& sat, SpacecraftTracker& t, int64_t epoch) {
  t.ukf = MagnetometerUkf(config_.ukf.filter);
  t.temperature = TemperatureCorrection{};
  t.anchor_calibration_id = 0;
  t.deferred_reanchor_id = 0;
  t.deferred_reanchor_utime = kNoTime;
  t.state_dirty = t.state_due = false;
  restore_filter(sat, t);
  const FilterState& st = t.ukf.state();
  // The filter goes on after its state's last sample (track_union()); with no state, from the
  // oldest stored one.
  t.filtered_utime = st.has_time ? st.last_utime : kNoTime;
  const auto newest = samples_->newest_utime(sat);
  t.union_newest_utime = newest.value_or(kNoTime);
  t.union_grew_wall_utime = wall_utime();
  t.union_due = true;
  t.union_seq = SeqGapCounter{};
  // The next early refit follows from the database: the latest refit's sample count; the
  // samples counted are those the state has taken.
  const auto latest_refit = history_->latest_refit(sat);
  t.n_samples = t.filtered_utime == kNoTime
                    ? 0
                    : samples_->count_in_window(sat, std::numeric_limits<int64_t>::min() / 2,
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
          samples_->oldest_utime(sat).value_or(*newest));
      t.data_refits->advance(std::min(resume, *newest));
    }
  }
  t.owned = true;
  t.lease_epoch = epoch;
  {
    std::lock_guard lock(owned_mutex_);
    owned_names_.insert(sat);
  }
  counters_.spacecraft.spacecraft(sat).owned.store(true, std::memory_order_relaxed);
  spdlog::info("{}: owned here (lease epoch {}); its UKF goes on from {}", sat, epoch,
               t.filtered_utime == kNoTime ? std::string("its first stored sample")
                                           : format_iso8601_utc(t.filtered_utime));
}

void IngestWorker::give_up(const std::string& sat, SpacecraftTracker& t) {
  t.owned = false;
  t.lease_epoch = 0;
  t.state_due = t.state_dirty = false;
  t.data_refits.reset();
  t.next_early_refit_samples = 0;
  t.ukf = MagnetometerUkf(config_.ukf.filter);  // nothing of the old filter is used again
  std::erase(states_due_, sat);
  std::erase_if(pending_snapshots_, [&](const PendingSnapshot& p) { return p.sat_id == sat; });
  {
    std::lock_guard lock(owned_mutex_);
    owned_names_.erase(sat);
  }
  counters_.spacecraft.spacecraft(sat).owned.store(false, std::memory_order_relaxed);
}

bool IngestWorker::owns(const std::string& sat_id) const {
  std::lock_guard lock(owned_mutex_);
  return owned_names_.count(sat_id) > 0;
}

void IngestWorker::maintain_leases() {
  const auto now_steady = std::chrono::steady_clock::now();
  next_lease_round_ =
      now_steady + std::chrono::microseconds(std::max<int64_t>(1, config_.lease_utime() / 3));
  const int64_t now = wall_utime();
  const int64_t ttl = config_.lease_utime();
  const std::string& me = config_.station.id;
  std::vector<std::pair<std::string, int64_t>> acquired;  // (sat, epoch), taken over below
  try {
    const auto before = leases_->heartbeat(me, instance_, now, ttl);
    if (before && before->instance != instance_ && before->expires_utime > now) {
      if (last_beat_utime_ != 0) {
        // It beat since this process did: it is alive.
        throw StationConflict(fmt::format(
            "another magcald runs as station '{}' on {} (it beat at {}, wall clock): give each "
            "daemon sharing a database its own [station] id (--station)",
            me, db_->name(), format_iso8601_utc(before->heartbeat_utime)));
      }
      spdlog::warn(
          "station '{}': the heartbeat of a previous process is live until {} (wall "
          "clock): a restart after a crash, or another magcald with the same [station] "
          "id (then both stop within {:.0f} s)",
          me, format_iso8601_utc(before->expires_utime), config_.fleet.lease_s / 3);
    }
    last_beat_utime_ = now;
    for (const auto& sat : unregistered_) leases_->ensure(sat);
    unregistered_.clear();
    std::unordered_map<std::string, int64_t> renewed;
    for (const auto& l : leases_->renew_all(me, now, ttl)) renewed.emplace(l.sat_id, l.epoch);
    size_t held = 0;
    fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
      if (!t.owned) return;
      const auto it = renewed.find(sat);
      if (it == renewed.end() || it->second != t.lease_epoch) {
        spdlog::warn("{}: lease lost (expired or taken over): its UKF stops here", sat);
        counters_.leases_lost.fetch_add(1, std::memory_order_relaxed);
        give_up(sat, t);
        return;
      }
      ++held;
    });
    // Leases still this station's that this process does not know it holds (it restarted
    // within their time to live): taken over at once.
    for (const auto& [sat, epoch] : renewed) {
      const SpacecraftTracker* t = fleet_.find(sat);
      if (t == nullptr || !t->owned) {
        ++held;  // (held either way: taken over now, or at a next round while it is renewed)
        if (acquired.size() < kMaxTakeoversPerRound) acquired.emplace_back(sat, epoch);
      }
    }
    const std::vector<storage::Lease> all = leases_->list();
    live_stations_ = std::max<size_t>(1, leases_->live_stations(now).size());
    const size_t share = (all.size() + live_stations_ - 1) / live_stations_;
    // Hand over the ones this station prefers least (the others take them at their next round),
    // once their snapshots are committed (one attempt: never waits through an outage).
    if (held > share) commit();
    if (held > share && !uncommitted()) {
      std::vector<std::pair<uint64_t, std::string>> mine;
      fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
        if (t.owned) mine.emplace_back(ownership_preference(sat, me), sat);
      });
      std::sort(mine.begin(), mine.end());
      for (size_t i = 0; i < mine.size() && held > share; ++i) {
        SpacecraftTracker& t = *fleet_.find(mine[i].second);
        if (t.state_dirty) {
          storage::Transaction tx(*db_);
          if (leases_->holds(mine[i].second, me, t.lease_epoch)) {
            filter_states_->save(stored_state(mine[i].second, t));
          }
          tx.commit();
        }
        leases_->release(mine[i].second, me, t.lease_epoch, wall_utime());
        spdlog::info("{}: handed over ({} live stations share {} spacecraft)", mine[i].second,
                     live_stations_, all.size());
        give_up(mine[i].second, t);
        --held;
      }
    } else if (held < share) {
      std::vector<std::pair<uint64_t, std::string>> free;
      for (const auto& l : all) {
        if (l.held_at(now)) continue;
        free.emplace_back(ownership_preference(l.sat_id, me), l.sat_id);
      }
      std::sort(free.rbegin(), free.rend());
      for (size_t i = 0; i < free.size() && held < share && acquired.size() < kMaxTakeoversPerRound;
           ++i) {
        if (const auto lease = leases_->try_acquire(free[i].second, me, now, ttl)) {
          acquired.emplace_back(free[i].second, lease->epoch);
          ++held;
        }
      }
    }
  } catch (const storage::StorageError& e) {
    // Retried at the next round; a lease that runs out meanwhile is given up there.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    warnings_.warn("leases", fmt::format("database: lease round failed, retried in {:.0f} s: {}",
                                         config_.fleet.lease_s / 3, e.what()));
  }
  for (const auto& [sat, epoch] : acquired) {
    bool created = false;
    SpacecraftTracker& t = tracker(sat, &created);
    try {
      if (created) {
        // Not received here (yet): its time base from the stored window.
        counters_.n_spacecraft.store(static_cast<int32_t>(fleet_.size()));
        if (const auto newest = samples_->newest_utime(sat)) restore_received(sat, t, *newest);
      }
      take_over(sat, t, epoch);
    } catch (const storage::StorageError& e) {
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      spdlog::error("{}: takeover failed, lease given back: {}", sat, e.what());
      give_up(sat, t);
      try {
        leases_->release(sat, me, epoch, wall_utime());
      } catch (const storage::StorageError&) {
        // It runs out by itself.
      }
    }
  }
}

void IngestWorker::leave_fleet() {
  save_filter_states();  // commits first
  // Storage failing (an outage): the leases and the heartbeat run out by themselves.
  if (uncommitted()) return;
  const std::string& me = config_.station.id;
  try {
    fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
      if (!t.owned) return;
      if (!t.state_dirty) leases_->release(sat, me, t.lease_epoch, wall_utime());
      give_up(sat, t);
    });
    leases_->leave(me, wall_utime());
  } catch (const storage::StorageError& e) {
    // The leases and the heartbeat run out by themselves.
    spdlog::warn("database: leases not handed back at stop ({}); they expire within {} s", e.what(),
                 config_.fleet.lease_s);
  }
}

void IngestWorker::restore_filter(const std::string& sat, SpacecraftTracker& t) {
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
  if (reanchor_id && *reanchor_id > t.anchor_calibration_id) {
    // An accepted refit the state was not re-anchored on (its owner died before it stored the
    // re-anchored state): applied after the samples up to the refit's time, where the
    // uninterrupted filter took it (the refit's estimate includes them: re-anchoring before
    // them would count them twice).
    t.deferred_reanchor_id = *reanchor_id;
    if (const auto rec = history_->get(*reanchor_id)) {
      spdlog::info(
          "{}: the stored UKF state predates the accepted refit of {}: re-anchored on "
          "it from there",
          sat, format_iso8601_utc(rec->utime));
      t.deferred_reanchor_utime = rec->utime;
      const FilterState& st = t.ukf.state();
      if (st.has_time && st.last_utime >= rec->utime) apply_deferred_reanchor(sat, t);
    }
  }
}

void IngestWorker::apply_deferred_reanchor(const std::string& sat, SpacecraftTracker& t) {
  const int64_t id = t.deferred_reanchor_id;
  t.deferred_reanchor_id = 0;
  t.deferred_reanchor_utime = kNoTime;
  if (const auto rec = history_->get(id)) reanchor(sat, t, result_from_record(*rec), rec->id);
}

void IngestWorker::track_union(const std::string& sat, SpacecraftTracker& t, bool drain) {
  t.union_due = false;
  // An accepted refit posted meanwhile applies before the samples committed since.
  if (have_reanchors_.load(std::memory_order_acquire)) apply_reanchors();
  if (!t.owned) return;
  const int64_t from =
      t.filtered_utime == kNoTime ? std::numeric_limits<int64_t>::min() / 2 : t.filtered_utime + 1;
  samples_->read_window(sat, from, std::numeric_limits<int64_t>::max(), union_rows_);
  if (union_rows_.empty()) return;
  const int64_t now = wall_utime();
  const int64_t newest = union_rows_.back().utime;
  if (newest > t.union_newest_utime) {
    t.union_newest_utime = newest;
    t.union_grew_wall_utime = now;
  }
  // Samples of another station may still come for the last reorder_delay of data time; once
  // none came for that long in wall time, the pass is over.
  const bool quiet = now - t.union_grew_wall_utime >= config_.reorder_delay_utime();
  const int64_t horizon =
      drain || quiet ? newest : saturating_sub(newest, config_.reorder_delay_utime());
  bool state_was_due = t.state_due;
  for (const auto& row : union_rows_) {
    if (row.utime > horizon) break;
    if (!t.owned) return;  // lost during a flush below
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
    check_early_refit(sat, t);
    if (data_schedule_) check_data_clock(sat, t);
    // A replay waits for the refits it triggers: their re-anchor applies from the next sample.
    if (have_reanchors_.load(std::memory_order_acquire)) apply_reanchors();
    state_was_due = state_was_due || t.state_due;
  }
  // A state due here (a snapshot, a re-anchor) but stored by a flush above goes in again with
  // every sample read now: a restart then re-runs none of them.
  if (state_was_due && t.owned) mark_state_due(sat, t);
  // Its retention follows the filter (run_retention()).
  retention_clock_utime_ = std::max(retention_clock_utime_, t.filtered_utime);
  if (!t.retention_due) {
    t.retention_due = true;
    retention_dirty_.push_back(sat);
  }
}

void IngestWorker::track_due() {
  track_owned(false);
}

void IngestWorker::track_all_now() {
  track_owned(true);
  last_retention_data_utime_ = std::numeric_limits<int64_t>::min() / 2;  // at the next commit
}

void IngestWorker::track_owned(bool drain) {
  if (tracking_) return;
  tracking_ = true;
  struct Done {
    bool& flag;
    ~Done() { flag = false; }
  } done{tracking_};
  const auto now = std::chrono::steady_clock::now();
  // Every kUnionPoll_s: while other stations are live, every owned spacecraft (their samples);
  // alone, those with samples still behind the reorder horizon (the end of a pass, taken once
  // it has been quiet for the reorder delay). Otherwise this station's commits say when.
  const bool due_poll = !drain && now >= next_union_poll_;
  if (due_poll) {
    next_union_poll_ = now + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                 std::chrono::duration<double>(kUnionPoll_s));
  }
  const bool poll_all = drain || (due_poll && live_stations_ > 1);
  auto due = [&](const SpacecraftTracker& t) {
    return t.union_due || poll_all ||
           (due_poll && t.union_newest_utime != kNoTime &&
            (t.filtered_utime == kNoTime || t.union_newest_utime > t.filtered_utime));
  };
  try {
    fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
      if (t.owned && due(t)) track_union(sat, t, drain);
    });
  } catch (const storage::StorageError& e) {
    // The filters wait where they are (a database outage): read again once commits go through.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    fleet_.for_each([](const std::string&, SpacecraftTracker& t) { t.union_due = t.owned; });
    warnings_.warn("track", fmt::format("database: the owned filters could not read the stored "
                                        "samples, retried: {}",
                                        e.what()));
  }
}

void IngestWorker::process(const IngestItem& item) {
  ++frame_counter_;
  for (const auto& s : item.samples) ingest_sample(s, item.batch_sat_id, item.receive_utime);
}

SpacecraftTracker& IngestWorker::tracker(const std::string& sat_id, bool* created) {
  bool is_new = false;
  SpacecraftTracker& t = fleet_.get(sat_id, &is_new);
  // Its counters are looked up once, here; the per-sample path uses the cached pointer.
  if (is_new) t.counters = &counters_.spacecraft.spacecraft(sat_id);
  if (is_new) {
    unregistered_.push_back(sat_id);  // its lease row, at once
    next_lease_round_ = {};
  }
  if (created) *created = is_new;
  return t;
}

void IngestWorker::count_missing(SpacecraftTracker& t, int64_t seq) {
  const int64_t missing = t.received_seq.observe(seq);
  // In a fleet another station may have delivered it: the owner counts the union's gaps.
  if (missing == 0 || live_stations_ > 1) return;
  counters_.missing_by_seq.fetch_add(missing, std::memory_order_relaxed);
  t.counters->missing.fetch_add(missing, std::memory_order_relaxed);
}

void IngestWorker::count_stored(std::span<const storage::StoredSample> rows) {
  // Rows come in runs of one spacecraft (a batch, a recorder dump): one lookup per run.
  size_t dup = 0;
  size_t run_start = 0;
  int64_t run_stored = 0;
  auto flush_run = [&](size_t at) {
    if (run_stored > 0) {
      if (SpacecraftTracker* t = fleet_.find(rows[run_start].sat_id)) {
        t->counters->stored.fetch_add(run_stored, std::memory_order_relaxed);
      }
    }
    run_stored = 0;
    run_start = at;
  };
  for (size_t i = 0; i < rows.size(); ++i) {
    if (rows[i].sat_id != rows[run_start].sat_id) flush_run(i);
    if (dup < duplicate_rows_.size() && duplicate_rows_[dup] == i) {
      ++dup;  // a duplicate the in-memory check could not see: counted as rejected instead
      continue;
    }
    ++run_stored;
  }
  flush_run(rows.size());
}

void IngestWorker::index_pending() {
  for (; pending_indexed_ < pending_.size(); ++pending_indexed_) {
    const auto& p = pending_[pending_indexed_];
    pending_index_.emplace(pending_key(p.sat_id, p.utime), static_cast<uint32_t>(pending_indexed_));
  }
}

void IngestWorker::reset_pending_index() {
  pending_index_.clear();
  pending_indexed_ = 0;
}

bool IngestWorker::is_duplicate(const std::string& sat_id, const SpacecraftTracker& t,
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
      return samples_->count_in_window(sat_id, utime, utime + 1) > 0;
    } catch (const storage::StorageError&) {
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      return false;
    }
  }
  // Reads work through most faults (WAL readers never wait for the writer); one that fails is
  // retried in place: the sample must not be taken before its answer.
  return read_retry_.run_blocking(
      [&] { return samples_->count_in_window(sat_id, utime, utime + 1) > 0; });
}

void IngestWorker::reject_sample(RejectReason r, const std::string& sat, const mag_sample_t& s) {
  counters_.reject(r);
  warnings_.warn(to_string(r), fmt::format("rejected sample ({}): sat '{}' utime {} seq {}",
                                           to_string(r), sat, s.utime, s.seq));
}

void IngestWorker::ingest_sample(const mag_sample_t& s, const std::string& batch_sat_id,
                                 int64_t receive_utime) {
  const auto reason = check_sample(s, batch_sat_id, validator_);
  const std::string& sat = sample_sat_id(s, batch_sat_id);
  if (reason) {
    if (*reason != RejectReason::kInvalidSatId && *reason != RejectReason::kBatchSatMismatch &&
        *reason != RejectReason::kUnknownSpacecraft) {
      // The frame was received: it is not missing, whatever is wrong with it.
      if (auto* t = fleet_.find(sat)) count_missing(*t, s.seq);
    }
    reject_sample(*reason, sat, s);
    return;
  }
  bool created = false;
  SpacecraftTracker& t = tracker(sat, &created);
  if (created) {
    counters_.n_spacecraft.store(static_cast<int32_t>(fleet_.size()));
    spdlog::info("new spacecraft '{}' (first sample {})", sat, format_iso8601_utc(s.utime));
  }
  count_missing(t, s.seq);
  // Telemetry cannot come from the future (beyond clock skew): a corrupt time tag.
  const int64_t now = receive_utime > 0 ? receive_utime : wall_utime();
  if (s.utime > saturating_add(now, config_.max_future_utime())) {
    reject_sample(RejectReason::kFutureTime, sat, s);
    return;
  }
  if (t.on_time_base(s.utime, config_.max_time_jump_utime())) {
    accept_sample(sat, t, s, receive_utime);
  } else {
    hold_sample(sat, t, s, receive_utime);
  }
}

void IngestWorker::accept_sample(const std::string& sat, SpacecraftTracker& t,
                                 const mag_sample_t& s, int64_t receive_utime) {
  if (t.newest_utime != kNoTime) {
    if (s.utime <= saturating_sub(t.newest_utime, config_.window_utime())) {
      reject_sample(RejectReason::kOlderThanWindow, sat, s);
      return;
    }
    if (s.utime <= t.newest_utime && is_duplicate(sat, t, s.utime)) {
      reject_sample(RejectReason::kDuplicate, sat, s);
      return;
    }
  }
  const auto sample = to_reference_sample(s, *field_);
  if (!sample) {
    reject_sample(RejectReason::kReferenceFailed, sat, s);
    return;
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
  if (!t.retention_due) {
    t.retention_due = true;
    retention_dirty_.push_back(sat);
  }
  data_clock_utime_ = std::max(data_clock_utime_, s.utime);
  if (!t.owned) retention_clock_utime_ = std::max(retention_clock_utime_, s.utime);
  if (static_cast<int>(pending_.size()) >= config_.storage.commit_every_samples) commit();
  if (advanced && !t.held.empty()) resolve_held(sat, t);
}

void IngestWorker::hold_sample(const std::string& sat, SpacecraftTracker& t, const mag_sample_t& s,
                               int64_t receive_utime) {
  if (t.holds_utime(s.utime)) {
    reject_sample(RejectReason::kDuplicate, sat, s);  // a repeat cannot corroborate itself
    return;
  }
  if (t.held.size() >= static_cast<size_t>(SpacecraftTracker::kHeldCapacity)) {
    reject_sample(RejectReason::kTimeJump, sat, t.held.front().sample);
    t.held.erase(t.held.begin());
  }
  if (t.held.empty() && t.newest_utime != kNoTime) {  // (a new spacecraft's first samples: normal)
    warnings_.warn("time_hold",
                   fmt::format("{}: sample at {} held: {} s past the newest sample (waiting for {} "
                               "more to corroborate it)",
                               sat, format_iso8601_utc(s.utime),
                               saturating_sub(s.utime, t.newest_utime) / 1000000,
                               SpacecraftTracker::kCorroborating));
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

void IngestWorker::resolve_held(const std::string& sat, SpacecraftTracker& t) {
  if (resolving_held_) return;  // accept_sample() below advanced the base: this loop goes on
  resolving_held_ = true;
  const int64_t max_jump = config_.max_time_jump_utime();
  size_t keep = 0;
  // In place (accept_sample() never adds to the hold): arrival order, no allocation.
  for (size_t i = 0; i < t.held.size(); ++i) {
    HeldSample& h = t.held[i];
    if (t.on_time_base(h.sample.utime, max_jump)) {
      accept_sample(sat, t, h.sample, h.receive_utime);
    } else if (t.advances - h.advances_at_hold >= SpacecraftTracker::kCorroborating) {
      reject_sample(RejectReason::kTimeJump, sat, h.sample);
    } else {
      if (keep != i) t.held[keep] = std::move(h);
      ++keep;
    }
  }
  t.held.erase(t.held.begin() + static_cast<std::ptrdiff_t>(keep), t.held.end());
  if (t.held.empty()) t.held.shrink_to_fit();  // a hold is rare: give its memory back
  resolving_held_ = false;
}

void IngestWorker::base_from_held(const std::string& sat, SpacecraftTracker& t) {
  const int64_t base = t.likeliest_held_utime(config_.max_time_jump_utime());
  if (base == kNoTime) return;
  spdlog::info("{}: time base {} from its {} held first sample(s), uncorroborated (no more came)",
               sat, format_iso8601_utc(base), t.held.size());
  t.newest_utime = base;
  resolve_held(sat, t);
}

void IngestWorker::release_first_holds(std::chrono::steady_clock::time_point now) {
  // first_holds_ is in the order of its times: only its front can be due (O(1) per call).
  const auto max_age = std::chrono::duration<double>(SpacecraftTracker::kFirstHoldMax_s);
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

void IngestWorker::settle_held() {
  fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
    if (t.newest_utime == kNoTime) base_from_held(sat, t);
    for (const auto& h : t.held) reject_sample(RejectReason::kJumpUnconfirmed, sat, h.sample);
    t.held.clear();
    t.held.shrink_to_fit();
  });
  first_holds_.clear();
}

int64_t IngestWorker::held_samples() {
  int64_t n = 0;
  fleet_.for_each(
      [&](const std::string&, SpacecraftTracker& t) { n += static_cast<int64_t>(t.held.size()); });
  return n;
}

void IngestWorker::maybe_snapshot(const std::string& sat_id, SpacecraftTracker& t, int64_t utime) {
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
  pending_snapshots_.push_back({sat_id, std::move(snap), t.temperature.refit_id});
  mark_state_due(sat_id, t);
}

void IngestWorker::mark_state_due(const std::string& sat_id, SpacecraftTracker& t) {
  if (t.state_due) return;
  t.state_due = true;
  states_due_.push_back(sat_id);
}

storage::FilterState IngestWorker::stored_state(const std::string& sat_id,
                                                const SpacecraftTracker& t) const {
  storage::FilterState st = stored_filter_state(sat_id, "ukf", t.ukf.state());
  st.anchor_calibration_id = t.anchor_calibration_id;
  return st;
}

void IngestWorker::commit_if_due() {
  if (have_reanchors_.load(std::memory_order_acquire)) apply_reanchors();
  const auto now = std::chrono::steady_clock::now();
  release_first_holds(now);
  if (now >= next_lease_round_) maintain_leases();
  if (uncommitted()) {
    const double age_ms =
        std::chrono::duration<double, std::milli>(now - first_pending_time_).count();
    if (age_ms >= config_.storage.commit_every_ms || pending_.empty()) commit();
  }
  if (!commit_retry_.failing()) track_due();
  if (!retention_dirty_.empty() && !commit_retry_.failing() &&
      std::chrono::duration<double>(now - last_retention_time_).count() >= kRetentionEvery_s) {
    run_retention();
  }
}

bool IngestWorker::uncommitted() const {
  return !pending_.empty() || !pending_snapshots_.empty() || !states_due_.empty() ||
         (spill_ && spill_->held_samples() > 0);
}

void IngestWorker::commit() {
  // An outage that outlasts memory: the batch goes to the spill file, intake goes on.
  if (commit_retry_.failing()) spill_pending(false);
  // Two rounds: the samples, then what the owned filters made of them (snapshots, states), so
  // that after commit() everything they produced from committed samples is stored too (not
  // while the spill drains: one slice per call).
  for (int round = 0; round < 2; ++round) {
    if (!uncommitted() || !commit_retry_.due() ||
        (round > 0 && spill_ && spill_->held_samples() > 0)) {
      break;
    }
    commit_retry_.attempting();
    try {
      commit_pending();
      commit_retry_.succeeded();
      spill_full_ = false;
    } catch (const storage::StorageError& e) {
      // Samples and snapshots stay pending.
      commit_retry_.failed(e);  // throws StorageOutage when storage stays broken
      return;
    }
    if (!deferred_refits_.empty() && !uncommitted()) {
      // Their samples are committed now; requested before retention runs (their floor).
      const auto due = std::move(deferred_refits_);
      deferred_refits_.clear();
      for (const auto& [sat, t_ref] : due) {
        if (hooks_.on_refit_due) hooks_.on_refit_due(sat, t_ref, "scheduled");
      }
    }
    if (tracking_) break;  // a commit inside track_union(): it goes on by itself
    // A new spacecraft gets its lease row and, when this daemon's share allows, its owner here
    // before its first samples are read back.
    if (std::chrono::steady_clock::now() >= next_lease_round_) maintain_leases();
    track_due();
  }
  // Retention by data time too, so a fast replay keeps its windows as a live feed would.
  if (!retention_dirty_.empty() && !commit_retry_.failing() &&
      (retention_clock_utime_ - last_retention_data_utime_ >= kRetentionEveryData_utime ||
       std::chrono::duration<double>(std::chrono::steady_clock::now() - last_retention_time_)
               .count() >= kRetentionEvery_s)) {
    run_retention();
  }
}

void IngestWorker::commit_pending() {
  // A backlog left by a storage fault goes in transactions of commit_every_samples: each holds
  // the write lock briefly, and on a nearly full disk every chunk that fits is stored. The
  // snapshots and the filter states that are due go with the last chunk (published once
  // stored; a state then includes exactly the committed samples).
  const auto chunk = static_cast<size_t>(config_.storage.commit_every_samples);
  // Spilled samples are older than the pending ones, and the states below include them. Until
  // the file is drained the pending batch queues behind it in the file (one order, and memory
  // stays bounded); snapshots and states wait.
  if (spill_ && spill_->held_samples() > 0) {
    commit_spill(false, std::chrono::steady_clock::now() +
                            std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                std::chrono::duration<double>(kSpillDrainSlice_s)));
    if (spill_->held_samples() > 0) {
      spill_pending(true);
      return;
    }
  }
  size_t done = 0;
  try {
    while (done < pending_.size() || !pending_snapshots_.empty() || !states_due_.empty()) {
      const size_t n = std::min(chunk, pending_.size() - done);
      const bool last = done + n == pending_.size();
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
        storage::Transaction tx(*db_);
        stats = samples_->insert_batch(std::span(pending_).subspan(done, n), &duplicate_rows_,
                                       config_.station.id);
        if (last) {
          fence_owned_writes();
          for (const auto& p : pending_snapshots_) {
            storage::CalibrationRecord rec = record_from_result(p.sat_id, p.result);
            rec.temperature_model_refit_id = p.temperature_model_refit_id;
            history_->append(rec);
          }
          for (const auto& sat : states_due_) {
            if (const SpacecraftTracker* t = fleet_.find(sat)) {
              filter_states_->save(stored_state(sat, *t));
            }
          }
        }
        tx.commit();
      }
      mark_union_due(std::span(pending_).subspan(done, n));
      count_stored(std::span(pending_).subspan(done, n));
      done += n;
      counters_.stored.fetch_add(stats.inserted, std::memory_order_relaxed);
      // Duplicates the in-memory check could not see (e.g. within one frame).
      if (stats.duplicates > 0) counters_.reject(RejectReason::kDuplicate, stats.duplicates);
      if (last) {
        for (const auto& sat : states_due_) {
          if (SpacecraftTracker* t = fleet_.find(sat)) t->state_due = t->state_dirty = false;
        }
        states_due_.clear();
      }
      if (last && !pending_snapshots_.empty()) {
        counters_.snapshots.fetch_add(static_cast<int64_t>(pending_snapshots_.size()));
        if (hooks_.on_snapshot) {
          for (const auto& p : pending_snapshots_) hooks_.on_snapshot(p.sat_id, p.result);
        }
        pending_snapshots_.clear();
      }
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

void IngestWorker::fence_owned_writes() {
  // Only while the lease is still this daemon's (on PostgreSQL its row stays locked until the
  // commit, so a takeover waits for it): a daemon that stalled past its lease writes nothing.
  const std::string& me = config_.station.id;
  std::vector<std::string> lost;
  auto check = [&](const std::string& sat) {
    if (std::find(lost.begin(), lost.end(), sat) != lost.end()) return;
    const SpacecraftTracker* t = fleet_.find(sat);
    if (t == nullptr || !t->owned || !leases_->holds(sat, me, t->lease_epoch)) lost.push_back(sat);
  };
  std::string last_checked;
  for (const auto& p : pending_snapshots_) {
    if (p.sat_id != last_checked) check(p.sat_id);
    last_checked = p.sat_id;
  }
  for (const auto& sat : states_due_) check(sat);
  for (const auto& sat : lost) {
    spdlog::warn(
        "{}: lease lost before its snapshots were stored: dropped (the new owner makes "
        "them)",
        sat);
    counters_.leases_lost.fetch_add(1, std::memory_order_relaxed);
    if (SpacecraftTracker* t = fleet_.find(sat)) give_up(sat, *t);
  }
}

void IngestWorker::mark_union_due(std::span<const storage::StoredSample> rows) {
  const std::string* last = nullptr;
  for (const auto& row : rows) {
    if (last != nullptr && *last == row.sat_id) continue;
    last = &row.sat_id;
    if (SpacecraftTracker* t = fleet_.find(*last); t != nullptr && t->owned) t->union_due = true;
  }
}

void IngestWorker::flush() {
  while (uncommitted()) {
    if (!commit_retry_.due()) std::this_thread::sleep_until(commit_retry_.next_attempt());
    commit();
  }
}

void IngestWorker::flush_at_stop() {
  if (spill_ && uncommitted()) {
    commit();
    if (commit_retry_.failing() && (pending_.empty() || spill_pending(true))) {
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
      return;
    }
  }
  flush();
}

int64_t IngestWorker::spill_all_pending() {
  const auto n = static_cast<int64_t>(pending_.size());
  return spill_pending(true) ? n : 0;
}

bool IngestWorker::spill_pending(bool at_any_size) {
  if (!spill_ || spill_full_ || pending_.empty()) return false;
  if (!at_any_size && static_cast<int64_t>(pending_.size()) < config_.storage.max_pending_samples) {
    return false;
  }
  bool appended = false;
  try {
    appended = spill_->append(pending_);
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
                    spill_->path(), pending_.size(), spill_->bytes(), spill_->max_bytes()));
    return false;
  }
  counters_.spilled.fetch_add(static_cast<int64_t>(pending_.size()), std::memory_order_relaxed);
  warnings_.warn(
      "spill",
      fmt::format("{}: {} pending samples spilled to {} ({} held there, {} bytes)",
                  commit_retry_.failing() ? "database commit failing" : "queued behind the spill",
                  pending_.size(), spill_->path(), spill_->held_samples(), spill_->bytes()));
  pending_.clear();
  reset_pending_index();
  update_spill_gauges();
  return true;
}

void IngestWorker::commit_spill(bool recovered, std::chrono::steady_clock::time_point until) {
  const auto chunk = static_cast<size_t>(config_.storage.commit_every_samples);
  // insert_batch sorts each chunk by (sat_id, utime), the fleet's one key order.
  while (std::chrono::steady_clock::now() < until && spill_->read_chunk(chunk, spill_chunk_) > 0) {
    const storage::InsertStats stats =
        samples_->insert_batch(spill_chunk_, &duplicate_rows_, config_.station.id);
    spill_->commit_read();
    mark_union_due(spill_chunk_);
    if (recovered) {
      // Received, counted and checked by the run that spilled them.
      counters_.spill_recovered.fetch_add(stats.inserted, std::memory_order_relaxed);
    } else {
      count_stored(spill_chunk_);
      counters_.stored.fetch_add(stats.inserted, std::memory_order_relaxed);
      if (stats.duplicates > 0) counters_.reject(RejectReason::kDuplicate, stats.duplicates);
    }
    update_spill_gauges();
  }
}

void IngestWorker::update_spill_gauges() {
  counters_.spill_held.store(spill_->held_samples(), std::memory_order_relaxed);
  counters_.spill_bytes.store(spill_->bytes(), std::memory_order_relaxed);
}

bool IngestWorker::committed_for_refit() {
  if (!spill_) {
    flush();
    return true;
  }
  commit();  // one attempt, or none during the backoff: never waits through an outage
  return !uncommitted();
}

void IngestWorker::run_retention() {
  last_retention_time_ = std::chrono::steady_clock::now();
  last_retention_data_utime_ = retention_clock_utime_;
  const int64_t window = config_.window_utime();
  const auto margin = static_cast<int64_t>(config_.storage.retention_margin_hours * 3.6e9);
  const int64_t floor = retention_floor_.load();
  std::vector<std::string> failed;
  for (const auto& sat : retention_dirty_) {
    SpacecraftTracker* t = fleet_.find(sat);
    if (!t || t->newest_utime == kNoTime) continue;
    // Only the owner deletes, behind its filter: it triggers refits at its own data time, which
    // may lag the stored samples (the reorder delay; a replay commits ahead of it), and another
    // station far ahead of it (a backfill) must not delete the window its refits will read.
    const int64_t edge = t->owned ? std::min(t->newest_utime, t->filtered_utime) : kNoTime;
    if (edge == kNoTime) {
      t->retention_due = false;  // due again once its filter has taken samples
      continue;
    }
    const int64_t cutoff = std::min(saturating_sub(edge, window + margin), floor);
    try {
      samples_->delete_before(sat, cutoff, kRetentionChunkRows);
      t->retention_due = false;
    } catch (const storage::StorageError& e) {
      // Nothing is lost by deleting later: kept for the next round.
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      spdlog::error("database: retention of '{}' failed, retried later: {}", sat, e.what());
      failed.push_back(sat);
    }
  }
  retention_dirty_.swap(failed);
}

void IngestWorker::check_data_clock(const std::string& sat_id, SpacecraftTracker& t) {
  if (!t.data_refits || t.filtered_utime == kNoTime) return;
  const int64_t skipped_before = t.data_refits->skipped();
  const auto due = t.data_refits->advance(t.filtered_utime);
  if (t.data_refits->skipped() != skipped_before) {
    warnings_.warn("refits_skipped",
                   fmt::format("{}: data clock jumped to {}: {} scheduled refits skipped, only the "
                               "latest runs",
                               sat_id, format_iso8601_utc(t.filtered_utime),
                               t.data_refits->skipped() - skipped_before));
  }
  if (due.empty()) return;
  // The refit reads what is committed: everything up to t_ref.
  if (!committed_for_refit()) {
    for (const int64_t t_ref : due) deferred_refits_.emplace_back(sat_id, t_ref);
    warnings_.warn("refit_deferred",
                   fmt::format("{}: refit due at {} waits until the database takes the held "
                               "samples",
                               sat_id, format_iso8601_utc(due.back())));
    return;
  }
  for (const int64_t t_ref : due) {
    if (hooks_.on_refit_due) hooks_.on_refit_due(sat_id, t_ref, "scheduled");
  }
}

void IngestWorker::check_early_refit(const std::string& sat_id, SpacecraftTracker& t) {
  if (t.next_early_refit_samples <= 0 || t.n_samples < t.next_early_refit_samples ||
      !t.ukf.initialized() || t.filtered_utime == kNoTime) {
    return;
  }
  // The refit reads what is committed; so does its key below. (During an outage: asked again
  // with the next samples.)
  if (!committed_for_refit()) return;
  const EarlyRefitPlan plan = config_.early_refits();
  const int64_t n = plan.latest_within(t.n_samples);
  std::optional<int64_t> first_utime, t_ref;
  try {
    first_utime = samples_->utime_at_rank(sat_id, 0);
    t_ref = samples_->utime_at_rank(sat_id, n - 1);
    if (!t_ref) {
      // Fewer stored than counted (duplicates only the insert saw): due once they are.
      t.n_samples = samples_->count(sat_id);
      return;
    }
  } catch (const storage::StorageError& e) {
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    warnings_.warn("early_refit", fmt::format("{}: early refit not requested, retried with its "
                                              "next samples: {}",
                                              sat_id, e.what()));
    return;
  }
  t.next_early_refit_samples = plan.next_after(n);
  if (*t_ref - *first_utime >= config_.window_utime()) {
    t.next_early_refit_samples = 0;  // a full window: the schedule's from now on
    return;
  }
  if (hooks_.on_refit_due) {
    hooks_.on_refit_due(sat_id, *t_ref, n == plan.min_samples ? "first" : "early");
  }
}

void IngestWorker::save_filter_states() {
  // A saved state must not include samples that are not stored: after a crash they come again
  // (re-replay, recorder dump) and the restored filter would use them twice.
  commit();
  if (uncommitted()) return;  // storage failing: saved once the commit goes through
  std::vector<SpacecraftTracker*> saved;
  try {
    storage::Transaction tx(*db_);
    fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
      if (!t.owned || !t.state_dirty) return;
      if (!leases_->holds(sat, config_.station.id, t.lease_epoch))
        return;  // lost: the next
                 // round gives it up
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
  for (SpacecraftTracker* t : saved) t->state_dirty = false;
  if (!saved.empty()) spdlog::debug("saved {} filter states", saved.size());
}

void IngestWorker::post_reanchor(const std::string& sat_id, const CalibrationResult& refit,
                                 int64_t calibration_id) {
  std::lock_guard lock(reanchor_mutex_);
  reanchors_.push_back({sat_id, refit, calibration_id});
  have_reanchors_.store(true, std::memory_order_release);
}

void IngestWorker::apply_reanchors() {
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

void IngestWorker::reanchor(const std::string& sat, SpacecraftTracker& t,
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
  t.ukf.reanchor(refit.parameters.packed(), refit.covariance, refit.model_error_covariance());
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
