// Who should own what in a fleet: the decisions of one lease round, as a pure function of what
// the database and this station know (no database here; OwnedSpacecraftTracker's lease round
// reads the inputs, then applies the decisions: acquire, reclaim, release).
//
// The live stations share the spacecraft evenly (each up to its fair share, rounded up), and
// ownership follows reception: the owner of a spacecraft only this station receives reads back
// nothing of other stations. Of the free leases, those received here within the last lease time
// are taken first, up to the share in received ones; the others up to the share, unless this
// station stopped taking leases (its input ended: it takes only what it still drains). A free
// lease not received here is left to its receivers for a third of the lease time (each takes
// it at its next round) unless its holder died or stopped (failover: taken at once), or no
// other station is live. Over the share, a station hands over those not received here first,
// then those it prefers least (rendezvous hashing: the stations of a fleet try different
// spacecraft first).
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include "storage/lease_store.hpp"

namespace magcal {

// How much `station` prefers to own `sat_id` (rendezvous hashing).
uint64_t ownership_preference(const std::string& sat_id, const std::string& station);

// A lease this process holds (it runs the spacecraft's filter).
struct OwnedLease {
  std::string sat_id;
  int64_t epoch = 0;
  bool received = false;  // received here within the last lease time
};

struct LeaseRoundInput {
  std::string station;  // this station's id
  int64_t now_utime = 0;
  int64_t lease_utime = 0;                 // a lease's time to live
  std::vector<storage::Lease> leases;      // every spacecraft's (LeaseStore::list())
  std::vector<std::string> live_stations;  // sorted (LeaseStore::live_stations())
  // This station's leases as renewed this round (LeaseStore::renew_all()): sat_id -> epoch.
  std::unordered_map<std::string, int64_t> renewed;
  std::vector<OwnedLease> owned;  // what this process believed it held before the round
  // Spacecraft received here within the last lease time, sorted.
  std::vector<std::string> received;
  bool taking_leases = true;  // false: only free leases received here are taken
  // Free leases not received here left to their receivers, and since when (the previous
  // round's LeaseRoundDecisions::free_since).
  std::unordered_map<std::string, int64_t> free_since;
};

struct LeaseRoundDecisions {
  size_t live_stations = 1;  // at least this one
  size_t share = 0;          // leases each live station may hold
  // Owned here, but renewed under another epoch or not at all (expired, taken over): given up.
  std::vector<std::string> lost;
  // This station's leases (renewed) that this process does not know it holds (a restart within
  // their time to live, or another process under this station id): taken over under the next
  // epoch (sat_id, the renewed epoch).
  std::vector<std::pair<std::string, int64_t>> reclaim;
  // Held after the losses (the reclaimed counted in), and of those owned, the received ones.
  size_t held = 0;
  size_t held_received = 0;
  // Free leases to try, most preferred first: received here, then the others.
  std::vector<std::string> free_received;
  std::vector<std::string> free_other;
  std::unordered_map<std::string, int64_t> free_since;  // the next round's input
};

LeaseRoundDecisions decide_lease_round(const LeaseRoundInput& in);

// Tries the free leases in the order decided, up to the share (received ones counted apart) and
// at most `max_acquisitions` in all (counting `acquired` already there), with `try_acquire`
// (sat_id -> the epoch granted, or nullopt when another station was faster). Adds what it got
// to `acquired` and to d.held / d.held_received.
template <typename TryAcquire>
void acquire_free_leases(LeaseRoundDecisions& d, bool taking_leases, size_t max_acquisitions,
                         std::vector<std::pair<std::string, int64_t>>& acquired,
                         TryAcquire&& try_acquire) {
  auto take = [&](const std::vector<std::string>& free, bool received) {
    for (size_t i = 0; i < free.size() && (received ? d.held_received : d.held) < d.share &&
                       acquired.size() < max_acquisitions;
         ++i) {
      if (const std::optional<int64_t> epoch = try_acquire(free[i])) {
        acquired.emplace_back(free[i], *epoch);
        ++d.held;
        if (received) ++d.held_received;
      }
    }
  };
  take(d.free_received, true);
  if (taking_leases) take(d.free_other, false);
}

// Over the share: the spacecraft to hand over, in order (not received here first, then the
// least preferred), `held - share` of them.
std::vector<std::string> leases_to_hand_over(const std::vector<OwnedLease>& owned,
                                             const std::string& station, size_t held, size_t share);

}  // namespace magcal
