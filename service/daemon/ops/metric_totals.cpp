#include "service/daemon/ops/metric_totals.hpp"

namespace magcal {
namespace {

http::DaemonMetrics::SpacecraftTotals spacecraft_totals(const SpacecraftCounters& c) {
  http::DaemonMetrics::SpacecraftTotals s;
  s.sat_label = c.sat_label;
  s.received = c.received.load(std::memory_order_relaxed);
  s.stored = c.stored.load(std::memory_order_relaxed);
  s.missing = c.missing.load(std::memory_order_relaxed);
  s.refits_accepted = c.refits_accepted.load(std::memory_order_relaxed);
  s.refits_rejected = c.refits_rejected.load(std::memory_order_relaxed);
  s.refits_error = c.refits_error.load(std::memory_order_relaxed);
  s.refits_claimed_elsewhere = c.refits_claimed_elsewhere.load(std::memory_order_relaxed);
  s.owned = c.owned.load(std::memory_order_relaxed);
  s.last_refit_success_utime = c.last_refit_success_utime.load(std::memory_order_relaxed);
  const SpacecraftCounters::UkfSnapshot ukf = c.ukf_snapshot();
  s.has_ukf_snapshot = ukf.present;
  s.ukf_bias_nT = ukf.bias_nT;
  s.ukf_bias_sigma_nT = ukf.bias_sigma_nT;
  s.ukf_accepted = ukf.accepted;
  return s;
}

}  // namespace

http::DaemonMetrics::Totals metric_totals(const DaemonCounters& counters, const QueueGauge& queue,
                                          double storage_failing_s) {
  http::DaemonMetrics::Totals t;
  t.rejected_by_reason.reserve(kRejectReasonCount);
  for (int i = 0; i < kRejectReasonCount; ++i) {
    const auto r = static_cast<RejectReason>(i);
    t.rejected_by_reason.emplace_back(to_string(r), counters.rejected_count(r));
  }
  t.queue_depth = queue.depth;
  t.queue_overflow = queue.overflow;
  t.storage_healthy = counters.storage_healthy();
  t.storage_failing_s = storage_failing_s;
  t.storage_pending = counters.storage_pending.load(std::memory_order_relaxed);
  t.spilled = counters.spilled.load(std::memory_order_relaxed);
  t.spill_held = counters.spill_held.load(std::memory_order_relaxed) +
                 counters.spill_held_earlier.load(std::memory_order_relaxed);
  t.spill_bytes = counters.spill_bytes.load(std::memory_order_relaxed);
  t.spill_recovered = counters.spill_recovered.load(std::memory_order_relaxed);
  t.spill_dropped = counters.spill_dropped.load(std::memory_order_relaxed);
  t.leases_lost = counters.leases_lost.load(std::memory_order_relaxed);
  t.fleet_settings_mismatch = counters.fleet_settings_mismatch.load(std::memory_order_relaxed);
  counters.spacecraft.for_each(
      [&t](const SpacecraftCounters& c) { t.spacecraft.push_back(spacecraft_totals(c)); });
  const auto buckets = counters.commit_seconds.bucket_counts();
  t.commit_bucket_counts.assign(buckets.begin(), buckets.end());
  t.commit_sum_s = counters.commit_seconds.sum_s();
  return t;
}

}  // namespace magcal
