// OwnedSpacecraftTracker's lease round: reads what the decisions need, lets decide_lease_round()
// decide (lease_round.hpp), and applies the decisions to the database (heartbeat, renew,
// acquire, reclaim, release: the epochs fence every write).
#include <algorithm>
#include <unordered_map>

#include <spdlog/spdlog.h>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ownership/owned_spacecraft_tracker.hpp"

namespace magcal {
namespace {

// Takeovers per lease round: each reads the spacecraft's state, history and job log (a few ms
// on PostgreSQL), so a daemon taking over hundreds of spacecraft keeps receiving in between;
// the rest follow at the next rounds.
constexpr size_t kMaxTakeoversPerRound = 256;

}  // namespace

bool OwnedSpacecraftTracker::begin_lease_round() {
  const auto now_steady = std::chrono::steady_clock::now();
  next_lease_round_ =
      now_steady + std::chrono::microseconds(std::max<int64_t>(1, config_.lease_utime() / 3));
  round_ = LeaseRoundState{};
  LeaseRoundInput in;
  in.station = config_.station.id;
  in.now_utime = now_utime();
  in.lease_utime = config_.lease_utime();
  const int64_t now = in.now_utime;
  const int64_t ttl = in.lease_utime;
  const std::string& me = in.station;
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
    for (const auto& l : leases_->renew_all(me, now, ttl)) in.renewed.emplace(l.sat_id, l.epoch);
    // What this station receives: ownership follows reception (the owner of a spacecraft only
    // this station receives reads back nothing of other stations).
    const int64_t received_since = saturating_sub(now, ttl);
    round_.received_since_utime = received_since;
    fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
      const bool received = t.received_since(received_since);
      if (received) in.received.push_back(sat);
      if (t.owned) in.owned.push_back({sat, t.lease_epoch, received});
    });
    std::sort(in.received.begin(), in.received.end());
    in.leases = leases_->list();
    in.live_stations = leases_->live_stations(now);
    in.taking_leases = taking_leases_.load();
    in.free_since = std::move(free_since_);
    LeaseRoundDecisions d = decide_lease_round(in);
    free_since_ = std::move(d.free_since);
    live_stations_ = d.live_stations;
    for (const auto& sat : d.lost) {
      spdlog::warn("{}: lease lost (expired or taken over): its UKF stops here", sat);
      counters_.leases_lost.fetch_add(1, std::memory_order_relaxed);
      give_up(sat, *fleet_.find(sat));
    }
    // Leases still this station's that this process does not know it holds: taken over at
    // once, under the next epoch, so that the other process's fenced writes fail (no two
    // processes write one spacecraft's snapshots) until the heartbeat stops one of them.
    for (const auto& [sat, epoch] : d.reclaim) {
      if (round_.acquired.size() >= kMaxTakeoversPerRound) break;
      if (const auto lease = leases_->reclaim(sat, me, epoch, now, ttl)) {
        round_.acquired.emplace_back(sat, lease->epoch);
      }
    }
    acquire_free_leases(d, in.taking_leases, kMaxTakeoversPerRound, round_.acquired,
                        [&](const std::string& sat) -> std::optional<int64_t> {
                          const auto lease = leases_->try_acquire(sat, me, now, ttl);
                          if (!lease) return std::nullopt;
                          return lease->epoch;
                        });
    round_.held = d.held;
    round_.share = d.share;
    round_.n_leases = in.leases.size();
    return round_.held > round_.share;
  } catch (const storage::StorageError& e) {
    lease_round_failed(e);
    return false;
  }
}

void OwnedSpacecraftTracker::hand_over_excess(bool writes_committed) {
  // Over the share: hand over those not received here first, then the ones this station
  // prefers least (the others take them at their next round), once their snapshots are
  // committed.
  if (round_.failed || !writes_committed || round_.held <= round_.share) return;
  const std::string& me = config_.station.id;
  const int64_t received_since = round_.received_since_utime;
  std::vector<OwnedLease> owned;
  fleet_.for_each([&](const std::string& sat, SpacecraftTracker& t) {
    if (t.owned) owned.push_back({sat, t.lease_epoch, t.received_since(received_since)});
  });
  try {
    for (const auto& sat : leases_to_hand_over(owned, me, round_.held, round_.share)) {
      OwnedSpacecraft& t = *fleet_.find(sat);
      if (t.state_dirty) {
        storage::Transaction tx(db_);
        if (leases_->holds(sat, me, t.lease_epoch)) filter_states_->save(stored_state(sat, t));
        tx.commit();
      }
      leases_->release(sat, me, t.lease_epoch, now_utime());
      const bool received = fleet_.find(sat)->received_since(received_since);
      spdlog::info("{}: handed over ({} live stations share {} spacecraft{})", sat, live_stations_,
                   round_.n_leases, received ? "" : "; received elsewhere or not at all");
      give_up(sat, t);
      --round_.held;
    }
  } catch (const storage::StorageError& e) {
    lease_round_failed(e);
  }
}

void OwnedSpacecraftTracker::end_lease_round() {
  if (round_.failed) return;
  try {
    poll_refits_elsewhere();
  } catch (const storage::StorageError& e) {
    lease_round_failed(e);
    return;
  }
  if (lease_round_failing_) {
    lease_round_failing_ = false;
    counters_.storage_path_recovered();
  }
}

void OwnedSpacecraftTracker::lease_round_failed(const storage::StorageError& e) {
  // Retried at the next round; a lease that runs out meanwhile is given up there.
  round_.failed = true;
  counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
  if (!lease_round_failing_) {
    lease_round_failing_ = true;
    counters_.storage_path_failing();
  }
  warnings_.warn("leases", fmt::format("database: lease round failed, retried in {:.0f} s: {}",
                                       config_.fleet.lease_s / 3, e.what()));
}

std::vector<std::string> OwnedSpacecraftTracker::acquired_unreceived() {
  std::vector<std::string> out;
  for (const auto& [sat, epoch] : round_.acquired) {
    if (fleet_.find(sat) == nullptr) out.push_back(sat);
  }
  return out;
}

void OwnedSpacecraftTracker::takeover_failed(const std::string& sat,
                                             const storage::StorageError& e) {
  const auto it = std::find_if(round_.acquired.begin(), round_.acquired.end(),
                               [&](const auto& a) { return a.first == sat; });
  if (it == round_.acquired.end()) return;
  const int64_t epoch = it->second;
  round_.acquired.erase(it);
  counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
  spdlog::error("{}: takeover failed, lease given back: {}", sat, e.what());
  give_up(sat, fleet_.get(sat));
  try {
    leases_->release(sat, config_.station.id, epoch, now_utime());
  } catch (const storage::StorageError&) {
    // It runs out by itself.
  }
}

void OwnedSpacecraftTracker::take_over_acquired() {
  for (const auto& [sat, epoch] : round_.acquired) {
    SpacecraftTracker& record = fleet_.get(sat);
    try {
      take_over(sat, record, epoch);
    } catch (const storage::StorageError& e) {
      counters_.storage_failures.fetch_add(1, std::memory_order_relaxed);
      spdlog::error("{}: takeover failed, lease given back: {}", sat, e.what());
      give_up(sat, record);
      try {
        leases_->release(sat, config_.station.id, epoch, now_utime());
      } catch (const storage::StorageError&) {
        // It runs out by itself.
      }
    }
  }
  // More to take over: the next round at once, after the frames received meanwhile (not a
  // lease period later: the filters of the rest would wait that long).
  if (round_.acquired.size() >= kMaxTakeoversPerRound) next_lease_round_ = {};
  round_.acquired.clear();
}

void OwnedSpacecraftTracker::release_all() {
  const std::string& me = config_.station.id;
  try {
    fleet_.for_each([&](const std::string& sat, OwnedSpacecraft& t) {
      if (!t.owned) return;
      if (!t.state_dirty) leases_->release(sat, me, t.lease_epoch, now_utime());
      give_up(sat, t);
    });
    leases_->leave(me, now_utime());
  } catch (const storage::StorageError& e) {
    // The leases and the heartbeat run out by themselves.
    spdlog::warn("database: leases not handed back at stop ({}); they expire within {} s", e.what(),
                 config_.fleet.lease_s);
  }
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
    if (refit_running_elsewhere(sat)) {
      ++i;
      continue;
    }
    refits_elsewhere_.erase(refits_elsewhere_.begin() + static_cast<std::ptrdiff_t>(i));
    if (const auto id = jobs_->newest_reanchor_calibration_id(sat)) {
      catch_up_reanchor(sat, *record, *id);
    }
  }
}

}  // namespace magcal
