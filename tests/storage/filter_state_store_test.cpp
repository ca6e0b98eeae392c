// filter_states table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp):
// bit-exact round trip of x and P, upsert per (sat, method).
#include "storage/filter_state_store.hpp"

#include <catch2/catch.hpp>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>

#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

bool bit_equal(double a, double b) {
  return std::memcmp(&a, &b, sizeof a) == 0;
}

FilterState random_state(const std::string& sat, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(-1e3, 1e3);
  FilterState s;
  s.sat_id = sat;
  s.method = "ukf";
  for (auto& v : s.x) v = u(rng);
  for (auto& v : s.P) v = u(rng) * 1e-7;
  // Values that a decimal text round trip would not preserve.
  s.x[0] = 0.1 + 0.2;
  s.P[80] = std::numeric_limits<double>::denorm_min();
  s.P[1] = -0.0;
  s.last_utime = 1'767'225'600'123'456LL;
  s.n_samples = 123456;
  s.counters = {1, 2, 3, 0, 255};
  s.updated_utime = 42;
  return s;
}

std::string fmt_sat(int i) {
  return (i < 10 ? "SAT-0" : "SAT-") + std::to_string(i);
}

}  // namespace

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "filter state round-trips bit for bit and is replaced per (sat, method)",
                          "[filter_states]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_filter_state_store();
  std::mt19937_64 rng(11);
  const FilterState a = random_state("SAT1", rng);
  store->save(a);
  auto back = store->load("SAT1", "ukf");
  REQUIRE(back.has_value());
  for (size_t i = 0; i < a.x.size(); ++i) CHECK(bit_equal(back->x[i], a.x[i]));
  for (size_t i = 0; i < a.P.size(); ++i) CHECK(bit_equal(back->P[i], a.P[i]));
  CHECK(back->last_utime == a.last_utime);
  CHECK(back->n_samples == a.n_samples);
  CHECK(back->counters == a.counters);
  CHECK(back->updated_utime == 42);

  FilterState a2 = random_state("SAT1", rng);
  a2.counters.clear();
  a2.updated_utime = 0;  // now
  store->save(a2);
  back = store->load("SAT1", "ukf");
  CHECK(back->x == a2.x);
  CHECK(back->counters.empty());
  CHECK(back->updated_utime > 1'700'000'000'000'000LL);

  FilterState e = random_state("SAT1", rng);
  e.method = "ekf";
  store->save(e);
  CHECK(store->load_all().size() == 2);
  CHECK_FALSE(store->load("SAT2", "ukf").has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "save_all stores a batch as saves one by one would (the later of a key)",
                          "[filter_states]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_filter_state_store();
  std::mt19937_64 rng(3);
  store->save(random_state("SAT-00", rng));  // replaced below
  // 70 = 64 + 4 + 2 rows (PostgreSQL's statement sizes) after SAT-07's two states become one;
  // out of key order.
  std::vector<FilterState> batch;
  for (int i = 70; i >= 0; --i) batch.push_back(random_state(fmt_sat(i), rng));
  FilterState later = random_state("SAT-07", rng);
  later.n_samples = 7;
  batch.push_back(later);
  store->save_all(batch);
  store->save_all({});
  const auto all = store->load_all();
  REQUIRE(all.size() == 71);
  for (const FilterState& want : batch) {
    if (want.sat_id == "SAT-07" && want.n_samples != 7) continue;  // replaced by the later one
    const auto got = store->load(want.sat_id, "ukf");
    REQUIRE(got.has_value());
    CHECK(got->n_samples == want.n_samples);
    for (size_t i = 0; i < want.P.size(); ++i) CHECK(bit_equal(got->P[i], want.P[i]));
    CHECK(got->counters == want.counters);
  }
}

TEMPLATE_TEST_CASE_METHOD(
    BackendTest,
    "the refit a state was re-anchored on round-trips, a state from before schema 4 has none",
    "[filter_states]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_filter_state_store();
  std::mt19937_64 rng(5);
  FilterState s = random_state("SAT1", rng);
  CHECK(s.anchor_calibration_id == 0);  // none, unless set
  store->save(s);
  CHECK(store->load("SAT1", "ukf")->anchor_calibration_id == 0);
  s.anchor_calibration_id = 1234;
  store->save(s);
  CHECK(store->load("SAT1", "ukf")->anchor_calibration_id == 1234);
  this->db->exec("UPDATE filter_states SET anchor_calibration_id = NULL");  // as migrated from 3
  CHECK_FALSE(store->load("SAT1", "ukf")->anchor_calibration_id.has_value());
  CHECK_FALSE(store->load_all().front().anchor_calibration_id.has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a filter state blob of the wrong size is reported, not misread",
                          "[filter_states]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_filter_state_store();
  std::mt19937_64 rng(3);
  store->save(random_state("SAT1", rng));
  this->db->exec("UPDATE filter_states SET P = " + TestType::zero_blob_sql(80));
  CHECK_THROWS_AS(store->load("SAT1", "ukf"), StorageError);
}
