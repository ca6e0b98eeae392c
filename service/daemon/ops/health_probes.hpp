// magcald's liveness and readiness as the operations server answers them (/-/healthy,
// /-/ready) and the note both add during a storage failure. Read from the http threads.
//
// /-/healthy: ingest, storage and the scheduler work. A dead thread or storage broken past its
// limit ends the process (fatal). Where a storage failure means this process is unhealthy
// (storage::Capabilities::failure_is_unhealthy: a local disk that fails wants this host's
// attention, and a restart reopens the file), "working" also means storage is not failing right
// now (a failing operation is being retried). Otherwise an outage is the network's or the
// server's, ridden out for the limit (samples held, then spilled): a liveness probe must not
// restart a daemon for it (that would not help, and would drop what it holds in memory), so it
// stays healthy and /-/ready answers 503 instead; both bodies say why.
// /-/ready: the database is open (the server only starts after it is) and LCM is live; where a
// failure is not unhealthy, also storage is not failing (nor unreachable since the start).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>

#include "service/config/daemon_config.hpp"
#include "service/daemon/ops/health.hpp"
#include "storage/connection.hpp"

namespace magcal {

class HealthProbes {
 public:
  // References must outlive the probes. `fatal`: the daemon stops on a fatal error.
  // `database_reached`: the worker restored from the database (false while it has been
  // unreachable since the start). `start_utime`: what the note quotes as the start.
  HealthProbes(const DaemonConfig& config, const DaemonCounters& counters,
               const std::atomic<bool>& fatal, std::function<bool()> database_reached,
               int64_t start_utime);

  // Subscribed and receiving (ready) or not.
  void set_lcm_live(bool live) { lcm_live_.store(live); }

  bool healthy() const;
  bool ready() const;
  // How long storage has been failing, s (0 while it works).
  double storage_failing_s() const;
  // The probes' extra line during a storage failure ("" otherwise).
  std::string storage_outage_note() const;

 private:
  const DaemonConfig& config_;
  const storage::Capabilities capabilities_;
  const DaemonCounters& counters_;
  const std::atomic<bool>& fatal_;
  const std::function<bool()> database_reached_;
  const int64_t start_utime_;
  std::atomic<bool> lcm_live_{false};
};

// ", N in the spill file" (and an earlier run's there, not committed yet).
std::string spill_note(const DaemonCounters& c);
// The final status line's books of the spill file, " spill_held=N" (and an earlier run's):
// received = stored + rejected + overflow + spill_held. "" without a spill file.
std::string spill_books(const DaemonCounters& c, const storage::Capabilities& capabilities);

}  // namespace magcal
