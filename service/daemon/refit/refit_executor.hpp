// What the refit thread (refit_thread.hpp) does with a request, on its own connection: the
// refit of each spacecraft the request names (on the wall clock, every one this daemon owns:
// the others' owners refit theirs), counted, published on LCM, logged, and an accepted result
// posted to the worker for re-anchoring. Storage errors are retried with backoff (each attempt
// has its job row) until [storage] max_failure_s, then StorageOutage.
#pragma once

#include <memory>

#include "service/config/daemon_config.hpp"
#include "service/daemon/intake/storage_retry.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/daemon/refit/refit_thread.hpp"
#include "service/refit/refit_runner.hpp"
#include "storage/connection.hpp"

namespace magcal {

class IngestWorker;
class LcmPublisher;

class RefitExecutor {
 public:
  // Opens its own connection to config.storage.db_path (throws storage::StorageError). Every
  // reference must outlive it; `stop` (nullptr: none) ends storage retries early.
  RefitExecutor(const DaemonConfig& config, DaemonCounters& counters, LcmPublisher& publisher,
                IngestWorker& worker, const StopDeadline* stop);
  ~RefitExecutor();
  RefitExecutor(const RefitExecutor&) = delete;
  RefitExecutor& operator=(const RefitExecutor&) = delete;

  // This station's refit jobs an earlier run left 'running' (it stopped during them) are marked
  // interrupted: other daemons sharing the database keep theirs.
  void mark_interrupted_jobs();
  void run(const RefitRequest& req);

 private:
  StorageRetry retry() const;
  RefitOutcome run_one(StorageRetry& retry, const std::string& sat, const RefitRequest& req);
  // Counts, publishes and logs a computed refit (an error or a result).
  void report(const std::string& sat, const RefitRequest& req, const RefitOutcome& out);

  const DaemonConfig& config_;
  DaemonCounters& counters_;
  LcmPublisher& publisher_;
  IngestWorker& worker_;
  const StopDeadline* stop_;
  std::unique_ptr<storage::Connection> db_;
  std::unique_ptr<RefitRunner> runner_;
};

}  // namespace magcal
