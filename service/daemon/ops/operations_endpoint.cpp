#include "service/daemon/ops/operations_endpoint.hpp"

#include <sys/resource.h>
#include <unistd.h>

#include <thread>
#include <utility>
#include <vector>

#include "service/daemon/ops/metric_totals.hpp"
#include "service/http/metrics.hpp"
#include "service/http/operations_server.hpp"

namespace magcal {
namespace {

// nice of the operations server's threads (ingest runs at the process's own, usually 0).
constexpr int kServerNice = 10;

}  // namespace

OperationsEndpoint::OperationsEndpoint(const DaemonConfig& config, Sources sources)
    : config_(config), sources_(std::move(sources)) {}

OperationsEndpoint::~OperationsEndpoint() = default;

std::string OperationsEndpoint::bind() {
  if (config_.http.listen.empty()) return "";
  metrics_ = std::make_unique<http::DaemonMetrics>(
      MAGCAL_VERSION, config_.station.id,
      std::vector<double>(CommitLatencyHistogram::kUpperBounds_s.begin(),
                          CommitLatencyHistogram::kUpperBounds_s.end()));
  metrics_->set_totals_source([this] {
    return metric_totals(sources_.counters, sources_.queue(), sources_.probes.storage_failing_s());
  });
  http::ServerHooks hooks;
  hooks.metrics_text = [this] { return metrics_->text(); };
  hooks.healthy = [this] { return sources_.probes.healthy(); };
  hooks.ready = [this] { return sources_.probes.ready(); };
  hooks.probe_detail = [this] { return sources_.probes.storage_outage_note(); };
  hooks.status_window_utime = config_.window_utime();
  std::string error;
  server_ = http::OperationsServer::bind(config_.http.listen, std::move(hooks), &error);
  if (!server_) return "[http] listen " + config_.http.listen + ": " + error;
  return "";
}

std::string OperationsEndpoint::serve() {
  if (!server_) return "";
  std::string error;
  bool served = false;
  // Started from a thread at a lower CPU priority, which every server thread inherits (Linux
  // nice is per thread, inherited at creation): on a saturated machine a client hammering the
  // API gets slower answers instead of slowing ingest (BM_DaemonReplayHttp measures both).
  std::thread starter([&] {
    ::setpriority(PRIO_PROCESS, static_cast<id_t>(::gettid()), kServerNice);
    const storage::OpenOptions db = config_.database_options();
    served = server_->serve(config_.storage.db_path, &error, db.connect_later, db.reply_timeout_ms);
  });
  starter.join();
  if (!served) {
    server_.reset();
    return "[http] listen " + config_.http.listen + ": " + error;
  }
  return "";  // the server logs its URL
}

void OperationsEndpoint::stop() {
  if (server_) server_->stop();
}

int OperationsEndpoint::port() const {
  return server_ ? server_->port() : 0;
}

}  // namespace magcal
