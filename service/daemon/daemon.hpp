// magcald's threads and their wiring (design.md "Daemon data flow"):
//
//   caller's thread : LCM receive loop (LcmIngest) -> IngestQueue
//   worker thread   : IngestQueue -> IngestWorker: SampleIntake (validate, store: every
//                     station) then OwnedSpacecraftTracker (the owned spacecraft's UKF over the
//                     stored union, snapshots, refit triggers, leases); daemon_status_t every
//                     [service] status_every_s, counters in the log every [log] status_every_s,
//                     filter states every 30 s
//   refit thread    : scheduled refits (wall clock: its own timer, every spacecraft; data
//                     clock: requests from the worker, each spacecraft on its own data time:
//                     refit/refit_thread.hpp) on its own connection (refit/refit_executor.hpp);
//                     publishes results and posts accepted ones back to the worker for
//                     re-anchoring. Never blocks ingestion.
//   http threads    : the operations server ([http] listen, ops/operations_endpoint.hpp): its
//                     own read-only connection; /metrics from the counters, /-/healthy and
//                     /-/ready from ops/health_probes.hpp. Bound by open() before the database is
//                     opened (a port it cannot bind is an error at start that leaves no file
//                     behind), served once the database is open (or, on PostgreSQL, found
//                     unreachable), stopped by run().
//
// run() ends when `stop` is set (SIGINT/SIGTERM) or, for a file:// URL, at the end of the log:
// stop receiving, drain the queue, commit, finish due refits (replay) or the running one
// (signal), write filter states, publish a last status. Exit codes as in cli_commands.hpp, and
// the two below. After a signal, storage that fails is given up [storage] stop_max_failure_s
// after it (StopDeadline): exit 3 with what was not committed counted, before systemd's
// TimeoutStopSec would kill it (a PostgreSQL outage without a spill file to take the samples).
//
// Never half-alive: storage that stays broken for [storage] max_failure_s (each failed
// operation kept and retried, service/daemon/intake/storage_retry.hpp), or a worker or refit thread
// that dies for any reason, stops receiving and ends run() with a non-zero exit code and the reason
// in the log; every received sample that was not committed is counted as storage_error and logged
// (re-running a replay fills them: stored samples come back as counted duplicates).
//
// A PostgreSQL server unreachable at start (down, restarting, refusing, timing out, a name that
// does not resolve; not a permanent refusal such as authentication, a missing database or role,
// or a foreign schema: those stay a start error, exit 2) does not stop the start: magcald
// receives and holds or spills the samples as in an outage that began later, /-/ready answers
// 503 and both probes say since when the database is unreachable, and the worker restores from
// it (spill, time bases, leases) once it answers (IngestWorker::restore()); the refit thread
// waits for that. Past [storage] pg_max_failure_s: exit 3, as in any outage.
//
// Under systemd (Type=notify, WatchdogSec; service/daemon/ops/systemd_notifier.hpp): READY=1 once
// open() succeeded and the LCM subscription is live (it receives: also while the database is
// unreachable, which /-/ready and STATUS= show), WATCHDOG=1 from the worker loop, STATUS= with
// every status message, STOPPING=1 when run() stops receiving and the drain starts.
#pragma once

#include <atomic>
#include <memory>
#include <string>

#include "service/config/daemon_config.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/io/exit_codes.hpp"

namespace magcal {

class Daemon {
 public:
  explicit Daemon(DaemonConfig config);
  ~Daemon();
  Daemon(const Daemon&) = delete;
  Daemon& operator=(const Daemon&) = delete;

  // Opens the database (a PostgreSQL server unreachable now is no error: see above), IGRF and
  // LCM; empty on success, else one line (the caller exits 2).
  std::string open();
  // Runs until `stop` or the end of a replayed log; returns the process exit code.
  int run(const std::atomic<bool>& stop);

  const DaemonCounters& counters() const;
  // The operations server's bound port after open() (useful with [http] listen port 0); 0 when
  // the server is off.
  int http_port() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace magcal
