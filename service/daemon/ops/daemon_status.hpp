// A running daemon's status at this moment: the queue's gauges and the status message
// (daemon_status_t on MAGCAL_STATUS, systemd's STATUS= and the log's status line).
#pragma once

#include <chrono>
#include <cstdint>

#include "service/daemon/intake/ingest_queue.hpp"
#include "service/daemon/ops/health.hpp"

namespace magcal {

QueueGauge queue_gauge(const IngestQueue& queue);

// Sets counters.storage_pending to `pending_samples` (the samples the worker holds uncommitted)
// and returns the status message for now, `started` being the daemon's start.
daemon_status_t current_status(DaemonCounters& counters, const QueueGauge& queue,
                               int64_t pending_samples,
                               std::chrono::steady_clock::time_point started);

}  // namespace magcal
