#include "service/daemon/refit/refit_executor.hpp"

#include <string_view>

#include <spdlog/spdlog.h>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ingest_worker.hpp"
#include "service/daemon/ops/lcm_publisher.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/refit_job_log.hpp"

namespace magcal {

RefitExecutor::RefitExecutor(const DaemonConfig& config, DaemonCounters& counters,
                             LcmPublisher& publisher, IngestWorker& worker,
                             const StopDeadline* stop)
    : config_(config),
      counters_(counters),
      publisher_(publisher),
      worker_(worker),
      stop_(stop),
      db_(storage::open_database(config.storage.db_path, config.database_options())),
      runner_(std::make_unique<RefitRunner>(config, *db_)) {}

RefitExecutor::~RefitExecutor() = default;

StorageRetry RefitExecutor::retry() const {
  return StorageRetry("refit", config_.storage_max_failure_s(), counters_,
                      config_.storage_max_failure_key(), stop_);
}

void RefitExecutor::mark_interrupted_jobs() {
  StorageRetry retry = this->retry();
  const int n = retry.run_blocking([this] {
    return db_->make_refit_job_log()->mark_station_running_interrupted(config_.station.id,
                                                                       now_utime());
  });
  if (n > 0) {
    spdlog::warn("{} refit job(s) were running when the daemon last stopped: interrupted", n);
  }
}

RefitOutcome RefitExecutor::run_one(StorageRetry& retry, const std::string& sat,
                                    const RefitRequest& req) {
  return retry.run_blocking([&] {
    RefitOutcome out = runner_->run(sat, req.t_ref_utime, req.trigger, req.scheduled_utime);
    if (out.kind == RefitOutcome::Kind::kError && out.storage_error &&
        out.storage_error->transient()) {
      throw *out.storage_error;
    }
    return out;
  });
}

void RefitExecutor::run(const RefitRequest& req) {
  StorageRetry retry = this->retry();
  std::vector<std::string> sats = req.sat_id.empty()
                                      ? retry.run_blocking([&] { return runner_->spacecraft(); })
                                      : std::vector<std::string>{req.sat_id};
  if (req.sat_id.empty()) {
    std::erase_if(sats, [this](const std::string& sat) { return !worker_.owns(sat); });
  }
  for (const auto& sat : sats) {
    const auto out = run_one(retry, sat, req);
    if (out.kind == RefitOutcome::Kind::kClaimedElsewhere) {
      // Another daemon runs it (and stores, publishes its result); this one's filter is not
      // re-anchored on it.
      counters_.spacecraft.spacecraft(sat).refits_claimed_elsewhere.fetch_add(
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
    report(sat, req, out);
    if (out.accepted()) {
      counters_.refits_accepted.fetch_add(1);
      worker_.post_reanchor(sat, out.result, out.calibration_id);
    }
  }
}

void RefitExecutor::report(const std::string& sat, const RefitRequest& req,
                           const RefitOutcome& out) {
  SpacecraftCounters& sc = counters_.spacecraft.spacecraft(sat);
  counters_.refits_run.fetch_add(1);
  if (out.kind == RefitOutcome::Kind::kError) {
    counters_.refits_failed.fetch_add(1);
    sc.count_refit(SpacecraftCounters::RefitVerdict::kError, 0);
    spdlog::error("refit {}: {}", sat, out.message);
    return;
  }
  const auto& r = out.result;
  // A failed or unobservable fit has no estimate, and so no window to show.
  const bool no_estimate =
      r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable;
  if (no_estimate) counters_.refits_failed.fetch_add(1);
  counters_.set_last_refit(sat, r.utime);
  // The verdict as stored in the history (magcal serve counts the same rows).
  sc.count_refit(r.accepted ? SpacecraftCounters::RefitVerdict::kAccepted
                            : SpacecraftCounters::RefitVerdict::kRejected,
                 r.utime);
  publisher_.publish(message_from_result(sat, r));
  const std::string trigger = req.trigger == storage::RefitTrigger::kScheduled
                                  ? ""
                                  : fmt::format(" ({})", to_string(req.trigger));
  if (no_estimate) {
    spdlog::warn("refit {}{} due {} ({} samples): {}: {}", sat, trigger,
                 format_iso8601_utc(req.scheduled_utime), r.n_samples, to_string(r.status),
                 r.message);
    return;
  }
  const Eigen::Vector3d sb = r.bias_sigma_nT();
  spdlog::info(
      "refit {}{} window {} .. {} ({} samples): {}, bias [{:.1f} {:.1f} {:.1f}] +- "
      "[{:.1f} {:.1f} {:.1f}] nT, residual {:.2f} nT{}{}",
      sat, trigger, format_iso8601_utc(r.window_start_utime),
      format_iso8601_utc(r.window_end_utime), r.n_samples,
      r.accepted ? to_string(r.status) : "rejected", r.parameters.bias_nT.x(),
      r.parameters.bias_nT.y(), r.parameters.bias_nT.z(), sb.x(), sb.y(), sb.z(), r.residual_rms_nT,
      r.rejection_reasons.empty() ? "" : ": ",
      fmt::format("{}", fmt::join(r.rejection_reasons, "; ")));
}

}  // namespace magcal
