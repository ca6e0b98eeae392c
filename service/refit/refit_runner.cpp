#include "service/refit/refit_runner.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <thread>

#include <spdlog/spdlog.h>

#include "pipeline/temperature_model.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"

namespace magcal {
namespace {

// A refit whose window spans at least this fraction of window_hours is a full-window refit
// (a 12 h window sampled every 10 s spans 99.98 %; an early refit at 8 h spans 67 %).
constexpr double kFullWindowFraction = 0.9;

// Why a refit does not run here: `done`, its job, ran it already (here, or unclaimed) or another
// station holds its claim.
void not_run_here(const storage::RefitJob& done, const std::string& station, RefitOutcome& out) {
  out.job_id = done.id;
  const std::string what =
      "the " + done.trigger + " refit ending at " + format_iso8601_utc(done.scheduled_utime);
  const std::string job = " (job " + std::to_string(done.id) + ", " + done.outcome + ")";
  if (done.claimed_by.empty() || done.claimed_by == station) {
    out.kind = RefitOutcome::Kind::kSkipped;
    out.message = what + " already ran" + job;
  } else {
    out.kind = RefitOutcome::Kind::kClaimedElsewhere;
    out.message = what + " is claimed by station " + done.claimed_by + job;
  }
}

}  // namespace

BatchCalibrationOptions batch_options_from_config(const DaemonConfig& config) {
  BatchCalibrationOptions o;
  o.method = BatchCalibrationOptions::Method::kTwoStep;
  o.sigma_nT = config.ukf.filter.sigma_nT;
  o.robust = config.refit.robust;
  o.gates = true;
  o.gate_options = config.gates;
  return o;
}

RefitRunner::RefitRunner(const DaemonConfig& config, storage::Connection& db)
    : config_(config),
      options_(batch_options_from_config(config)),
      db_(db),
      samples_(db.make_sample_window_store()),
      history_(db.make_calibration_history()),
      jobs_(db.make_refit_job_log()),
      leases_(db.make_lease_store()) {
  if (const char* ms = std::getenv("MAGCAL_FAULT_REFIT_PAUSE_MS"); ms != nullptr) {
    pause_before_storing_ = std::chrono::milliseconds(std::max(0L, std::strtol(ms, nullptr, 10)));
  }
}

std::vector<std::string> RefitRunner::spacecraft() {
  return samples_->spacecraft();
}

bool RefitRunner::accept_corroborated_change(const std::string& sat_id,
                                             const CalibrationResult& reference,
                                             CalibrationResult& result) {
  // A real change of the sensor (a drift, a new bias after a thermal or magnetic event) fails
  // the change gate against the old reference every time: accepting nothing from then on would
  // lock the spacecraft out for good. When the only reasons are the change gate's and the
  // previous full-window refit, newer than the reference, failed on the same gate only and
  // agrees with this one (the same chi-square test between the two), the change is
  // corroborated by two independent windows: accept it, and say so.
  if (result.accepted || result.rejection_reasons.empty()) return false;
  const auto is_change = [](const std::string& r) {
    return r.rfind("bias_change", 0) == 0 || r.rfind("D_change", 0) == 0;
  };
  for (const auto& r : result.rejection_reasons)
    if (!is_change(r)) return false;
  const auto last = history_->latest_refit(sat_id);
  if (!last || last->utime <= reference.utime || last->utime >= result.utime) return false;
  if (last->window_end_utime - last->window_start_utime <
          static_cast<int64_t>(kFullWindowFraction * config_.window_utime()) ||
      last->n_samples < config_.refit.min_samples || last->rejection_reasons.empty()) {
    return false;
  }
  for (const auto& r : last->rejection_reasons)
    if (!is_change(r)) return false;
  const CalibrationResult corroborating =
      at_utime(at_temperature(result_from_record(*last), mean_temperature_C(window_)),
               result.window_end_utime);
  GateOptions only_change = options_.gate_options;
  only_change.residual_enabled = only_change.observability_enabled = false;
  only_change.coverage_enabled = only_change.bounds_enabled = false;
  GateInputs in;
  in.previous_accepted = &corroborating;
  if (!evaluate_gates(result, in, only_change).accepted) return false;
  result.accepted = true;
  result.rejection_reasons.clear();
  if (result.status == CalibrationStatus::kRejected)
    result.status = result.converged ? CalibrationStatus::kOk : CalibrationStatus::kNotConverged;
  result.message = "change since the refit of " + format_iso8601_utc(reference.utime) +
                   " corroborated by the refit of " + format_iso8601_utc(corroborating.utime);
  return true;
}

std::optional<storage::RefitJob> RefitRunner::finished_early_refit(const std::string& sat_id,
                                                                   storage::RefitTrigger trigger,
                                                                   int64_t scheduled_utime) {
  if (!storage::is_early_refit(trigger)) return std::nullopt;
  // A spacecraft's early refits are few (about five in its first window): the recent jobs hold
  // them.
  for (auto& job : jobs_->recent(sat_id, 32)) {
    if (job.trigger == to_string(trigger) && job.scheduled_utime == scheduled_utime &&
        job.calibration_id.has_value()) {
      return std::move(job);
    }
  }
  return std::nullopt;
}

bool RefitRunner::claim_job(const std::string& sat_id, storage::RefitTrigger trigger,
                            int64_t scheduled_utime, RefitOutcome& out) {
  const std::string& station = config_.station.id;
  std::optional<storage::RefitJob> holder;
  // No holder after a refused claim: it was interrupted in between (its station restarted),
  // and the claim is free again.
  for (int attempt = 0; attempt < 3 && !holder; ++attempt) {
    if (const auto id =
            jobs_->claim(sat_id, to_string(trigger), scheduled_utime, now_utime(), station)) {
      out.job_id = *id;
      return true;
    }
    holder = jobs_->claim_holder(sat_id, to_string(trigger), scheduled_utime);
    if (holder && holder->claimed_by != station &&
        holder->outcome == storage::job_outcome::kRunning) {
      // Claimed by a station that died while running it (its heartbeat ran out: this daemon
      // took its spacecraft over): its jobs will never finish, so their claims are given up
      // and the refit runs here.
      const auto live = leases_->live_stations(now_utime());
      if (std::find(live.begin(), live.end(), holder->claimed_by) == live.end()) {
        const int n = jobs_->mark_station_running_interrupted(holder->claimed_by, now_utime());
        spdlog::warn("{} refit job(s) of station {}, no longer live, were running: interrupted", n,
                     holder->claimed_by);
        holder.reset();
      }
    }
  }
  if (holder && holder->claimed_by == station &&
      holder->outcome == storage::job_outcome::kRunning) {
    // This station's job still running is an earlier attempt of this refit thread, whose end a
    // storage failure kept from being written: this attempt carries it on.
    out.job_id = holder->id;
    return true;
  }
  if (holder) {
    not_run_here(*holder, station, out);
  } else {
    out.kind = RefitOutcome::Kind::kClaimedElsewhere;
    out.message = "the " + std::string(to_string(trigger)) + " refit ending at " +
                  format_iso8601_utc(scheduled_utime) + " was claimed by another station";
  }
  return false;
}

std::string RefitRunner::skip_reason(const std::string& sat_id,
                                     std::optional<int64_t> t_ref_utime) {
  if (!t_ref_utime) t_ref_utime = samples_->newest_utime(sat_id);
  if (!t_ref_utime) return "no stored samples for '" + sat_id + "'";
  return too_few_samples_reason(samples_->count_in_window(
      sat_id, *t_ref_utime - config_.window_utime() + 1, *t_ref_utime + 1));
}

std::string RefitRunner::too_few_samples_reason(int64_t n_in_window) const {
  if (n_in_window >= config_.refit.min_samples) return "";
  return std::to_string(n_in_window) + " samples in the window, " +
         std::to_string(config_.refit.min_samples) + " needed ([refit] min_samples)";
}

RefitOutcome RefitRunner::run(const std::string& sat_id, std::optional<int64_t> t_ref_utime,
                              storage::RefitTrigger trigger, int64_t scheduled_utime) {
  RefitOutcome out;
  // `magcal refit` runs whenever asked; the daemons' refits run once for all of them.
  const bool claimed = trigger != storage::RefitTrigger::kManual;
  // An unclaimed (manual) job is written with its end, in the end's transaction: a 'running'
  // row of its own would stay running for good if the process died (Ctrl-C) or its COMMIT got
  // no reply and landed later, since no daemon owns a manual job to interrupt it.
  const int64_t started_utime = now_utime();
  const auto finish_job = [&](std::string_view outcome, const std::string& message,
                              std::optional<int64_t> calibration_id) {
    if (!claimed)
      out.job_id = jobs_->start(sat_id, to_string(trigger), scheduled_utime, started_utime);
    jobs_->finish(out.job_id, outcome, now_utime(), message, calibration_id);
  };
  try {
    if (const auto done = finished_early_refit(sat_id, trigger, scheduled_utime)) {
      not_run_here(*done, config_.station.id, out);
      return out;
    }
    if (claimed && !claim_job(sat_id, trigger, scheduled_utime, out)) return out;
  } catch (const storage::StorageError& e) {
    out.message = std::string("cannot write the job row: ") + e.what();
    out.storage_error = e;
    return out;
  }
  try {
    if (!t_ref_utime) t_ref_utime = samples_->newest_utime(sat_id);
    // The window is read once and its rows counted for skip_reason()'s test: the count query
    // took a quarter of the read's time on top (perf, refit_fleet_bench).
    if (t_ref_utime) {
      samples_->read_window(sat_id, *t_ref_utime - config_.window_utime() + 1, *t_ref_utime + 1,
                            rows_);
    }
    if (std::string why = t_ref_utime ? too_few_samples_reason(static_cast<int64_t>(rows_.size()))
                                      : skip_reason(sat_id, t_ref_utime);
        !why.empty()) {
      out.kind = RefitOutcome::Kind::kSkipped;
      out.job_outcome = storage::job_outcome::kSkipped;
      out.message = std::move(why);
      storage::Transaction tx(db_);
      finish_job(out.job_outcome, out.message, std::nullopt);
      tx.commit();
      return out;
    }
    const int64_t t_ref = *t_ref_utime;
    out.n_window_samples = static_cast<int>(rows_.size());
    window_.clear();
    window_.reserve(rows_.size());
    for (const auto& r : rows_) window_.push_back(calibration_sample_from_stored(r));

    // The change gate's reference: the last accepted *full-window* refit. A refit on a short
    // window (the first hours of a spacecraft, or after a gap: span below 90 % of
    // window_hours) has wider true errors and must not become the yardstick of later full
    // refits; with none yet, the refit is judged on its own evidence (change gate skipped).
    // A yardstick with a bias rate is moved by it to this window's end (where this refit
    // publishes its bias): a drifting sensor's refits differ by the drift, not by a jump.
    std::optional<CalibrationResult> previous;
    if (const auto rec = history_->latest_accepted_refit(
            sat_id, static_cast<int64_t>(kFullWindowFraction * config_.window_utime()),
            config_.refit.min_samples)) {
      previous = at_utime(at_temperature(result_from_record(*rec), mean_temperature_C(window_)),
                          rows_.empty() ? t_ref : rows_.back().utime);
    }
    out.result = calibrate_batch(window_, options_, previous ? &*previous : nullptr);
    out.result.utime = t_ref;  // the time the refit refers to: its scheduled window end
    if (previous) accept_corroborated_change(sat_id, *previous, out.result);
    if (pause_before_storing_.count() > 0) std::this_thread::sleep_for(pause_before_storing_);
    // The result and its job's outcome in one transaction: a restart after a crash finds a
    // refit either done (both) or interrupted (neither), and runs only the latter again.
    storage::Transaction tx(db_);
    out.calibration_id = history_->append(record_from_result(sat_id, out.result));
    if (out.result.accepted && out.result.status == CalibrationStatus::kOk) {
      out.job_outcome = storage::job_outcome::kOk;
    } else if (out.result.status == CalibrationStatus::kRejected) {
      out.job_outcome = storage::job_outcome::kRejected;
    } else {
      out.job_outcome = storage::job_outcome::kFailed;
      out.message = out.result.message.empty() ? to_string(out.result.status) : out.result.message;
    }
    finish_job(out.job_outcome, out.message, out.calibration_id);
    tx.commit();
    out.kind = RefitOutcome::Kind::kComputed;
  } catch (const storage::StorageError& e) {
    out.kind = RefitOutcome::Kind::kError;
    out.calibration_id = 0;  // rolled back
    // A transient failure of a claimed refit is retried (the daemon's refit thread): its job
    // gives the claim up, or the retry would find the refit taken.
    out.job_outcome = claimed && e.transient() ? storage::job_outcome::kInterrupted
                                               : storage::job_outcome::kFailed;
    out.message = e.what();
    out.storage_error = e;
    // A COMMIT in doubt (PostgreSQL: no reply to it) may have stored the result with its job's
    // outcome: the job row is left as that commit left it (finish() would only wait on its
    // lock, and then refuse a row no longer running). The retry then finds the refit done, or
    // its own job still running and carries it on (claim_job), never a second result.
    if (!claimed) out.job_id = 0;  // written with its end: rolled back (or in doubt) with it
    if (e.in_doubt_transaction() != 0) return out;
    try {
      storage::Transaction tx(db_);
      finish_job(out.job_outcome, out.message, std::nullopt);
      tx.commit();
    } catch (const storage::StorageError&) {
      // The database is unusable; the caller reports out.message.
    }
  }
  return out;
}

}  // namespace magcal
