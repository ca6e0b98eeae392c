#include "service/daemon/ops/health_probes.hpp"

#include <algorithm>
#include <utility>

#include <fmt/format.h>

#include "pipeline/time_utc.hpp"

namespace magcal {

HealthProbes::HealthProbes(const DaemonConfig& config, const DaemonCounters& counters,
                           const std::atomic<bool>& fatal, std::function<bool()> database_reached,
                           int64_t start_utime)
    : config_(config),
      capabilities_(config.storage_capabilities()),
      counters_(counters),
      fatal_(fatal),
      database_reached_(std::move(database_reached)),
      start_utime_(start_utime) {}

bool HealthProbes::healthy() const {
  return !fatal_.load() && (!capabilities_.failure_is_unhealthy || counters_.storage_healthy());
}

bool HealthProbes::ready() const {
  return lcm_live_.load() && !fatal_.load() &&
         (capabilities_.failure_is_unhealthy || counters_.storage_healthy());
}

double HealthProbes::storage_failing_s() const {
  const int64_t since = counters_.storage_failing_since_utime.load();
  return since == 0 ? 0.0 : std::max<double>(0.0, static_cast<double>(now_utime() - since) * 1e-6);
}

std::string HealthProbes::storage_outage_note() const {
  if (counters_.storage_healthy()) return "";
  const int64_t since = counters_.storage_failing_since_utime.load();
  return fmt::format(
      "storage failing for {:.0f} s of [storage] {} = {:.0f} s (database {}{}): {} samples held "
      "in memory{}\n",
      storage_failing_s(), config_.storage_max_failure_key(), config_.storage_max_failure_s(),
      storage::database_name(config_.storage.db_path),
      database_reached_() || since == 0
          ? ""
          : ", unreachable since magcald started at " + format_iso8601_utc(start_utime_),
      counters_.storage_pending.load(),
      capabilities_.spill_during_outage ? spill_note(counters_) : "");
}

std::string spill_note(const DaemonCounters& c) {
  const int64_t earlier = c.spill_held_earlier.load();
  return fmt::format(
      ", {} in the spill file{}", c.spill_held.load(),
      earlier > 0 ? fmt::format(" (and {} an earlier run left there)", earlier) : "");
}

std::string spill_books(const DaemonCounters& c, const storage::Capabilities& capabilities) {
  if (!capabilities.spill_during_outage) return "";
  std::string books = fmt::format(" spill_held={}", c.spill_held.load());
  if (const int64_t earlier = c.spill_held_earlier.load(); earlier > 0) {
    books += fmt::format(" (and {} of an earlier run)", earlier);
  }
  return books;
}

}  // namespace magcal
