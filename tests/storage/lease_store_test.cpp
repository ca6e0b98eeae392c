// leases table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): one owner per
// spacecraft, renewal, expiry and takeover with a new epoch (fencing), release, and daemons
// racing for the same leases on their own connections.
#include "storage/lease_store.hpp"

#include <algorithm>
#include <catch2/catch.hpp>
#include <map>
#include <string>
#include <vector>

#include "storage/migrations.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kTtl = 30 * kSecond;
constexpr int64_t kT0 = 1'767'225'600LL * kSecond;

}  // namespace

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a lease has one owner until it expires, then the next takes it over "
                          "with a new epoch",
                          "[leases]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto leases = this->db->make_lease_store();
  CHECK_FALSE(leases->get("SAT1").has_value());
  CHECK_FALSE(leases->owner_of("SAT1", kT0).has_value());

  const auto a = leases->try_acquire("SAT1", "A", kT0, kTtl);
  REQUIRE(a.has_value());
  CHECK(a->owner == "A");
  CHECK(a->epoch == 1);
  CHECK(a->acquired_utime == kT0);
  CHECK(a->expires_utime == kT0 + kTtl);
  CHECK(leases->owner_of("SAT1", kT0 + kTtl - 1) == "A");
  CHECK_FALSE(leases->owner_of("SAT1", kT0 + kTtl).has_value());  // expired: nobody's

  // Held: refused to another owner; the owner's own acquire renews it (same epoch).
  CHECK_FALSE(leases->try_acquire("SAT1", "B", kT0 + kTtl - 1, kTtl).has_value());
  const auto again = leases->try_acquire("SAT1", "A", kT0 + 10 * kSecond, kTtl);
  REQUIRE(again.has_value());
  CHECK(again->epoch == 1);
  CHECK(again->acquired_utime == kT0);
  CHECK(again->expires_utime == kT0 + 10 * kSecond + kTtl);
  CHECK(leases->renew("SAT1", "A", 1, kT0 + 20 * kSecond, kTtl));
  CHECK(leases->get("SAT1")->expires_utime == kT0 + 20 * kSecond + kTtl);
  CHECK(leases->holds("SAT1", "A", 1));
  CHECK_FALSE(leases->holds("SAT1", "B", 1));

  // A is silent past its expiry: B takes it over (epoch 2); A's renewal, release and fence fail.
  const int64_t later = kT0 + 20 * kSecond + kTtl;
  const auto b = leases->try_acquire("SAT1", "B", later, kTtl);
  REQUIRE(b.has_value());
  CHECK(b->epoch == 2);
  CHECK(b->acquired_utime == later);
  CHECK_FALSE(leases->renew("SAT1", "A", 1, later, kTtl));
  CHECK_FALSE(leases->release("SAT1", "A", 1, later));
  CHECK_FALSE(leases->holds("SAT1", "A", 1));
  CHECK(leases->holds("SAT1", "B", 2));
  CHECK(leases->owner_of("SAT1", later) == "B");

  // B releases: A may take it at once, as a new owner (epoch 3), so A's old epoch stays stale.
  CHECK(leases->release("SAT1", "B", 2, later + kSecond));
  CHECK_FALSE(leases->owner_of("SAT1", later + kSecond).has_value());
  const auto a2 = leases->try_acquire("SAT1", "A", later + kSecond, kTtl);
  REQUIRE(a2.has_value());
  CHECK(a2->epoch == 3);
  CHECK_FALSE(leases->renew("SAT1", "A", 1, later + kSecond, kTtl));
  CHECK(leases->renew("SAT1", "A", 3, later + kSecond, kTtl));

  // A new process of station A reclaims A's unexpired lease under the next epoch: the fence of
  // the old epoch fails (a second process under one station id writes nothing more); a stale
  // epoch or another owner cannot reclaim.
  const auto re = leases->reclaim("SAT1", "A", 3, later + 2 * kSecond, kTtl);
  REQUIRE(re.has_value());
  CHECK(re->owner == "A");
  CHECK(re->epoch == 4);
  CHECK(re->acquired_utime == later + 2 * kSecond);
  CHECK(re->expires_utime == later + 2 * kSecond + kTtl);
  CHECK_FALSE(leases->holds("SAT1", "A", 3));
  CHECK(leases->holds("SAT1", "A", 4));
  CHECK_FALSE(leases->reclaim("SAT1", "A", 3, later + 2 * kSecond, kTtl).has_value());
  CHECK_FALSE(leases->reclaim("SAT1", "B", 4, later + 2 * kSecond, kTtl).has_value());
  CHECK(leases->renew("SAT1", "A", 4, later + 2 * kSecond, kTtl));

  leases->try_acquire("SAT0", "B", kT0, kTtl);
  const auto all = leases->list();
  REQUIRE(all.size() == 2);
  CHECK(all[0].sat_id == "SAT0");
  CHECK(all[1].sat_id == "SAT1");
  CHECK(all[1].owner == "A");
  CHECK_THROWS_AS(leases->try_acquire("SAT2", "A", kT0, 0), StorageError);
  CHECK_THROWS_AS(leases->try_acquire("SAT2", "", kT0, kTtl), StorageError);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "not_held names the leases of a list that their owner no longer holds",
                          "[leases]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto leases = this->db->make_lease_store();
  for (const char* sat : {"SAT1", "SAT2", "SAT3"})
    REQUIRE(leases->try_acquire(sat, "A", kT0, kTtl));
  REQUIRE(leases->try_acquire("SAT4", "B", kT0, kTtl));
  // SAT2 taken over by B after A's lease ran out (epoch 2).
  REQUIRE(leases->try_acquire("SAT2", "B", kT0 + kTtl, kTtl));
  const std::vector<LeaseStore::Held> mine{
      {"SAT3", 1}, {"SAT2", 1}, {"SAT5", 1}, {"SAT1", 1}, {"SAT4", 1}};
  CHECK(leases->not_held("A", mine) == std::vector<std::string>{"SAT2", "SAT5", "SAT4"});
  CHECK(leases->not_held("B", mine) ==
        std::vector<std::string>{"SAT3", "SAT2", "SAT5", "SAT1"});  // SAT2 is B's at epoch 2
  CHECK(leases->not_held("A", {}).empty());
}

TEMPLATE_TEST_CASE(
    "daemons racing for leases: exactly one owner of each, and exactly one takes "
    "over an expired lease",
    "[leases]", SqliteBackend, PostgresBackend) {
  TestType backend;
  const auto setup = backend.open();
  if (!setup) return;
  constexpr int kDaemons = 4;
  constexpr int kSpacecraft = 40;
  std::vector<std::unique_ptr<Connection>> connections;
  std::vector<std::string> owners, sats;
  for (int d = 0; d < kDaemons; ++d) {
    connections.push_back(backend.open_again());
    owners.push_back("D" + std::to_string(d));
  }
  for (int i = 0; i < kSpacecraft; ++i) sats.push_back("SAT" + std::to_string(i));

  // Round 1 at kT0 (every lease free), round 2 once all have expired: each daemon tries every
  // spacecraft, starting at its own offset so the daemons collide on every row.
  auto race = [&](int64_t now_utime) {
    std::vector<std::vector<Lease>> won(kDaemons);
    std::vector<std::unique_ptr<LeaseStore>> stores;
    for (const auto& c : connections) stores.push_back(c->make_lease_store());
    const auto errors = magcal::test::run_at_once(kDaemons, [&](int d) {
      const auto k = static_cast<size_t>(d);
      for (int i = 0; i < kSpacecraft; ++i) {
        const std::string& sat = sats[static_cast<size_t>((i + d * 7) % kSpacecraft)];
        if (auto l = stores[k]->try_acquire(sat, owners[k], now_utime, kTtl)) {
          won[k].push_back(*l);
        }
      }
    });
    std::map<std::string, Lease> winner;
    for (int d = 0; d < kDaemons; ++d) {
      CHECK(errors[static_cast<size_t>(d)] == "");
      for (const Lease& l : won[static_cast<size_t>(d)]) {
        INFO(l.sat_id << " won by " << l.owner);
        CHECK(winner.emplace(l.sat_id, l).second);  // one winner per lease
      }
    }
    CHECK(winner.size() == kSpacecraft);
    return winner;
  };
  const auto first = race(kT0);
  for (const auto& [sat, l] : first) CHECK(l.epoch == 1);
  const auto second = race(kT0 + kTtl);  // all expired: each taken over once
  const auto leases = setup->make_lease_store();
  for (const auto& [sat, l] : second) {
    INFO(sat);
    // Its previous owner re-acquiring keeps the epoch; anyone else is a takeover.
    CHECK(l.epoch == (l.owner == first.at(sat).owner ? 1 : 2));
    CHECK(leases->owner_of(sat, kT0 + kTtl) == l.owner);
  }
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "registered spacecraft, renewing all of an owner's leases at once, and "
                          "the live stations",
                          "[leases]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto leases = this->db->make_lease_store();
  // A registered spacecraft has a row without an owner: free, and its first owner gets epoch 1.
  leases->ensure("SAT1");
  leases->ensure("SAT2");
  leases->ensure("SAT3");
  REQUIRE(leases->list().size() == 3);
  CHECK(leases->get("SAT1")->owner.empty());
  CHECK_FALSE(leases->owner_of("SAT1", kT0).has_value());
  const auto a1 = leases->try_acquire("SAT1", "A", kT0, kTtl);
  REQUIRE(a1.has_value());
  CHECK(a1->epoch == 1);
  leases->ensure("SAT1");  // registering again changes nothing
  CHECK(leases->get("SAT1")->owner == "A");
  REQUIRE(leases->try_acquire("SAT2", "A", kT0, kTtl).has_value());
  REQUIRE(leases->try_acquire("SAT3", "B", kT0, kTtl).has_value());

  // renew_all: every lease A holds, and only those; returned with their epochs.
  auto renewed = leases->renew_all("A", kT0 + 10 * kSecond, kTtl);
  REQUIRE(renewed.size() == 2);
  for (const auto& l : renewed) {
    CHECK(l.owner == "A");
    CHECK(l.epoch == 1);
    CHECK(l.expires_utime == kT0 + 10 * kSecond + kTtl);
  }
  CHECK(leases->get("SAT3")->expires_utime == kT0 + kTtl);  // B's untouched
  // A released SAT2: not brought back by A's next renewal (another daemon may be taking it).
  REQUIRE(leases->release("SAT2", "A", 1, kT0 + 11 * kSecond));
  renewed = leases->renew_all("A", kT0 + 12 * kSecond, kTtl);
  REQUIRE(renewed.size() == 1);
  CHECK(renewed[0].sat_id == "SAT1");
  // Expired (A stalled past its lease): not renewed either, so A learns it lost it.
  CHECK(leases->renew_all("A", kT0 + 12 * kSecond + kTtl, kTtl).empty());
  CHECK_THROWS_AS(leases->renew_all("", kT0, kTtl), StorageError);

  // Stations: live until their heartbeat's time to live runs out, or they leave.
  CHECK(leases->live_stations(kT0).empty());
  CHECK_FALSE(leases->heartbeat("A", "a1", {}, kT0, kTtl).has_value());  // the first beat
  leases->heartbeat("B", "b1", {}, kT0 + 5 * kSecond, kTtl);
  CHECK(leases->live_stations(kT0 + 6 * kSecond) == std::vector<std::string>{"A", "B"});
  CHECK(leases->live_stations(kT0 + kTtl) == std::vector<std::string>{"B"});
  // Beats again: live again; the row as it was comes back (a second process under one id would
  // see the other's instance there).
  const auto before = leases->heartbeat("A", "a2", {}, kT0 + kTtl, kTtl);
  REQUIRE(before.has_value());
  CHECK(before->instance == "a1");
  CHECK(before->heartbeat_utime == kT0);
  CHECK(before->expires_utime == kT0 + kTtl);
  CHECK(leases->heartbeat("A", "a2", {}, kT0 + kTtl + 1, kTtl)->instance == "a2");
  CHECK(leases->live_stations(kT0 + kTtl + 1) == std::vector<std::string>{"A", "B"});
  leases->leave("B", kT0 + kTtl + 2);
  CHECK(leases->live_stations(kT0 + kTtl + 2) == std::vector<std::string>{"A"});
  CHECK_THROWS_AS(leases->heartbeat("C", "c1", {}, kT0, 0), StorageError);
  // Every row stays listed, the one that left with its end (the same order on both backends:
  // "a" sorts after "B" by bytes).
  leases->heartbeat("a", "x1", {}, kT0, kTtl);
  const auto rows = leases->stations();
  REQUIRE(rows.size() == 3);
  CHECK(rows[0].station == "A");
  CHECK(rows[0].instance == "a2");
  CHECK(rows[0].heartbeat_utime == kT0 + kTtl + 1);
  CHECK(rows[0].live_at(kT0 + kTtl + 2));
  CHECK(rows[1].station == "B");
  CHECK(rows[1].expires_utime == kT0 + kTtl + 2);
  CHECK_FALSE(rows[1].live_at(kT0 + kTtl + 2));
  CHECK(rows[2].station == "a");
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a station's settings round-trip through its heartbeat, and a beat "
                          "without settings reads as unknown",
                          "[leases]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto leases = this->db->make_lease_store();
  // Text as the daemon writes it (service/io/station_settings.hpp): lines, '=' and quotes kept.
  const StationSettings a{"refit.every_hours=6\nukf.cold_start=data\nx.list=[S1,\"S 2\"]\n",
                          "0123456789abcdef"};
  leases->heartbeat("A", "a1", a, kT0, kTtl);
  leases->heartbeat("B", "b1", {}, kT0, kTtl);
  auto rows = leases->stations();
  REQUIRE(rows.size() == 2);
  REQUIRE(rows[0].settings.has_value());
  CHECK(rows[0].settings->text == a.text);
  CHECK(rows[0].settings->hash == a.hash);
  CHECK_FALSE(rows[1].settings.has_value());
  // Each beat writes what the process declares now (a restart with another config).
  const StationSettings a2{"refit.every_hours=0\n", "fedcba9876543210"};
  leases->heartbeat("A", "a2", a2, kT0 + kSecond, kTtl);
  leases->heartbeat("B", "b1", a, kT0 + kSecond, kTtl);
  rows = leases->stations();
  REQUIRE(rows.size() == 2);
  CHECK(rows[0].settings->text == a2.text);
  CHECK(rows[0].settings->hash == a2.hash);
  REQUIRE(rows[1].settings.has_value());
  CHECK(rows[1].settings->text == a.text);
}

TEMPLATE_TEST_CASE("a stations row from before the settings columns reads as unknown settings",
                   "[leases]", SqliteBackend, PostgresBackend) {
  TestType backend;
  {
    const auto db = backend.open(magcal::test::before_migration("_station_settings"));
    if (!db) return;
    db->exec(
        "INSERT INTO stations (station, heartbeat_utime, expires_utime, instance) "
        "VALUES ('gs-old', 5, 10, 'i1')");
  }
  const auto db = backend.open_again();  // migrates to the newest schema
  const auto rows = db->make_lease_store()->stations();
  REQUIRE(rows.size() == 1);
  CHECK(rows[0].station == "gs-old");
  CHECK(rows[0].expires_utime == 10);
  CHECK_FALSE(rows[0].settings.has_value());
}
