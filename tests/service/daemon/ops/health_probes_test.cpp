// The probes and the metrics totals (service/daemon/ops/): healthy and ready follow the
// database's capabilities, not its name; the outage note names the limit, the samples held and
// (with a spill file) the file's; the totals copy every counter once.
#include <catch2/catch.hpp>

#include <atomic>
#include <string>

#include "service/daemon/ops/daemon_status.hpp"
#include "service/daemon/ops/health_probes.hpp"
#include "service/daemon/ops/metric_totals.hpp"

using magcal::DaemonConfig;
using magcal::DaemonCounters;
using magcal::HealthProbes;

namespace {

DaemonConfig config_for(const std::string& db_path) {
  DaemonConfig c;
  c.storage.db_path = db_path;
  return c;
}

bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

}  // namespace

TEST_CASE("where a storage failure is unhealthy, /-/healthy answers for it and /-/ready not",
          "[ops][probes]") {
  const DaemonConfig config = config_for("/var/lib/magcal/magcal.db");
  REQUIRE(config.storage_capabilities().failure_is_unhealthy);
  DaemonCounters counters;
  std::atomic<bool> fatal{false};
  HealthProbes probes(
      config, counters, fatal, [] { return true; }, 0);
  CHECK(probes.healthy());
  CHECK_FALSE(probes.ready());  // LCM not live yet
  probes.set_lcm_live(true);
  CHECK(probes.ready());
  CHECK(probes.storage_outage_note().empty());
  counters.storage_pending.store(7);
  counters.storage_path_failing();
  CHECK_FALSE(probes.healthy());
  CHECK(probes.ready());
  const std::string note = probes.storage_outage_note();
  CHECK(contains(note, "[storage] max_failure_s"));
  CHECK(contains(note, "7 samples held in memory"));
  CHECK_FALSE(contains(note, "spill file"));
  CHECK_FALSE(contains(note, "unreachable since"));
  CHECK(probes.storage_failing_s() >= 0.0);
  counters.storage_path_recovered();
  CHECK(probes.healthy());
  CHECK(probes.storage_failing_s() == 0.0);
  fatal.store(true);
  CHECK_FALSE(probes.healthy());
  CHECK_FALSE(probes.ready());
}

TEST_CASE("where an outage is ridden out, /-/ready answers for it, /-/healthy stays 200",
          "[ops][probes]") {
  const DaemonConfig config = config_for("postgresql://magcal@db.example/magcal");
  REQUIRE_FALSE(config.storage_capabilities().failure_is_unhealthy);
  REQUIRE(config.storage_capabilities().spill_during_outage);
  DaemonCounters counters;
  std::atomic<bool> fatal{false};
  std::atomic<bool> reached{false};
  HealthProbes probes(
      config, counters, fatal, [&] { return reached.load(); },
      /*start_utime=*/1'700'000'000'000'000);
  probes.set_lcm_live(true);
  counters.storage_path_failing();
  counters.spill_held.store(12);
  counters.spill_held_earlier.store(3);
  CHECK(probes.healthy());
  CHECK_FALSE(probes.ready());
  std::string note = probes.storage_outage_note();
  CHECK(contains(note, "[storage] pg_max_failure_s"));
  CHECK(contains(note, ", 12 in the spill file (and 3 an earlier run left there)"));
  CHECK(contains(note, "unreachable since magcald started at 2023-11-14T22:13:20"));
  reached.store(true);  // restored since: the outage began later
  note = probes.storage_outage_note();
  CHECK_FALSE(contains(note, "unreachable since"));
  CHECK(magcal::spill_books(counters, config.storage_capabilities()) ==
        " spill_held=12 (and 3 of an earlier run)");
  CHECK(magcal::spill_books(counters, config_for("x.db").storage_capabilities()).empty());
}

TEST_CASE("the metrics totals copy every counter once", "[ops][metrics]") {
  DaemonCounters c;
  c.reject(magcal::RejectReason::kDuplicate, 4);
  c.storage_pending.store(5);
  c.spilled.store(6);
  c.spill_held.store(7);
  c.spill_held_earlier.store(8);
  c.spill_bytes.store(9);
  c.spill_recovered.store(10);
  c.spill_dropped.store(11);
  c.leases_lost.store(12);
  c.fleet_settings_mismatch.store(2);
  c.commit_seconds.observe(0.003);
  auto& sat = c.spacecraft.spacecraft("SAT-A");
  sat.received.store(100);
  sat.stored.store(90);
  sat.owned.store(true);
  sat.set_ukf_snapshot({true, {1.0, 2.0, 3.0}, {0.1, 0.2, 0.3}, true});
  const auto t = magcal::metric_totals(c, magcal::QueueGauge{13, 1000, 14}, 1.5);
  REQUIRE(t.rejected_by_reason.size() == static_cast<size_t>(magcal::kRejectReasonCount));
  int64_t duplicates = -1;
  for (const auto& [reason, n] : t.rejected_by_reason) {
    if (reason == "duplicate") duplicates = n;
  }
  CHECK(duplicates == 4);
  CHECK(t.queue_depth == 13);
  CHECK(t.queue_overflow == 14);
  CHECK(t.storage_healthy);
  CHECK(t.storage_failing_s == 1.5);
  CHECK(t.storage_pending == 5);
  CHECK(t.spilled == 6);
  CHECK(t.spill_held == 7 + 8);  // everything the file holds
  CHECK(t.spill_bytes == 9);
  CHECK(t.spill_recovered == 10);
  CHECK(t.spill_dropped == 11);
  CHECK(t.leases_lost == 12);
  CHECK(t.fleet_settings_mismatch == 2);
  REQUIRE(t.spacecraft.size() == 1);
  CHECK(t.spacecraft[0].sat_label == "SAT-A");
  CHECK(t.spacecraft[0].received == 100);
  CHECK(t.spacecraft[0].stored == 90);
  CHECK(t.spacecraft[0].owned);
  CHECK(t.spacecraft[0].has_ukf_snapshot);
  CHECK(t.spacecraft[0].ukf_bias_nT[2] == 3.0);
  CHECK(t.spacecraft[0].ukf_bias_sigma_nT[1] == 0.2);
  REQUIRE(t.commit_bucket_counts.size() == magcal::CommitLatencyHistogram::kBuckets);
  int64_t commits = 0;
  for (int64_t n : t.commit_bucket_counts) commits += n;
  CHECK(commits == 1);
  CHECK(t.commit_sum_s == Approx(0.003).margin(1e-6));
}
