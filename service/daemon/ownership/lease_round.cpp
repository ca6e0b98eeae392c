#include "service/daemon/ownership/lease_round.hpp"

#include <algorithm>
#include <functional>
#include <string_view>
#include <tuple>
#include <unordered_set>

namespace magcal {

uint64_t ownership_preference(const std::string& sat_id, const std::string& station) {
  const uint64_t h = std::hash<std::string>{}(sat_id)*0x9E3779B97F4A7C15ULL;
  return h ^ (std::hash<std::string>{}(station) + 0x7F4A7C15ULL + (h << 6) + (h >> 2));
}

LeaseRoundDecisions decide_lease_round(const LeaseRoundInput& in) {
  LeaseRoundDecisions d;
  const int64_t now = in.now_utime;
  std::unordered_set<std::string_view> owned_here;  // still, after the losses
  for (const auto& o : in.owned) {
    const auto it = in.renewed.find(o.sat_id);
    if (it == in.renewed.end() || it->second != o.epoch) {
      d.lost.push_back(o.sat_id);
      continue;
    }
    owned_here.insert(o.sat_id);
    ++d.held;
    if (o.received) ++d.held_received;
  }
  // (Held either way: taken over now, or at a next round while it is renewed. One lost under
  // an older epoch but renewed under a newer one is this station's again.)
  for (const auto& [sat, epoch] : in.renewed) {
    if (!owned_here.contains(sat)) {
      ++d.held;
      d.reclaim.emplace_back(sat, epoch);
    }
  }
  d.live_stations = std::max<size_t>(1, in.live_stations.size());
  d.share = (in.leases.size() + d.live_stations - 1) / d.live_stations;
  auto received_here = [&](const std::string& sat) {
    return std::binary_search(in.received.begin(), in.received.end(), sat);
  };
  std::vector<std::pair<uint64_t, std::string>> free_received, free_other;
  for (const auto& l : in.leases) {
    if (l.held_at(now)) continue;
    const uint64_t preference = ownership_preference(l.sat_id, in.station);
    if (received_here(l.sat_id)) {
      free_received.emplace_back(preference, l.sat_id);
      continue;
    }
    // (This station's own lease that ran out, e.g. a stall: back at once too.) A spacecraft's
    // first lease counts as handed over by its receiver.
    const bool holder_gone =
        l.owner == in.station ||
        (!l.owner.empty() &&
         !std::binary_search(in.live_stations.begin(), in.live_stations.end(), l.owner));
    const auto seen = in.free_since.find(l.sat_id);
    const int64_t since = seen == in.free_since.end() ? now : seen->second;
    if (holder_gone || in.live_stations.size() <= 1 || now - since >= in.lease_utime / 3) {
      free_other.emplace_back(preference, l.sat_id);
    } else {
      d.free_since.emplace(l.sat_id, since);
    }
  }
  auto most_preferred_first = [](std::vector<std::pair<uint64_t, std::string>>& free,
                                 std::vector<std::string>& out) {
    std::sort(free.rbegin(), free.rend());
    out.reserve(free.size());
    for (auto& [preference, sat] : free) out.push_back(std::move(sat));
  };
  most_preferred_first(free_received, d.free_received);
  most_preferred_first(free_other, d.free_other);
  return d;
}

std::vector<std::string> leases_to_hand_over(const std::vector<OwnedLease>& owned,
                                             const std::string& station, size_t held,
                                             size_t share) {
  std::vector<std::tuple<bool, uint64_t, std::string>> order;
  order.reserve(owned.size());
  for (const auto& o : owned) {
    order.emplace_back(o.received, ownership_preference(o.sat_id, station), o.sat_id);
  }
  std::sort(order.begin(), order.end());
  std::vector<std::string> out;
  for (size_t i = 0; i < order.size() && held > share; ++i, --held) {
    out.push_back(std::get<2>(order[i]));
  }
  return out;
}

}  // namespace magcal
