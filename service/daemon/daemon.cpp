#include "service/daemon/daemon.hpp"

#include <sys/resource.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include <spdlog/spdlog.h>
#include <lcm/lcm-cpp.hpp>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ingest_queue.hpp"
#include "service/daemon/ingest_worker.hpp"
#include "service/daemon/lcm_ingest.hpp"
#include "service/daemon/lcm_publisher.hpp"
#include "service/daemon/refit_runner.hpp"
#include "service/daemon/refit_scheduler.hpp"
#include "service/daemon/storage_retry.hpp"
#include "service/daemon/systemd_notifier.hpp"
#include "service/http/metrics.hpp"
#include "service/http/operations_server.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/refit_job_log.hpp"

namespace magcal {
namespace {

constexpr double kFilterStateEvery_s = 30.0;
// nice of the operations server's threads (ingest runs at the process's own, usually 0).
constexpr int kServerNice = 10;

int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

struct RefitRequest {
  std::string sat_id;                  // data clock: that spacecraft; "" (wall clock): every one
  std::optional<int64_t> t_ref_utime;  // nullopt: each spacecraft's newest sample (wall clock)
  int64_t scheduled_utime = 0;
  const char* trigger = "scheduled";  // or "first" / "early" (IngestWorker::Hooks::on_refit_due)
};

}  // namespace

struct Daemon::Impl {
  DaemonConfig config;
  DaemonCounters counters;
  std::chrono::steady_clock::time_point start_time = std::chrono::steady_clock::now();
  const int64_t start_utime = wall_utime();  // what the probes quote for "unreachable since"
  bool replay = false;
  bool postgres = false;  // config.postgres(), once

  std::unique_ptr<lcm::LCM> lcm;
  std::unique_ptr<LcmPublisher> publisher;
  std::unique_ptr<IngestQueue> queue;
  std::unique_ptr<IngestWorker> worker;
  std::unique_ptr<storage::Connection> refit_db;
  std::unique_ptr<RefitRunner> refits;
  // Type=notify + WatchdogSec (deploy/magcald.service); a no-op outside systemd.
  SystemdNotifier systemd;
  // Set when a signal stops run(): every storage retry gives up [storage] stop_max_failure_s
  // later (before systemd's TimeoutStopSec).
  StopDeadline stop_deadline;

  // Refit requests (worker -> refit thread) and the retention floor they imply.
  std::mutex refit_mutex;
  std::condition_variable refit_cv;
  std::deque<RefitRequest> refit_queue;
  std::multiset<int64_t> floors;  // window starts of due, unfinished refits
  std::condition_variable refit_idle_cv;
  bool refit_busy = false;
  bool refit_stop = false;
  bool refit_drain = false;  // finish queued requests before stopping (replay)

  // A fatal failure (storage broken for max_failure_s, a thread died): the first one wins.
  std::atomic<bool> fatal{false};
  std::mutex fatal_mutex;
  int fatal_exit = 0;
  std::string fatal_reason;

  // The operations server ([http] listen; none when ""): /metrics from `metrics`, health from
  // the flags below. Declared after everything its hooks read, so it stops first.
  std::unique_ptr<http::DaemonMetrics> metrics;
  std::atomic<bool> lcm_live{false};  // subscribed and receiving (ready)
  std::unique_ptr<http::OperationsServer> server;

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
    {
      std::lock_guard lock(refit_mutex);
      refit_stop = true;
      refit_drain = false;
    }
    refit_cv.notify_all();
    refit_idle_cv.notify_all();
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

  // Worker thread, or the main thread after the join.
  daemon_status_t status() {
    // Samples the worker holds uncommitted; after a fatal stop they are counted as
    // storage_error instead.
    counters.storage_pending.store(fatal.load() ? 0 : worker->pending_samples(),
                                   std::memory_order_relaxed);
    const QueueGauge g{queue->depth_samples(), queue->capacity_samples(),
                       queue->overflow_samples()};
    const auto uptime = std::chrono::duration_cast<std::chrono::seconds>(
                            std::chrono::steady_clock::now() - start_time)
                            .count();
    return make_status_message(counters, g, wall_utime(), uptime);
  }

  void update_floor_locked() {
    worker->set_retention_floor(floors.empty() ? std::numeric_limits<int64_t>::max()
                                               : *floors.begin());
  }

  // Worker thread: a refit of sat's window ending at t_ref is due (its data clock passed a
  // scheduled time, or its first refit: IngestWorker::Hooks), and its samples are committed.
  void on_refit_due(const std::string& sat, int64_t t_ref, const char* trigger) {
    std::unique_lock lock(refit_mutex);
    floors.insert(t_ref - config.window_utime() + 1);
    update_floor_locked();
    refit_queue.push_back({sat, t_ref, t_ref, trigger});
    refit_cv.notify_one();
    if (replay) {
      // A replay has no live source to fall behind: wait for the refit so its re-anchoring
      // lands at the same point of the data every time (deterministic backfill). Live
      // ingestion never waits for refits.
      refit_idle_cv.wait(lock,
                         [this] { return (refit_queue.empty() && !refit_busy) || refit_stop; });
    }
  }

  void on_snapshot(const std::string& sat, const CalibrationResult& snap) {
    publisher->publish(message_from_result(sat, snap));
    const Eigen::Vector3d sigma = snap.bias_sigma_nT();
    const Eigen::Vector3d& bias = snap.parameters.bias_nT;
    counters.spacecraft.spacecraft(sat).set_ukf_snapshot(
        {true, {bias.x(), bias.y(), bias.z()}, {sigma.x(), sigma.y(), sigma.z()}, snap.accepted});
  }

  void count_refit(const std::string& sat, SpacecraftCounters::RefitVerdict verdict,
                   int64_t utime) {
    counters.spacecraft.spacecraft(sat).count_refit(verdict, utime);
  }

  // /-/healthy: ingest, storage and the scheduler work. A dead thread or storage broken past
  // its limit ends the process (fatal). On SQLite "working" also means storage is not failing
  // right now (a failing operation is being retried): a local disk that fails wants this
  // host's attention, and a restart reopens the file. On PostgreSQL an outage is the network's
  // or the server's, ridden out for pg_max_failure_s (samples held, then spilled): a liveness
  // probe must not restart a daemon for it (that would not help, and would drop what it holds
  // in memory), so it stays healthy and /-/ready answers 503 instead; both bodies say why.
  bool healthy() const { return !fatal.load() && (postgres || counters.storage_healthy()); }
  // /-/ready: the database is open (the server only starts after it is) and LCM is live; on
  // PostgreSQL, and storage is not failing (also not while unreachable since the start).
  bool ready() const {
    return lcm_live.load() && !fatal.load() && (!postgres || counters.storage_healthy());
  }
  double storage_failing_s() const {
    const int64_t since = counters.storage_failing_since_utime.load();
    return since == 0 ? 0.0
                      : std::max<double>(0.0, static_cast<double>(wall_utime() - since) * 1e-6);
  }
  // The probes' extra line during a storage failure ("" otherwise).
  std::string storage_outage_note() const {
    if (counters.storage_healthy()) return "";
    const int64_t since = counters.storage_failing_since_utime.load();
    return fmt::format(
        "storage failing for {:.0f} s of [storage] {} = {:.0f} s (database {}{}): {} samples held "
        "in memory{}\n",
        storage_failing_s(), config.storage_max_failure_key(), config.storage_max_failure_s(),
        storage::database_name(config.storage.db_path),
        worker->restored() || since == 0
            ? ""
            : ", unreachable since magcald started at " + format_iso8601_utc(start_utime),
        counters.storage_pending.load(), postgres ? spill_note() : "");
  }
  // ", N in the spill file" (and an earlier run's there, not committed yet).
  std::string spill_note() const {
    const int64_t earlier = counters.spill_held_earlier.load();
    return fmt::format(
        ", {} in the spill file{}", counters.spill_held.load(),
        earlier > 0 ? fmt::format(" (and {} an earlier run left there)", earlier) : "");
  }

  http::DaemonMetrics::Totals metric_totals() const {
    http::DaemonMetrics::Totals t;
    t.rejected_by_reason.reserve(kRejectReasonCount);
    for (int i = 0; i < kRejectReasonCount; ++i) {
      const auto r = static_cast<RejectReason>(i);
      t.rejected_by_reason.emplace_back(to_string(r), counters.rejected_count(r));
    }
    t.queue_depth = queue->depth_samples();
    t.queue_overflow = queue->overflow_samples();
    t.storage_healthy = counters.storage_healthy();
    t.storage_failing_s = storage_failing_s();
    t.storage_pending = counters.storage_pending.load(std::memory_order_relaxed);
    t.spilled = counters.spilled.load(std::memory_order_relaxed);
    // Everything the file holds: what an operator watches for (the books count this run's).
    t.spill_held = counters.spill_held.load(std::memory_order_relaxed) +
                   counters.spill_held_earlier.load(std::memory_order_relaxed);
    t.spill_bytes = counters.spill_bytes.load(std::memory_order_relaxed);
    t.spill_recovered = counters.spill_recovered.load(std::memory_order_relaxed);
    t.spill_dropped = counters.spill_dropped.load(std::memory_order_relaxed);
    t.leases_lost = counters.leases_lost.load(std::memory_order_relaxed);
    t.fleet_settings_mismatch = counters.fleet_settings_mismatch.load(std::memory_order_relaxed);
    counters.spacecraft.for_each([&t](const SpacecraftCounters& c) {
      http::DaemonMetrics::SpacecraftTotals s;
      s.sat_label = c.sat_label;
      s.received = c.received.load(std::memory_order_relaxed);
      s.stored = c.stored.load(std::memory_order_relaxed);
      s.missing = c.missing.load(std::memory_order_relaxed);
      s.refits_accepted = c.refits_accepted.load(std::memory_order_relaxed);
      s.refits_rejected = c.refits_rejected.load(std::memory_order_relaxed);
      s.refits_error = c.refits_error.load(std::memory_order_relaxed);
      s.refits_claimed_elsewhere = c.refits_claimed_elsewhere.load(std::memory_order_relaxed);
      s.owned = c.owned.load(std::memory_order_relaxed);
      s.last_refit_success_utime = c.last_refit_success_utime.load(std::memory_order_relaxed);
      const SpacecraftCounters::UkfSnapshot ukf = c.ukf_snapshot();
      s.has_ukf_snapshot = ukf.present;
      s.ukf_bias_nT = ukf.bias_nT;
      s.ukf_bias_sigma_nT = ukf.bias_sigma_nT;
      s.ukf_accepted = ukf.accepted;
      t.spacecraft.push_back(std::move(s));
    });
    const auto buckets = counters.commit_seconds.bucket_counts();
    t.commit_bucket_counts.assign(buckets.begin(), buckets.end());
    t.commit_sum_s = counters.commit_seconds.sum_s();
    return t;
  }

  // Before the database is opened: a listen address that cannot be bound must not leave a new,
  // empty database behind. Empty, or why it could not bind.
  std::string bind_server() {
    if (config.http.listen.empty()) return "";
    metrics->set_totals_source([this] { return metric_totals(); });
    http::ServerHooks hooks;
    hooks.metrics_text = [this] { return metrics->text(); };
    hooks.healthy = [this] { return healthy(); };
    hooks.ready = [this] { return ready(); };
    hooks.probe_detail = [this] { return storage_outage_note(); };
    hooks.status_window_utime = config.window_utime();
    std::string error;
    server = http::OperationsServer::bind(config.http.listen, std::move(hooks), &error);
    if (!server) return "[http] listen " + config.http.listen + ": " + error;
    return "";
  }

  // After the database and LCM are open: empty, or why the server could not start.
  std::string start_server() {
    if (!server) return "";
    std::string error;
    bool served = false;
    // Started from a thread at a lower CPU priority, which every server thread inherits (Linux
    // nice is per thread, inherited at creation): on a saturated machine a client hammering the
    // API gets slower answers instead of slowing ingest (BM_DaemonReplayHttp measures both).
    std::thread starter([&] {
      ::setpriority(PRIO_PROCESS, static_cast<id_t>(::gettid()), kServerNice);
      const storage::OpenOptions db = config.database_options();
      served = server->serve(config.storage.db_path, &error, db.connect_later, db.reply_timeout_ms);
    });
    starter.join();
    if (!served) {
      server.reset();
      return "[http] listen " + config.http.listen + ": " + error;
    }
    return "";  // the server logs its URL
  }

  // The refit thread's storage retries.
  StorageRetry refit_retry() {
    return StorageRetry("refit", config.storage_max_failure_s(), counters,
                        config.storage_max_failure_key(), &stop_deadline);
  }

  // Refit thread: one refit, its storage errors retried with backoff (each attempt has its job
  // row); StorageOutage once storage stays broken.
  RefitOutcome run_refit(StorageRetry& retry, const std::string& sat, const RefitRequest& req) {
    return retry.run_blocking([&] {
      // RefitRequest still carries the trigger's text until it takes a RefitTrigger.
      const storage::RefitTrigger trigger = storage::refit_trigger_from_string(req.trigger)
                                                .value_or(storage::RefitTrigger::kScheduled);
      RefitOutcome out = refits->run(sat, req.t_ref_utime, trigger, req.scheduled_utime);
      if (out.kind == RefitOutcome::Kind::kError && out.storage_error &&
          out.storage_error->transient()) {
        throw *out.storage_error;
      }
      return out;
    });
  }

  void refit_all(const RefitRequest& req) {
    StorageRetry retry = refit_retry();
    // The wall-clock schedule refits the spacecraft this daemon owns (design.md "Fleet"); the
    // others' owners refit theirs.
    std::vector<std::string> sats = req.sat_id.empty()
                                        ? retry.run_blocking([&] { return refits->spacecraft(); })
                                        : std::vector<std::string>{req.sat_id};
    if (req.sat_id.empty()) {
      std::erase_if(sats, [this](const std::string& sat) { return !worker->owns(sat); });
    }
    for (const auto& sat : sats) {
      const auto out = run_refit(retry, sat, req);
      if (out.kind == RefitOutcome::Kind::kClaimedElsewhere) {
        // Another daemon runs it (and stores, publishes its result); this one's filter is not
        // re-anchored on it.
        counters.spacecraft.spacecraft(sat).refits_claimed_elsewhere.fetch_add(
            1, std::memory_order_relaxed);
        spdlog::info("refit {} at {}: not run here ({})", sat,
                     format_iso8601_utc(req.scheduled_utime), out.message);
        continue;
      }
      if (out.kind == RefitOutcome::Kind::kSkipped) {
        spdlog::info("refit {} at {}: skipped ({})", sat, format_iso8601_utc(req.scheduled_utime),
                     out.message);
        continue;
      }
      counters.refits_run.fetch_add(1);
      if (out.kind == RefitOutcome::Kind::kError) {
        counters.refits_failed.fetch_add(1);
        count_refit(sat, SpacecraftCounters::RefitVerdict::kError, 0);
        spdlog::error("refit {}: {}", sat, out.message);
        continue;
      }
      const auto& r = out.result;
      if (r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable) {
        counters.refits_failed.fetch_add(1);
      }
      counters.set_last_refit(sat, r.utime);
      // The verdict as stored in the history (magcal serve counts the same rows).
      count_refit(sat,
                  r.accepted ? SpacecraftCounters::RefitVerdict::kAccepted
                             : SpacecraftCounters::RefitVerdict::kRejected,
                  r.utime);
      publisher->publish(message_from_result(sat, r));
      const Eigen::Vector3d sb = r.bias_sigma_nT();
      const std::string trigger =
          std::string_view(req.trigger) == "scheduled" ? "" : fmt::format(" ({})", req.trigger);
      if (r.status == CalibrationStatus::kFailed ||
          r.status == CalibrationStatus::kUnobservable) {  // no estimate, no window to show
        spdlog::warn("refit {}{} due {} ({} samples): {}: {}", sat, trigger,
                     format_iso8601_utc(req.scheduled_utime), r.n_samples, to_string(r.status),
                     r.message);
      } else {
        spdlog::info(
            "refit {}{} window {} .. {} ({} samples): {}, bias [{:.1f} {:.1f} {:.1f}] +- "
            "[{:.1f} {:.1f} {:.1f}] nT, residual {:.2f} nT{}{}",
            sat, trigger, format_iso8601_utc(r.window_start_utime),
            format_iso8601_utc(r.window_end_utime), r.n_samples,
            r.accepted ? to_string(r.status) : "rejected", r.parameters.bias_nT.x(),
            r.parameters.bias_nT.y(), r.parameters.bias_nT.z(), sb.x(), sb.y(), sb.z(),
            r.residual_rms_nT, r.rejection_reasons.empty() ? "" : ": ",
            fmt::format("{}", fmt::join(r.rejection_reasons, "; ")));
      }
      if (out.accepted()) {
        counters.refits_accepted.fetch_add(1);
        worker->post_reanchor(sat, r, out.calibration_id);
      }
    }
  }

  void refit_thread() {
    guarded("refit", [this] { refit_loop(); });
  }

  void mark_interrupted_jobs() {
    StorageRetry retry = refit_retry();
    // Only this station's (and unclaimed) jobs: other daemons sharing the database run theirs.
    const int n = retry.run_blocking([this] {
      return refit_db->make_refit_job_log()->mark_station_running_interrupted(config.station.id,
                                                                              wall_utime());
    });
    if (n > 0) {
      spdlog::warn("{} refit job(s) were running when the daemon last stopped: interrupted", n);
    }
  }

  void refit_loop() {
    const bool wall = !config.data_clock();
    const RefitSchedule schedule{parse_daily_time_utc(config.refit.daily_at_utc).value_or(120),
                                 config.refit.every_hours};
    int64_t next_wall = next_scheduled_utime(schedule, wall_utime());
    if (wall) spdlog::info("next scheduled refit {}", format_iso8601_utc(next_wall));
    std::unique_lock lock(refit_mutex);
    // Nothing before the worker reached the database (unreachable at start: a stop meanwhile
    // must not wait for it here), and then this station's jobs an earlier run left running are
    // ended first, so that none of this run's is taken for one.
    while (!worker->restored() && !refit_stop) {
      refit_cv.wait_for(lock, std::chrono::milliseconds(200));
    }
    if (!worker->restored()) return;
    lock.unlock();
    mark_interrupted_jobs();
    lock.lock();
    while (true) {
      if (!refit_queue.empty() && !(refit_stop && !refit_drain)) {
        const RefitRequest req = refit_queue.front();
        refit_queue.pop_front();
        refit_busy = true;
        lock.unlock();
        refit_all(req);
        lock.lock();
        refit_busy = false;
        if (req.t_ref_utime) {
          const auto it = floors.find(*req.t_ref_utime - config.window_utime() + 1);
          if (it != floors.end()) floors.erase(it);
          update_floor_locked();
        }
        refit_idle_cv.notify_all();
        continue;
      }
      if (refit_stop) break;
      if (wall && wall_utime() >= next_wall) {
        refit_queue.push_back({"", std::nullopt, next_wall});
        next_wall = next_scheduled_utime(schedule, wall_utime());
        continue;
      }
      const auto wait_ms =
          wall ? std::clamp<int64_t>((next_wall - wall_utime()) / 1000, 1, 1000) : int64_t{1000};
      refit_cv.wait_for(lock, std::chrono::milliseconds(wait_ms));
    }
    if (!refit_queue.empty()) {
      spdlog::warn("{} scheduled refit(s) not run: shutting down", refit_queue.size());
    }
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

Daemon::Daemon(DaemonConfig config) : impl_(std::make_unique<Impl>()) {
  impl_->config = std::move(config);
}

Daemon::~Daemon() = default;

const DaemonCounters& Daemon::counters() const {
  return impl_->counters;
}

int Daemon::http_port() const {
  return impl_->server ? impl_->server->port() : 0;
}

std::string Daemon::open() {
  auto& d = *impl_;
  const auto& c = d.config;
  d.replay = is_file_url(c.lcm.url);
  d.postgres = c.postgres();
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
  if (!c.http.listen.empty()) {
    d.metrics = std::make_unique<http::DaemonMetrics>(
        MAGCAL_VERSION, c.station.id,
        std::vector<double>(CommitLatencyHistogram::kUpperBounds_s.begin(),
                            CommitLatencyHistogram::kUpperBounds_s.end()));
  }
  // The listen socket before the database, for the same reason as LCM.
  if (std::string e = d.bind_server(); !e.empty()) return e;
  try {
    d.worker = std::make_unique<IngestWorker>(
        c, d.counters, std::move(field),
        IngestWorker::Hooks{
            [&d](const std::string& sat, const CalibrationResult& r) { d.on_snapshot(sat, r); },
            [&d](const std::string& sat, int64_t t, const char* trigger) {
              d.on_refit_due(sat, t, trigger);
            }},
        &d.stop_deadline);
    d.refit_db = storage::open_database(c.storage.db_path, c.database_options());
    d.refits = std::make_unique<RefitRunner>(d.config, *d.refit_db);
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
  return d.start_server();
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
  d.lcm_live.store(true);
  d.systemd.ready();
  const auto end = ingest.run(stop, d.replay, &d.fatal);
  // A stop must end before systemd's TimeoutStopSec: storage that fails gives up at this bound.
  if (end == LcmIngest::End::kStopped) d.stop_deadline.start(c.storage.stop_max_failure_s);
  d.lcm_live.store(false);
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
  {
    std::lock_guard lock(d.refit_mutex);
    d.refit_stop = true;
    // A replay finishes its refits (unless storage failed).
    d.refit_drain = end == LcmIngest::End::kEndOfLog && !d.fatal.load();
  }
  d.refit_cv.notify_all();
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
  // On PostgreSQL the books also count what waits in the spill file for the next start
  // (received = stored + rejected + overflow + spill_held).
  std::string spill_books;
  if (d.postgres) {
    spill_books = fmt::format(" spill_held={}", d.counters.spill_held.load());
    if (const int64_t earlier = d.counters.spill_held_earlier.load(); earlier > 0) {
      spill_books += fmt::format(" (and {} of an earlier run)", earlier);
    }
  }
  spdlog::info("final {}{}", format_status_line(st), spill_books);
  if (d.server) d.server->stop();
  if (d.fatal.load()) {
    std::lock_guard lock(d.fatal_mutex);
    spdlog::critical("magcald stopped: {} (exit code {})", d.fatal_reason, d.fatal_exit);
    return d.fatal_exit;
  }
  return end == LcmIngest::End::kError ? kExitData : kExitOk;
}

}  // namespace magcal
