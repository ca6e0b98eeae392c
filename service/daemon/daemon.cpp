#include "service/daemon/daemon.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>
#include <lcm/lcm-cpp.hpp>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ingest_worker.hpp"
#include "service/daemon/intake/ingest_queue.hpp"
#include "service/daemon/intake/lcm_ingest.hpp"
#include "service/daemon/intake/storage_retry.hpp"
#include "service/daemon/ops/daemon_status.hpp"
#include "service/daemon/ops/health_probes.hpp"
#include "service/daemon/ops/lcm_publisher.hpp"
#include "service/daemon/ops/operations_endpoint.hpp"
#include "service/daemon/ops/systemd_notifier.hpp"
#include "service/daemon/refit/refit_executor.hpp"
#include "service/daemon/refit/refit_thread.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/refit_job_log.hpp"

namespace magcal {
namespace {

constexpr double kFilterStateEvery_s = 30.0;

RefitThread::Settings refit_settings(const DaemonConfig& config, bool replay) {
  RefitThread::Settings s;
  s.window_utime = config.window_utime();
  if (!config.data_clock()) {
    s.wall_schedule = RefitSchedule{parse_daily_time_utc(config.refit.daily_at_utc).value_or(120),
                                    config.refit.every_hours};
  }
  s.replay = replay;
  return s;
}

}  // namespace

struct Daemon::Impl {
  explicit Impl(DaemonConfig c) : config(std::move(c)) {}

  const DaemonConfig config;
  const bool replay = is_file_url(config.lcm.url);
  DaemonCounters counters;
  std::chrono::steady_clock::time_point start_time = std::chrono::steady_clock::now();

  std::unique_ptr<lcm::LCM> lcm;
  std::unique_ptr<LcmPublisher> publisher;
  std::unique_ptr<IngestQueue> queue;
  std::unique_ptr<IngestWorker> worker;
  std::unique_ptr<RefitExecutor> refit_executor;  // the refit thread's, on its own connection
  // Type=notify + WatchdogSec (deploy/magcald.service); a no-op outside systemd.
  SystemdNotifier systemd;
  // Set when a signal stops run(): every storage retry gives up [storage] stop_max_failure_s
  // later (before systemd's TimeoutStopSec).
  StopDeadline stop_deadline;

  // Refit requests (worker -> refit thread) and the retention floor they imply.
  RefitThread refit{
      refit_settings(config, replay),
      {[this] { return worker->restored(); }, [this] { refit_executor->mark_interrupted_jobs(); },
       [this](const RefitRequest& req) { refit_executor->run(req); },
       [this](int64_t floor_utime) { worker->set_retention_floor(floor_utime); }}};

  // A fatal failure (storage broken for max_failure_s, a thread died): the first one wins.
  std::atomic<bool> fatal{false};
  std::mutex fatal_mutex;
  int fatal_exit = 0;
  std::string fatal_reason;

  // The probes and the operations server ([http] listen), declared after everything they read,
  // so that the server stops first.
  HealthProbes probes{config, counters, fatal, [this] { return worker->restored(); }, now_utime()};
  OperationsEndpoint server{config, {counters, probes, [this] { return queue_gauge(*queue); }}};

  // From any thread: log why, stop receiving, stop the worker and the refit thread; run() then
  // returns `exit_code`. Never half-alive: nothing keeps receiving what cannot be stored.
  void fail(int exit_code, const std::string& why) {
    {
      std::lock_guard lock(fatal_mutex);
      if (fatal_exit != 0) return;
      fatal_exit = exit_code;
      fatal_reason = why;
    }
    spdlog::critical("{}: stopping magcald (exit code {})", why, exit_code);
    fatal.store(true);
    queue->close();  // the receive side stops; a blocked replay push returns
    refit.stop(/*drain=*/false);
  }

  // Runs a thread's body; whatever escapes it ends the process (non-zero), never the thread
  // alone.
  template <typename Body>
  void guarded(const char* thread, Body&& body) {
    try {
      body();
    } catch (const StorageOutage& e) {
      fail(kExitStorageFailed, fmt::format("storage failed ({} thread): {}", thread, e.what()));
    } catch (const StationConflict& e) {
      fail(kExitUsage, e.what());
    } catch (const RefusedAtFirstContact& e) {
      fail(kExitData, e.what());
    } catch (const std::exception& e) {
      fail(kExitThreadDied, fmt::format("{} thread died: {}", thread, e.what()));
    } catch (...) {
      fail(kExitThreadDied, fmt::format("{} thread died: unknown exception", thread));
    }
  }

  // Worker thread, or the main thread after the join. Samples the worker holds uncommitted;
  // after a fatal stop they are counted as storage_error instead.
  daemon_status_t status() {
    return current_status(counters, queue_gauge(*queue),
                          fatal.load() ? 0 : worker->pending_samples(), start_time);
  }

  // Worker thread: a refit of sat's window ending at t_ref is due (its data clock passed a
  // scheduled time, or its first refit: IngestWorker::Hooks), and its samples are committed.
  void on_refit_due(const std::string& sat, int64_t t_ref, storage::RefitTrigger trigger) {
    refit.request(sat, t_ref, trigger);
  }

  void on_snapshot(const std::string& sat, const CalibrationResult& snap) {
    publisher->publish(message_from_result(sat, snap));
    const Eigen::Vector3d sigma = snap.bias_sigma_nT();
    const Eigen::Vector3d& bias = snap.parameters.bias_nT;
    counters.spacecraft.spacecraft(sat).set_ukf_snapshot(
        {true, {bias.x(), bias.y(), bias.z()}, {sigma.x(), sigma.y(), sigma.z()}, snap.accepted});
  }

  void refit_thread() {
    guarded("refit", [this] { refit.run(); });
  }

  void worker_thread() {
    guarded("worker", [this] { worker_loop(); });
  }

  // The worker loop's frames: popped from the queue, items[next..] not processed yet. After a
  // fatal error they go to the pending batch, and so to the spill file (keep_after_fatal()).
  std::vector<IngestItem> popped_items;
  size_t popped_next = 0;

  // After a fatal error, with the worker stopped: the frames it had popped but not processed,
  // those still queued and the first samples held for their time base go to the pending batch,
  // which the spill file (PostgreSQL) then takes; none is counted as lost while it has room.
  void keep_after_fatal() {
    try {
      for (size_t i = popped_next; i < popped_items.size(); ++i) {
        worker->ingest_without_commit(popped_items[i]);
      }
      popped_items.clear();
      popped_next = 0;
      std::vector<IngestItem> queued;
      while (queue->pop_all(queued, 0) && !queued.empty()) {  // (closed: false once empty)
        for (const IngestItem& item : queued) worker->ingest_without_commit(item);
        queued.clear();
      }
      worker->settle_held();
    } catch (const std::exception& e) {
      spdlog::error(
          "after the fatal error, received samples could not be kept for the spill "
          "file: {}",
          e.what());
    }
  }

  void worker_loop() {
    using clock = std::chrono::steady_clock;
    auto last_status = clock::now();
    auto last_log = clock::now();
    auto last_states = clock::now();
    std::vector<IngestItem>& items = popped_items;
    size_t& next = popped_next;  // items[next..] are popped but not processed yet
    while (!fatal.load()) {
      // The loop wakes at least every 100 ms (pop_all, the retry wait); a commit blocks at most
      // [storage] busy_timeout_ms. Sent every WatchdogSec/2: a stuck worker gets restarted.
      systemd.watchdog_ping();
      if (next == items.size() && !worker->backlogged()) {
        items.clear();
        next = 0;
        if (!queue->pop_all(items, 100)) break;
      }
      while (next < items.size() && !worker->backlogged() && !fatal.load()) {
        worker->process(items[next++]);
      }
      if (worker->backlogged()) {
        // Back-pressure: take no more frames (a live queue then overflows, counted; a replay
        // waits) until the pending batch is committed.
        if (worker->commit_failing()) {
          std::this_thread::sleep_until(std::min(worker->next_commit_attempt(),
                                                 clock::now() + std::chrono::milliseconds(100)));
        }
        worker->commit();
      }
      worker->commit_if_due();
      const auto now = clock::now();
      if (std::chrono::duration<double>(now - last_status).count() >=
          config.service.status_every_s) {
        last_status = now;
        const auto st = status();
        publisher->publish(st);
        if (systemd.enabled()) systemd.status(format_status_line(st));  // systemctl status
      }
      if (std::chrono::duration<double>(now - last_log).count() >= config.log.status_every_s) {
        last_log = now;
        spdlog::info("{}", format_status_line(status()));
      }
      if (std::chrono::duration<double>(now - last_states).count() >= kFilterStateEvery_s) {
        last_states = now;
        worker->save_filter_states();
      }
    }
    if (fatal.load()) return;
    // Drained (end of log or stop): store everything, retrying until max_failure_s, or a
    // signal's stop_max_failure_s (on PostgreSQL during an outage: spilled for the next start,
    // when the spill file takes them); the owned filters take every
    // stored sample (their refits still run: this thread is the refit thread's client).
    worker->flush_at_stop();
    worker->track_all_now();
    worker->flush_at_stop();
  }
};

Daemon::Daemon(DaemonConfig config) : impl_(std::make_unique<Impl>(std::move(config))) {}

Daemon::~Daemon() = default;

const DaemonCounters& Daemon::counters() const {
  return impl_->counters;
}

int Daemon::http_port() const {
  return impl_->server.port();
}

std::string Daemon::open() {
  auto& d = *impl_;
  const auto& c = d.config;
  std::string error;
  auto field = ReferenceField::from_file(c.igrf.coefficients_file, &error);
  if (!field) return "[igrf] coefficients_file: " + error;
  // LCM first: a URL that cannot be opened must not leave a new, empty database behind.
  std::string lcm_error;
  d.lcm = open_lcm(c.lcm.url, &lcm_error);
  if (!d.lcm->good()) {
    return "[lcm] url '" + c.lcm.url +
           "': cannot open LCM URL: " + (d.replay ? unreadable_log_reason(c.lcm.url) : lcm_error);
  }
  const std::string pub_url = !c.lcm.publish_url.empty() ? c.lcm.publish_url
                              : d.replay                 ? std::string()
                                                         : c.lcm.url;
  if (!c.lcm.publish_url.empty() || !d.replay) {
    d.publisher =
        std::make_unique<LcmPublisher>(pub_url, c.lcm.calibration_channel, c.lcm.status_channel);
    if (!d.publisher->ok()) {
      return "[lcm] publish_url '" + pub_url + "': cannot open LCM URL: " + d.publisher->error();
    }
  } else {
    d.publisher = std::make_unique<LcmPublisher>();  // replay without publish_url: no output
  }
  d.queue = std::make_unique<IngestQueue>(c.service.queue_capacity_samples, d.replay);
  // The listen socket before the database, for the same reason as LCM.
  if (std::string e = d.server.bind(); !e.empty()) return e;
  try {
    d.worker = std::make_unique<IngestWorker>(
        c, d.counters, std::move(field),
        IngestWorker::Hooks{
            [&d](const std::string& sat, const CalibrationResult& r) { d.on_snapshot(sat, r); },
            [&d](const std::string& sat, int64_t t, storage::RefitTrigger trigger) {
              d.on_refit_due(sat, t, trigger);
            }},
        &d.stop_deadline);
    d.refit_executor =
        std::make_unique<RefitExecutor>(c, d.counters, *d.publisher, *d.worker, &d.stop_deadline);
    // False: a PostgreSQL server unreachable now, an outage from the start (IngestWorker).
    d.worker->restore();
  } catch (const storage::StorageError& e) {
    // Storage errors mostly name the database themselves; name it once.
    const std::string name = storage::database_name(c.storage.db_path);
    const std::string what = e.what();
    return what.find(name) != std::string::npos ? "database: " + what
                                                : "database " + name + ": " + what;
  } catch (const SpillForAnotherDatabase& e) {
    return e.what();
  } catch (const SpillError& e) {
    // The worker creates the spill file at once (a directory that cannot take it must show
    // now, not in the middle of an outage; access() would not tell: root passes it on /sys).
    const char* state_dir = std::getenv("STATE_DIRECTORY");
    return fmt::format(
        "[storage] spill_dir {}: {} (the spill file takes the samples of a PostgreSQL outage; "
        "spill_max_bytes = 0 runs without one)",
        !c.storage.spill_dir.empty() ? "'" + c.storage.spill_dir + "'"
        : state_dir != nullptr       ? std::string("unset ($STATE_DIRECTORY)")
                                     : std::string("unset (the working directory)"),
        e.what());
  }
  return d.server.serve();
}

int Daemon::run(const std::atomic<bool>& stop) {
  auto& d = *impl_;
  const auto& c = d.config;
  spdlog::info("magcald {} up: db {}, lcm {} ({}), refits {} clock at {} UTC{}", MAGCAL_VERSION,
               storage::database_name(c.storage.db_path), lcm_url_for_log(c.lcm.url),
               d.replay ? "replay" : "live", c.refit.clock, c.refit.daily_at_utc,
               c.refit.every_hours > 0 ? fmt::format(" + every {} h", c.refit.every_hours) : "");
  std::thread worker([&d] { d.worker_thread(); });
  std::thread refitter([&d] { d.refit_thread(); });

  LcmIngest ingest(*d.lcm, c.lcm.samples_channel, c.lcm.batch_channel, *d.queue, d.counters);
  // The database is open (open(); or PostgreSQL unreachable, an outage /-/ready reports) and
  // the subscription live (the constructor): it receives, systemd may start what is ordered
  // after magcald, and the watchdog runs from here.
  d.probes.set_lcm_live(true);
  d.systemd.ready();
  const auto end = ingest.run(stop, d.replay, &d.fatal);
  // A stop must end before systemd's TimeoutStopSec: storage that fails gives up at this bound.
  if (end == LcmIngest::End::kStopped) d.stop_deadline.start(c.storage.stop_max_failure_s);
  d.probes.set_lcm_live(false);
  d.worker->input_ended(end == LcmIngest::End::kEndOfLog);
  // The drain (bounded by [storage] max_failure_s, and after a signal by stop_max_failure_s)
  // runs under TimeoutStopSec, not the watchdog.
  d.systemd.stopping();
  spdlog::info("{}; draining {} queued samples",
               d.fatal.load()                     ? "stopped on a fatal error"
               : end == LcmIngest::End::kEndOfLog ? "end of log"
               : end == LcmIngest::End::kStopped  ? "stop requested"
                                                  : "LCM receive failed",
               d.queue->depth_samples());
  d.queue->close();
  worker.join();
  // A replay finishes its refits (unless storage failed).
  d.refit.stop(/*drain=*/end == LcmIngest::End::kEndOfLog && !d.fatal.load());
  refitter.join();
  if (!d.fatal.load()) {
    d.guarded("main", [&d] {
      d.worker->commit_if_due();  // applies re-anchors posted by the last refits
      d.worker->settle_held();    // first samples stored, unconfirmed jumps counted
      d.worker->flush_at_stop();
      d.worker->save_filter_states();
      d.worker->leave_fleet();  // the other daemons take its spacecraft over at once
    });
  }
  if (d.fatal.load()) {
    d.keep_after_fatal();
    // On PostgreSQL the pending batch goes to the spill file: committed at the next start.
    if (const int64_t spilled = d.worker->spill_all_pending(); spilled > 0) {
      spdlog::warn("{} pending samples spilled: committed at the next start", spilled);
    }
    // Everything received and neither stored, spilled nor counted yet was never committed:
    // the pending batch, the frames popped or still queued. Counted, so the books balance.
    const int64_t not_committed = d.counters.received.load() - d.counters.stored.load() -
                                  d.counters.rejected_total() - d.queue->overflow_samples() -
                                  d.counters.spill_held.load();
    if (not_committed > 0) {
      d.counters.reject(RejectReason::kStorageError, not_committed);
      spdlog::error(
          "{} received samples were not committed (counted as storage_error; never stored, so "
          "re-running the replay or recorder dump fills them, stored ones come back as counted "
          "duplicates)",
          not_committed);
    }
  }
  const auto st = d.status();
  d.publisher->publish(st);
  // With a spill file the books also count what waits there for the next start.
  spdlog::info("final {}{}", format_status_line(st),
               spill_books(d.counters, c.storage_capabilities()));
  d.server.stop();
  if (d.fatal.load()) {
    std::lock_guard lock(d.fatal_mutex);
    spdlog::critical("magcald stopped: {} (exit code {})", d.fatal_reason, d.fatal_exit);
    return d.fatal_exit;
  }
  return end == LcmIngest::End::kError ? kExitData : kExitOk;
}

}  // namespace magcal
