// magcald's operations server ([http] listen; none when ""): /metrics from the daemon's
// counters (metric_totals.hpp), /-/healthy and /-/ready from HealthProbes, the read-only API
// over its own connection (service/http/operations_server.hpp). Bound before the database is
// opened (a port it cannot bind is an error at start that leaves no file behind), served once
// the database is open (or found unreachable), stopped by the daemon or its destructor.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "service/config/daemon_config.hpp"
#include "service/daemon/ops/health_probes.hpp"

namespace magcal {

namespace http {
class DaemonMetrics;
class OperationsServer;
}  // namespace http

class OperationsEndpoint {
 public:
  // Reads what it serves from these at each request: they must outlive it.
  struct Sources {
    const DaemonCounters& counters;
    const HealthProbes& probes;
    std::function<QueueGauge()> queue;
  };

  OperationsEndpoint(const DaemonConfig& config, Sources sources);
  ~OperationsEndpoint();
  OperationsEndpoint(const OperationsEndpoint&) = delete;
  OperationsEndpoint& operator=(const OperationsEndpoint&) = delete;

  // Binds [http] listen (nothing when it is ""): empty, or why it could not.
  std::string bind();
  // After the database and LCM are open: empty, or why the server could not start.
  std::string serve();
  void stop();       // idempotent
  int port() const;  // the bound port; 0 when the server is off

 private:
  const DaemonConfig& config_;
  Sources sources_;
  std::unique_ptr<http::DaemonMetrics> metrics_;
  std::unique_ptr<http::OperationsServer> server_;
};

}  // namespace magcal
