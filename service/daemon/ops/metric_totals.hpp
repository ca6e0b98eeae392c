// What /metrics shows of the daemon's counters (health.hpp), read at scrape time: the daemon
// counts once, in its own types, and the metrics library only sees these totals.
#pragma once

#include "service/daemon/ops/health.hpp"
#include "service/http/metrics.hpp"

namespace magcal {

// The totals of `counters` and the queue's gauges, with storage failing for `storage_failing_s`
// (0: it works). The spill gauge counts everything the file holds, an earlier run's too (what
// an operator watches for; the status line's books count this run's).
http::DaemonMetrics::Totals metric_totals(const DaemonCounters& counters, const QueueGauge& queue,
                                          double storage_failing_s);

}  // namespace magcal
