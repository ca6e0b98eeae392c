// The daemon's own counters (service/daemon/ops/health.hpp): the per-spacecraft table the ingest
// path counts in and /metrics reads at scrape time, and the lock-free commit-latency histogram.
#include <algorithm>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>

#include "service/daemon/ops/health.hpp"

using magcal::CommitLatencyHistogram;
using magcal::SpacecraftCounters;
using magcal::SpacecraftCounterTable;

TEST_CASE("spacecraft counters: one entry per id, capped, nothing lost past the cap",
          "[daemon][counters]") {
  SpacecraftCounterTable table;
  SpacecraftCounters& a = table.spacecraft("SAT-A");
  CHECK(&table.spacecraft("SAT-A") == &a);  // cached by the threads: the same entry every time
  CHECK(a.sat_label == "SAT-A");
  constexpr size_t kExtra = 10;
  for (size_t i = 0; i + 1 < SpacecraftCounterTable::kMaxSpacecraft + kExtra; ++i) {
    std::string sat = "S";
    sat += std::to_string(i);
    table.spacecraft(sat).received.fetch_add(1);
  }
  std::set<std::string> labels;
  int64_t total = 0;
  table.for_each([&](const SpacecraftCounters& c) {
    labels.insert(c.sat_label);
    total += c.received.load();
  });
  CHECK(labels.size() == SpacecraftCounterTable::kMaxSpacecraft + 1);  // + "(other)"
  CHECK(labels.count(SpacecraftCounterTable::kOther) == 1);
  CHECK(total == static_cast<int64_t>(SpacecraftCounterTable::kMaxSpacecraft + kExtra - 1));
}

TEST_CASE("spacecraft counters: refits and the UKF snapshot", "[daemon][counters]") {
  SpacecraftCounterTable table;
  SpacecraftCounters& c = table.spacecraft("SAT-A");
  CHECK(!c.ukf_snapshot().present);
  c.count_refit(SpacecraftCounters::RefitVerdict::kAccepted, 1'577'923'200'000'000);
  c.count_refit(SpacecraftCounters::RefitVerdict::kRejected, 1'577'930'400'000'000);
  c.count_refit(SpacecraftCounters::RefitVerdict::kError, 0);
  CHECK(c.refits_accepted.load() == 1);
  CHECK(c.refits_rejected.load() == 1);
  CHECK(c.refits_error.load() == 1);
  // The accepted refit's time, not the rejected later one's.
  CHECK(c.last_refit_success_utime.load() == 1'577'923'200'000'000);
  c.set_ukf_snapshot({false, {1.0, 2.0, 3.0}, {0.1, 0.2, 0.3}, true});
  const auto s = c.ukf_snapshot();
  CHECK(s.present);
  CHECK(s.bias_nT[1] == 2.0);
  CHECK(s.bias_sigma_nT[2] == 0.3);
  CHECK(s.accepted);
}

TEST_CASE("spacecraft counters: counts from two threads while another reads add up",
          "[daemon][counters]") {
  SpacecraftCounterTable table;
  constexpr int kPerThread = 20000;
  auto count = [&](const std::string& sat) {
    SpacecraftCounters& own = table.spacecraft(sat);
    for (int i = 0; i < kPerThread; ++i) {
      own.received.fetch_add(1, std::memory_order_relaxed);
      table.spacecraft("shared").stored.fetch_add(1, std::memory_order_relaxed);
    }
  };
  std::thread t1(count, "A");
  std::thread t2(count, "B");
  for (int i = 0; i < 50; ++i) {
    int64_t seen = 0;
    table.for_each([&](const SpacecraftCounters& c) { seen += c.received.load(); });
    CHECK(seen <= 2 * kPerThread);
  }
  t1.join();
  t2.join();
  CHECK(table.spacecraft("A").received.load() + table.spacecraft("B").received.load() ==
        2 * kPerThread);
  CHECK(table.spacecraft("shared").stored.load() == 2 * kPerThread);
}

TEST_CASE("commit latency histogram: bucket by upper bound (le), +Inf, sum", "[daemon][counters]") {
  CommitLatencyHistogram h;
  const std::vector<double> observed_s{0.0, 0.0001, 0.00010001, 0.003, 0.003, 7.0, 11.0, 1e6};
  for (const double s : observed_s) h.observe(s);
  const auto counts = h.bucket_counts();
  const auto& bounds = CommitLatencyHistogram::kUpperBounds_s;
  REQUIRE(counts.size() == bounds.size() + 1);
  // Counted here independently: the first bound not below the value, else +Inf.
  std::vector<int64_t> expected(counts.size(), 0);
  for (const double s : observed_s) {
    size_t i = 0;
    while (i < bounds.size() && s > bounds[i]) ++i;
    ++expected[i];
  }
  CHECK(std::vector<int64_t>(counts.begin(), counts.end()) == expected);
  CHECK(counts.back() == 2);  // 11 s and 1e6 s are beyond the last bound
  double sum = 0.0;
  for (const double s : observed_s) sum += s;
  CHECK(h.sum_s() == Approx(sum).epsilon(1e-12));
}
