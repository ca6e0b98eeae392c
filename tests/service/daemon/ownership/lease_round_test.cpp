// The lease round's policy (decide_lease_round(), lease_round.hpp) without a database: a small
// fleet of stations sharing a lease table in memory, each running rounds as the daemon does
// (renew, decide, acquire, hand over), on a wall clock the test moves.
#include <catch2/catch.hpp>

#include <algorithm>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "service/daemon/ownership/lease_round.hpp"

namespace magcal {
namespace {

constexpr int64_t kLease_utime = 30'000'000;  // [fleet] lease_s = 30

struct Station {
  std::string id;
  std::set<std::string> received;  // received within the last lease time
  bool live = true;
  bool taking_leases = true;
  std::map<std::string, int64_t> owned;  // what this process holds: sat -> epoch
  std::unordered_map<std::string, int64_t> free_since;
};

// The lease table and the stations' heartbeats, in memory.
struct Fleet {
  int64_t now_utime = 1'700'000'000'000'000;
  std::map<std::string, storage::Lease> leases;
  std::map<std::string, Station> stations;

  explicit Fleet(const std::vector<std::string>& sats) {
    for (const auto& sat : sats) leases[sat] = storage::Lease{sat, "", 0, 0, 0};
  }
  Station& add(const std::string& id, std::set<std::string> received) {
    Station& s = stations[id];
    s.id = id;
    s.received = std::move(received);
    return s;
  }
  std::vector<std::string> live() const {
    std::vector<std::string> out;
    for (const auto& [id, s] : stations) {
      if (s.live) out.push_back(id);
    }
    return out;  // (a std::map: sorted)
  }

  // One lease round of station `id`; returns its decisions.
  LeaseRoundDecisions round(const std::string& id) {
    Station& s = stations.at(id);
    LeaseRoundInput in;
    in.station = id;
    in.now_utime = now_utime;
    in.lease_utime = kLease_utime;
    for (auto& [sat, l] : leases) {
      if (l.owner == id && l.held_at(now_utime)) {
        l.expires_utime = now_utime + kLease_utime;
        in.renewed.emplace(sat, l.epoch);
      }
      in.leases.push_back(l);
    }
    in.live_stations = live();
    for (const auto& [sat, epoch] : s.owned) {
      in.owned.push_back({sat, epoch, s.received.count(sat) > 0});
    }
    in.received.assign(s.received.begin(), s.received.end());
    in.taking_leases = s.taking_leases;
    in.free_since = s.free_since;
    LeaseRoundDecisions d = decide_lease_round(in);
    s.free_since = d.free_since;
    for (const auto& sat : d.lost) s.owned.erase(sat);
    std::vector<OwnedLease> owned_before;  // handed over: of those owned before the round
    for (const auto& [sat, epoch] : s.owned) {
      owned_before.push_back({sat, epoch, s.received.count(sat) > 0});
    }
    std::vector<std::pair<std::string, int64_t>> acquired;
    for (const auto& [sat, epoch] : d.reclaim) {
      storage::Lease& l = leases.at(sat);
      l.epoch = epoch + 1;
      acquired.emplace_back(sat, l.epoch);
    }
    acquire_free_leases(d, s.taking_leases, 256, acquired,
                        [&](const std::string& sat) -> std::optional<int64_t> {
                          storage::Lease& l = leases.at(sat);
                          if (l.held_at(now_utime)) return std::nullopt;
                          if (l.owner != id) ++l.epoch;
                          l.owner = id;
                          l.expires_utime = now_utime + kLease_utime;
                          return l.epoch;
                        });
    for (const auto& sat : leases_to_hand_over(owned_before, id, d.held, d.share)) {
      leases.at(sat).expires_utime = now_utime;  // released: free, its last holder kept
      s.owned.erase(sat);
    }
    for (const auto& [sat, epoch] : acquired) s.owned[sat] = epoch;
    return d;
  }
  // Every live station's round, in turn, `n` times, a third of the lease time apart.
  void rounds(int n) {
    for (int i = 0; i < n; ++i) {
      for (auto& [id, s] : stations) {
        if (s.live) round(id);
      }
      now_utime += kLease_utime / 3;
    }
  }
  // A station stops without releasing (a crash): its heartbeat and leases run out.
  void crash(const std::string& id) {
    stations.at(id).live = false;
    stations.at(id).owned.clear();
    for (auto& [sat, l] : leases) {
      if (l.owner == id) l.expires_utime = std::min(l.expires_utime, now_utime);
    }
  }
  size_t owned_count(const std::string& id) const { return stations.at(id).owned.size(); }
  // Every lease held by exactly the station whose process owns it.
  void check_consistent() const {
    std::map<std::string, std::string> owner_of;
    for (const auto& [id, s] : stations) {
      for (const auto& [sat, epoch] : s.owned) {
        INFO(sat);
        CHECK(owner_of.emplace(sat, id).second);  // one owner
        CHECK(leases.at(sat).owner == id);
        CHECK(leases.at(sat).epoch == epoch);
        CHECK(leases.at(sat).held_at(now_utime));
      }
    }
  }
  size_t n_owned() const {
    size_t n = 0;
    for (const auto& [id, s] : stations) n += s.owned.size();
    return n;
  }
};

std::vector<std::string> sats(int n) {
  std::vector<std::string> out;
  for (int i = 0; i < n; ++i) out.push_back("SAT-" + std::to_string(i));
  return out;
}

std::set<std::string> all_of(const std::vector<std::string>& v) {
  return {v.begin(), v.end()};
}

}  // namespace

TEST_CASE("alone, a station takes every lease at its first round, received or not",
          "[lease_round]") {
  Fleet f(sats(5));
  f.add("A", {"SAT-0", "SAT-1"});
  const LeaseRoundDecisions d = f.round("A");
  CHECK(d.live_stations == 1);
  CHECK(d.share == 5);
  CHECK(f.owned_count("A") == 5);
  f.check_consistent();
  // The next round renews them all: nothing lost, nothing to take.
  const LeaseRoundDecisions again = f.round("A");
  CHECK(again.lost.empty());
  CHECK(again.held == 5);
  CHECK(again.free_received.empty());
  CHECK(again.free_other.empty());
}

TEST_CASE("two stations receiving everything share it evenly, a late one gets its half",
          "[lease_round]") {
  const auto all = sats(8);
  Fleet f(all);
  f.add("A", all_of(all));
  f.round("A");
  REQUIRE(f.owned_count("A") == 8);  // alone so far
  f.add("B", all_of(all));
  // A, over its share now, hands over 4; B takes them at its next round.
  f.rounds(2);
  CHECK(f.owned_count("A") == 4);
  CHECK(f.owned_count("B") == 4);
  CHECK(f.n_owned() == 8);
  f.check_consistent();
}

TEST_CASE("three stations share nine spacecraft three each, ten at most four each",
          "[lease_round]") {
  for (const int n : {9, 10}) {
    INFO(n << " spacecraft");
    const auto all = sats(n);
    Fleet f(all);
    for (const char* id : {"A", "B", "C"}) f.add(id, all_of(all));
    f.rounds(4);
    const size_t share = (static_cast<size_t>(n) + 2) / 3;
    for (const char* id : {"A", "B", "C"}) {
      INFO(id);
      CHECK(f.owned_count(id) <= share);
      if (n % 3 == 0) CHECK(f.owned_count(id) == share);
    }
    CHECK(f.n_owned() == static_cast<size_t>(n));
    f.check_consistent();
  }
}

TEST_CASE("ownership follows uneven receptions: each owns what only it receives", "[lease_round]") {
  // A receives SAT-0..3, B SAT-4..5: a share of 3 each. B's two are B's; A keeps three of its
  // four and the fourth goes to B once A's receivers had their third of a lease time for it.
  Fleet f(sats(6));
  f.add("A", {"SAT-0", "SAT-1", "SAT-2", "SAT-3"});
  f.add("B", {"SAT-4", "SAT-5"});
  const LeaseRoundDecisions first_a = f.round("A");
  CHECK(first_a.share == 3);
  CHECK(f.owned_count("A") == 3);  // received ones only, up to the share
  for (const auto& sat : f.stations.at("A").owned)
    CHECK(f.stations.at("A").received.count(sat.first));
  // SAT-4 and SAT-5 are left to their receiver for now.
  CHECK(first_a.free_since.count("SAT-4") == 1);
  CHECK(first_a.free_since.count("SAT-5") == 1);
  f.round("B");
  CHECK(f.stations.at("B").owned.count("SAT-4") == 1);
  CHECK(f.stations.at("B").owned.count("SAT-5") == 1);
  f.rounds(4);
  CHECK(f.owned_count("A") == 3);
  CHECK(f.owned_count("B") == 3);
  for (const auto& [sat, epoch] : f.stations.at("A").owned) {
    CHECK(f.stations.at("A").received.count(sat) == 1);
  }
  CHECK(f.n_owned() == 6);
  f.check_consistent();
}

TEST_CASE("a dead station's leases are taken at once, without waiting for their receivers",
          "[lease_round]") {
  const auto all = sats(6);
  Fleet f(all);
  f.add("A", {"SAT-0", "SAT-1"});
  f.add("B", {"SAT-2", "SAT-3"});
  f.add("C", {"SAT-4", "SAT-5"});
  f.rounds(4);
  REQUIRE(f.owned_count("C") == 2);
  f.crash("C");
  // A free lease not received here would wait a third of a lease time for its receivers; one
  // whose holder died is taken at the next round (A and B now share 3 each).
  const LeaseRoundDecisions a = f.round("A");
  CHECK(a.share == 3);
  CHECK(a.free_since.empty());
  CHECK(f.owned_count("A") == 3);
  f.round("B");
  CHECK(f.owned_count("B") == 3);
  CHECK(f.n_owned() == 6);
  f.check_consistent();
}

TEST_CASE("a draining station takes of a stopped station's leases only what it received",
          "[lease_round]") {
  const auto all = sats(4);
  Fleet f(all);
  f.add("A", all_of(all));
  f.add("B", all_of(all));
  f.rounds(3);
  REQUIRE(f.owned_count("A") == 2);
  REQUIRE(f.owned_count("B") == 2);
  const std::string a_first = f.stations.at("A").owned.begin()->first;
  const std::string a_second = std::next(f.stations.at("A").owned.begin())->first;
  // B's input ended (it drains what it received: of A's, only a_first) ...
  Station& b = f.stations.at("B");
  b.taking_leases = false;
  b.received = {a_first};
  for (const auto& [sat, epoch] : b.owned) b.received.insert(sat);
  // ... and A stops cleanly: it hands everything back and its heartbeat ends.
  for (const auto& [sat, epoch] : f.stations.at("A").owned) {
    f.leases.at(sat).expires_utime = f.now_utime;
  }
  f.stations.at("A").owned.clear();
  f.stations.at("A").live = false;
  const LeaseRoundDecisions d = f.round("B");
  CHECK(d.live_stations == 1);
  CHECK(f.owned_count("B") == 3);
  CHECK(b.owned.count(a_first) == 1);
  CHECK(b.owned.count(a_second) == 0);  // left for a station that takes leases
  CHECK(d.free_other == std::vector<std::string>{a_second});
  f.check_consistent();
}

TEST_CASE("a station that stopped taking leases takes only the free ones it received",
          "[lease_round]") {
  Fleet f(sats(4));
  Station& a = f.add("A", {"SAT-1"});
  a.taking_leases = false;
  const LeaseRoundDecisions d = f.round("A");
  // Alone, it would take all four; its input ended, so only what it still drains.
  CHECK(d.free_other.size() == 3);
  CHECK(f.owned_count("A") == 1);
  CHECK(f.stations.at("A").owned.count("SAT-1") == 1);
  // Still renewing what it holds.
  f.now_utime += kLease_utime / 2;
  const LeaseRoundDecisions next = f.round("A");
  CHECK(next.lost.empty());
  CHECK(f.owned_count("A") == 1);
  f.check_consistent();
}

TEST_CASE("a lease lost to another epoch is given up, one this station holds unknown is reclaimed",
          "[lease_round]") {
  Fleet f(sats(2));
  f.add("A", {"SAT-0", "SAT-1"});
  f.round("A");
  REQUIRE(f.owned_count("A") == 2);
  // Another station took SAT-0 while A stalled past its lease.
  f.leases.at("SAT-0").owner = "B";
  ++f.leases.at("SAT-0").epoch;
  // A restart within the lease time: the process knows none of SAT-1's lease.
  const int64_t epoch_1 = f.stations.at("A").owned.at("SAT-1");
  f.stations.at("A").owned.erase("SAT-1");
  const LeaseRoundDecisions d = f.round("A");
  CHECK(d.lost == std::vector<std::string>{"SAT-0"});
  REQUIRE(d.reclaim.size() == 1);
  CHECK(d.reclaim[0] == std::pair<std::string, int64_t>{"SAT-1", epoch_1});
  CHECK(f.stations.at("A").owned.at("SAT-1") == epoch_1 + 1);  // under the next epoch
  CHECK(f.stations.at("A").owned.count("SAT-0") == 0);
}

TEST_CASE("a handover gives back what is not received here first", "[lease_round]") {
  const std::vector<OwnedLease> owned = {
      {"SAT-0", 1, true}, {"SAT-1", 1, false}, {"SAT-2", 1, true}, {"SAT-3", 1, false}};
  const auto out = leases_to_hand_over(owned, "A", 4, 2);
  REQUIRE(out.size() == 2);
  CHECK(std::set<std::string>(out.begin(), out.end()) == std::set<std::string>{"SAT-1", "SAT-3"});
  CHECK(leases_to_hand_over(owned, "A", 4, 4).empty());
  CHECK(leases_to_hand_over(owned, "A", 5, 2).size() == 3);
}

}  // namespace magcal
