#include "service/daemon/ops/daemon_status.hpp"

#include "pipeline/time_utc.hpp"

namespace magcal {

QueueGauge queue_gauge(const IngestQueue& queue) {
  return {queue.depth_samples(), queue.capacity_samples(), queue.overflow_samples()};
}

daemon_status_t current_status(DaemonCounters& counters, const QueueGauge& queue,
                               int64_t pending_samples,
                               std::chrono::steady_clock::time_point started) {
  counters.storage_pending.store(pending_samples, std::memory_order_relaxed);
  const auto uptime_s =
      std::chrono::duration_cast<std::chrono::seconds>(std::chrono::steady_clock::now() - started)
          .count();
  return make_status_message(counters, queue, now_utime(), uptime_s);
}

}  // namespace magcal
