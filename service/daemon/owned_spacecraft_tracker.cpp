#include "service/daemon/owned_spacecraft_tracker.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <tuple>
#include <unordered_map>

#include <spdlog/spdlog.h>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/temperature_model.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/station_settings.hpp"

namespace magcal {
namespace {

constexpr int64_t kNoTime = OwnedSpacecraft::kNoTime;
// While other stations are live, the owner looks for their samples this often (wall time).
constexpr double kUnionPoll_s = 1.0;
// Spacecraft whose new samples one statement reads (SampleWindowStore::read_windows).
constexpr size_t kUnionReadsPerStatement = 64;
// Takeovers per lease round: each reads the spacecraft's state, history and job log (a few ms
// on PostgreSQL), so a daemon taking over hundreds of spacecraft keeps receiving in between;
// the rest follow at the next rounds.
constexpr size_t kMaxTakeoversPerRound = 256;
// Jobs of a spacecraft looked at for a refit still running elsewhere (newest first).
constexpr int kRecentJobs = 8;

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

int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
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

// A refit of sat_id another station is running (claimed, not ended).
bool refit_running_elsewhere(storage::RefitJobLog& jobs, const std::string& sat_id,
                             const std::string& station) {
  for (const auto& j : jobs.recent(sat_id, kRecentJobs)) {
    if (j.outcome == storage::job_outcome::kRunning && !j.claimed_by.empty() &&
        j.claimed_by != station) {
      return true;
    }
  }
  return false;
}

}  // namespace

OwnedSpacecraftTracker::OwnedSpacecraftTracker(const DaemonConfig& config, DaemonCounters& counters,
                                               storage::Connection& db,
                                               storage::SampleWindowStore& samples,
                                               SpacecraftFleet& fleet, SampleIntake& intake,
                                               Hooks hooks, Links links)
    : config_(config),
      counters_(counters),
      hooks_(std::move(hooks)),
      links_(std::move(links)),
      db_(db),
      samples_(samples),
      history_(db.make_calibration_history()),
      filter_states_(db.make_filter_state_store()),
      jobs_(db.make_refit_job_log()),
      leases_(db.make_lease_store()),
      fleet_(fleet),
      intake_(intake),
      instance_(random_instance_id()),
      settings_watch_(config.station.id, station_settings(config.result_settings()), counters) {
  if (config.data_clock()) {
    const auto minute = parse_daily_time_utc(config.refit.daily_at_utc);
    data_schedule_ = RefitSchedule{minute.value_or(120), config.refit.every_hours};
  }
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
  if (refit_running_elsewhere(*jobs_, sat, config_.station.id)) refits_elsewhere_.push_back(sat);
  restore_filter(sat, t);
  const FilterState& st = t.ukf.state();
  // The filter goes on after its state's last sample (track_union()); with no state, from the
  // oldest stored one.
  t.filtered_utime = st.has_time ? st.last_utime : kNoTime;
  const auto newest = samples_.newest_utime(sat);
  t.union_newest_utime = newest.value_or(kNoTime);
  t.union_grew_wall_utime = wall_utime();
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
  intake_.allow_retention(sat, kNoTime);  // its new owner deletes behind its own filter
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

void OwnedSpacecraftTracker::maintain_leases() {
  const auto now_steady = std::chrono::steady_clock::now();
  next_lease_round_ =
      now_steady + std::chrono::microseconds(std::max<int64_t>(1, config_.lease_utime() / 3));
  const int64_t now = wall_utime();
  const int64_t ttl = config_.lease_utime();
  const std::string& me = config_.station.id;
  std::vector<std::pair<std::string, int64_t>> acquired;  // (sat, epoch), taken over below
  try {
    const auto before = leases_->heartbeat(me, instance_, settings_watch_.mine(), now, ttl);
    if (before && before->instance != instance_ && before->expires_utime > now) {
      if (last_beat_utime_ != 0) {
        // It beat since this process did: it is alive.
        throw StationConflict(fmt::format(
            "another magcald runs as station '{}' on {} (it beat at {}, wall clock): give each "
            "daemon sharing a database its own [station] id (--station)",
            me, db_.name(), format_iso8601_utc(before->heartbeat_utime)));
      }
      spdlog::warn(
          "station '{}': the heartbeat of a previous process is live until {} (wall "
          "clock): a restart after a crash, or another magcald with the same [station] "
          "id (then both stop within {:.0f} s)",
          me, format_iso8601_utc(before->expires_utime), config_.fleet.lease_s / 3);
    }
    last_beat_utime_ = now;
    settings_watch_.check(leases_->stations(), now);
    for (const auto& sat : unregistered_) leases_->ensure(sat);
    unregistered_.clear();
    std::unordered_map<std::string, int64_t> renewed;
    for (const auto& l : leases_->renew_all(me, now, ttl)) renewed.emplace(l.sat_id, l.epoch);
    size_t held = 0;
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
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
    // within their time to live, or another process runs under this station id): taken over at
    // once, under the next epoch, so that the other process's fenced writes fail (no two
    // processes write one spacecraft's snapshots) until the heartbeat stops one of them.
    for (const auto& [sat, epoch] : renewed) {
      const SpacecraftTracker* t = fleet_.find(sat);
      if (t == nullptr || !t->owned) {
        ++held;  // (held either way: taken over now, or at a next round while it is renewed)
        if (acquired.size() >= kMaxTakeoversPerRound) continue;
        if (const auto lease = leases_->reclaim(sat, me, epoch, now, ttl)) {
          acquired.emplace_back(sat, lease->epoch);
        }
      }
    }
    const std::vector<storage::Lease> all = leases_->list();
    const std::vector<std::string> live = leases_->live_stations(now);
    live_stations_ = std::max<size_t>(1, live.size());
    const size_t share = (all.size() + live_stations_ - 1) / live_stations_;
    // Ownership follows reception (the owner of a spacecraft only this station receives reads
    // back nothing of other stations): of the free leases, those received here within the last
    // lease time are taken first, up to the share in received ones (the excess of others is
    // handed over below); the others up to the share. A free lease not received here is left
    // to its receivers for a lease round (lease_s / 3: each takes it at its next round) unless
    // its holder died or stopped (failover: taken at once), or no other station is live. A
    // spacecraft's first lease counts as handed over by its receiver.
    const int64_t received_since = saturating_sub(now, ttl);
    auto received_here = [&](const std::string& sat) {
      const SpacecraftTracker* t = fleet_.find(sat);
      return t != nullptr && t->received_since(received_since);
    };
    size_t held_received = 0;
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
      if (t.owned && received_here(sat)) ++held_received;
    });
    std::vector<std::pair<uint64_t, std::string>> free_received, free_other;
    std::unordered_map<std::string, int64_t> free_since;
    for (const auto& l : all) {
      if (l.held_at(now)) continue;
      if (received_here(l.sat_id)) {
        free_received.emplace_back(ownership_preference(l.sat_id, me), l.sat_id);
        continue;
      }
      // (This station's own lease that ran out, e.g. a stall: back at once too.)
      const bool holder_gone =
          l.owner == me ||
          (!l.owner.empty() && !std::binary_search(live.begin(), live.end(), l.owner));
      const auto seen = free_since_.find(l.sat_id);
      const int64_t since = seen == free_since_.end() ? now : seen->second;
      if (holder_gone || live.size() <= 1 || now - since >= ttl / 3) {
        free_other.emplace_back(ownership_preference(l.sat_id, me), l.sat_id);
      } else {
        free_since.emplace(l.sat_id, since);
      }
    }
    free_since_.swap(free_since);
    auto take = [&](std::vector<std::pair<uint64_t, std::string>>& free, bool received) {
      std::sort(free.rbegin(), free.rend());
      for (size_t i = 0; i < free.size() && (received ? held_received : held) < share &&
                         acquired.size() < kMaxTakeoversPerRound;
           ++i) {
        if (const auto lease = leases_->try_acquire(free[i].second, me, now, ttl)) {
          acquired.emplace_back(free[i].second, lease->epoch);
          ++held;
          if (received) ++held_received;
        }
      }
    };
    take(free_received, true);
    if (taking_leases_.load()) take(free_other, false);
    // Over the share: hand over those not received here first, then the ones this station
    // prefers least (the others take them at their next round), once their snapshots are
    // committed (one attempt: never waits through an outage).
    if (held > share && links_.commit_all(false)) {
      std::vector<std::tuple<bool, uint64_t, std::string>> mine;
      fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
        if (t.owned) mine.emplace_back(received_here(sat), ownership_preference(sat, me), sat);
      });
      std::sort(mine.begin(), mine.end());
      for (size_t i = 0; i < mine.size() && held > share; ++i) {
        const std::string& sat = std::get<2>(mine[i]);
        OwnedSpacecraft& t = *fleet_.find(sat);
        if (t.state_dirty) {
          storage::Transaction tx(db_);
          if (leases_->holds(sat, me, t.lease_epoch)) filter_states_->save(stored_state(sat, t));
          tx.commit();
        }
        leases_->release(sat, me, t.lease_epoch, wall_utime());
        spdlog::info("{}: handed over ({} live stations share {} spacecraft{})", sat,
                     live_stations_, all.size(),
                     std::get<0>(mine[i]) ? "" : "; received elsewhere or not at all");
        give_up(sat, t);
        --held;
      }
    }
    poll_refits_elsewhere();
    if (lease_round_failing_) {
      lease_round_failing_ = false;
      counters_.storage_path_recovered();
    }
  } catch (const storage::StorageError& e) {
    // Retried at the next round; a lease that runs out meanwhile is given up there.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    if (!lease_round_failing_) {
      lease_round_failing_ = true;
      counters_.storage_path_failing();
    }
    warnings_.warn("leases", fmt::format("database: lease round failed, retried in {:.0f} s: {}",
                                         config_.fleet.lease_s / 3, e.what()));
  }
  for (const auto& [sat, epoch] : acquired) {
    SpacecraftTracker* record = fleet_.find(sat);
    try {
      if (record == nullptr) {
        // Not received here (yet): its time base from the stored window.
        intake_.restore_spacecraft(sat);
        record = &fleet_.get(sat);
      }
      take_over(sat, *record, epoch);
    } catch (const storage::StorageError& e) {
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      spdlog::error("{}: takeover failed, lease given back: {}", sat, e.what());
      if (record == nullptr) record = &fleet_.get(sat);
      give_up(sat, *record);
      try {
        leases_->release(sat, me, epoch, wall_utime());
      } catch (const storage::StorageError&) {
        // It runs out by itself.
      }
    }
  }
  // More to take over: the next round at once, after the frames received meanwhile (not a
  // lease period later: the filters of the rest would wait that long).
  if (acquired.size() >= kMaxTakeoversPerRound) next_lease_round_ = {};
}

void OwnedSpacecraftTracker::release_all() {
  const std::string& me = config_.station.id;
  try {
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
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

void OwnedSpacecraftTracker::poll_refits_elsewhere() {
  // (Throws storage::StorageError: the lease round's; the list stays for the next round.)
  for (size_t i = 0; i < refits_elsewhere_.size();) {
    const std::string sat = refits_elsewhere_[i];
    SpacecraftTracker* record = fleet_.find(sat);
    if (record == nullptr || !record->owned) {
      refits_elsewhere_.erase(refits_elsewhere_.begin() + static_cast<std::ptrdiff_t>(i));
      continue;
    }
    if (refit_running_elsewhere(*jobs_, sat, config_.station.id)) {
      ++i;
      continue;
    }
    refits_elsewhere_.erase(refits_elsewhere_.begin() + static_cast<std::ptrdiff_t>(i));
    if (const auto id = jobs_->newest_reanchor_calibration_id(sat)) {
      catch_up_reanchor(sat, *record, *id);
    }
  }
}

void OwnedSpacecraftTracker::track_union(const std::string& sat, OwnedSpacecraft& t, bool drain,
                                         std::span<const storage::StoredSample> union_rows) {
  // An accepted refit posted meanwhile applies before the samples committed since.
  apply_reanchors_if_posted();
  if (!t.owned) return;
  if (union_rows.empty()) return;
  const int64_t now = wall_utime();
  const int64_t newest = union_rows.back().utime;
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
  for (const auto& row : union_rows) {
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
    apply_reanchors_if_posted();
    state_was_due = state_was_due || t.state_due;
  }
  // A state due here (a snapshot, a re-anchor) but stored by a flush above goes in again with
  // every sample read now: a restart then re-runs none of them.
  if (state_was_due && t.owned) mark_state_due(sat, t);
  // Its retention follows the filter.
  if (t.owned) intake_.allow_retention(sat, t.filtered_utime);
}

void OwnedSpacecraftTracker::track_owned(bool drain) {
  if (tracking_) return;
  tracking_ = true;
  struct Done {
    bool& flag;
    ~Done() { flag = false; }
  } done{tracking_};
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
  const int64_t quiet_since_utime = saturating_sub(wall_utime(), config_.reorder_delay_utime());
  auto due = [&](const OwnedSpacecraft& t) {
    return t.union_due || poll_all ||
           (due_poll && t.union_newest_utime != kNoTime &&
            (t.filtered_utime == kNoTime || t.union_newest_utime > t.filtered_utime) &&
            t.union_grew_wall_utime <= quiet_since_utime);
  };
  try {
    union_due_sats_.clear();
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
      if (t.owned && due(t)) union_due_sats_.push_back(&sat);  // (map keys: stable)
    });
    // Their samples after the filter, kUnionReadsPerStatement spacecraft per read.
    for (size_t begin = 0; begin < union_due_sats_.size(); begin += kUnionReadsPerStatement) {
      const size_t n = std::min(kUnionReadsPerStatement, union_due_sats_.size() - begin);
      union_requests_.clear();
      for (size_t i = begin; i < begin + n; ++i) {
        OwnedSpacecraft& t = *fleet_.find(*union_due_sats_[i]);
        t.union_due = false;  // (again once a commit meanwhile stores more of it)
        const int64_t from = t.filtered_utime == kNoTime ? std::numeric_limits<int64_t>::min() / 2
                                                         : t.filtered_utime + 1;
        union_requests_.push_back({*union_due_sats_[i], from, std::numeric_limits<int64_t>::max()});
      }
      samples_.read_windows(union_requests_, union_rows_, union_row_ends_);
      size_t from_row = 0;
      for (size_t i = 0; i < n; ++i) {
        const std::string& sat = *union_due_sats_[begin + i];
        const auto rows = std::span(union_rows_).subspan(from_row, union_row_ends_[i] - from_row);
        from_row = union_row_ends_[i];
        track_union(sat, *fleet_.find(sat), drain, rows);
      }
    }
  } catch (const storage::StorageError& e) {
    // The filters wait where they are (a database outage): read again once commits go through.
    counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
    fleet_.for_each([](const std::string&, OwnedSpacecraft& t) { t.union_due = t.owned; });
    warnings_.warn("track", fmt::format("database: the owned filters could not read the stored "
                                        "samples, retried: {}",
                                        e.what()));
  }
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
    if (hooks_.on_snapshot) {
      for (auto p = pending_snapshots_.begin(); p != end; ++p)
        hooks_.on_snapshot(p->sat_id, p->result);
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

void OwnedSpacecraftTracker::check_data_clock(const std::string& sat_id, OwnedSpacecraft& t) {
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
  if (!links_.commit_all(!intake_.has_spill())) {
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

void OwnedSpacecraftTracker::request_deferred_refits() {
  if (deferred_refits_.empty()) return;
  // Requested before retention runs (their floor).
  const auto due = std::move(deferred_refits_);
  deferred_refits_.clear();
  for (const auto& [sat, t_ref] : due) {
    if (hooks_.on_refit_due) hooks_.on_refit_due(sat, t_ref, "scheduled");
  }
}

void OwnedSpacecraftTracker::check_early_refit(const std::string& sat_id, OwnedSpacecraft& t) {
  if (t.next_early_refit_samples <= 0 || t.n_samples < t.next_early_refit_samples ||
      !t.ukf.initialized() || t.filtered_utime == kNoTime) {
    return;
  }
  // The refit reads what is committed; so does its key below. (During an outage: asked again
  // with the next samples.)
  if (!links_.commit_all(!intake_.has_spill())) return;
  const EarlyRefitPlan plan = config_.early_refits();
  const int64_t n = plan.latest_within(t.n_samples);
  std::optional<int64_t> first_utime, t_ref;
  try {
    first_utime = samples_.utime_at_rank(sat_id, 0);
    t_ref = samples_.utime_at_rank(sat_id, n - 1);
    if (!t_ref) {
      // Fewer stored than counted (duplicates only the insert saw): due once they are.
      t.n_samples = samples_.count(sat_id);
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
