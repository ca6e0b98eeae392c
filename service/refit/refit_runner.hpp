// One offline refit of a spacecraft's stored window (design.md "Daemon data flow"):
//   job row 'running' -> window (t_ref - window_hours, t_ref] from the store
//   -> calibrate_batch (centered -> LM -> alignment when the samples carry reference
//      directions -> acceptance gates; the change gate compares with the previous accepted
//      refit from the history) -> history row + job row finished, one transaction (ok |
//      rejected | failed; skipped, job row only, when fewer than [refit] min_samples).
// The same code runs in the daemon's refit thread and in `magcal refit` (its own process and
// connection: SQLite WAL lets it run while the daemon writes, PostgreSQL is shared anyway).
// Publishing and re-anchoring the UKF are the caller's business.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_result.hpp"
#include "service/config/daemon_config.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

struct RefitOutcome {
  enum class Kind {
    kComputed,  // a result was computed and stored (accepted or rejected, or a failed fit)
    kSkipped,   // too few samples in the window: job row only
    kError,     // database error: job row marked failed if it could be written
    // A daemon's refit another station claimed (design.md "Fleet"): it runs there, nothing
    // here; job_id is its job (0 when unknown).
    kClaimedElsewhere,
  };
  Kind kind = Kind::kError;
  CalibrationResult result;  // valid for kComputed
  std::string job_outcome;   // storage job_outcome::k*
  std::string message;       // why skipped / error text
  int64_t job_id = 0;
  int64_t calibration_id = 0;
  int n_window_samples = 0;
  // kError: the storage failure (its transient() ones the daemon's refit thread retries).
  std::optional<storage::StorageError> storage_error;
  // Accepted by the gates and a valid estimate: the UKF may re-anchor on it.
  bool accepted() const {
    return kind == Kind::kComputed && result.accepted && result.status == CalibrationStatus::kOk;
  }
};

BatchCalibrationOptions batch_options_from_config(const DaemonConfig& config);

class RefitRunner {
 public:
  // Uses `db` (one thread's connection) for the window, the history and the job log.
  RefitRunner(const DaemonConfig& config, storage::Connection& db);

  // t_ref: end of the window (data clock: the scheduled time); nullopt = the newest stored
  // sample of the spacecraft. An early refit (storage::is_early_refit, keyed by its window end:
  // IngestWorker::Hooks::on_refit_due) whose job already produced a result is skipped without a
  // job row: each runs once. A daemon's refit (any trigger but kManual) is claimed under [station]
  // id, so that daemons sharing a database run it once: kClaimedElsewhere when another station
  // holds the claim, kSkipped when this station's job already ended; a transient storage error ends
  // the job 'interrupted', which gives the claim up for the retry. Never throws.
  RefitOutcome run(const std::string& sat_id, std::optional<int64_t> t_ref_utime,
                   storage::RefitTrigger trigger, int64_t scheduled_utime);

  std::vector<std::string> spacecraft();  // with stored samples

  // Why run() would skip this refit ("" when it would not): no stored samples of sat_id, or
  // fewer than [refit] min_samples in the window. Reads only: `magcal refit` refuses such a
  // refit before writing anything, where the daemon records it as a 'skipped' job.
  std::string skip_reason(const std::string& sat_id, std::optional<int64_t> t_ref_utime);

 private:
  // skip_reason() for a window of n_in_window samples.
  std::string too_few_samples_reason(int64_t n_in_window) const;
  // Accepts `result` when it failed only the change gate against `reference` and the previous
  // full-window refit (newer than the reference) failed only that gate too and agrees with it
  // (a real change seen by two windows). True when it changed the verdict.
  bool accept_corroborated_change(const std::string& sat_id, const CalibrationResult& reference,
                                  CalibrationResult& result);
  // The finished job of the early refit (sat_id, trigger, scheduled_utime), if there is one.
  std::optional<storage::RefitJob> finished_early_refit(const std::string& sat_id,
                                                        storage::RefitTrigger trigger,
                                                        int64_t scheduled_utime);
  // Claims the refit's job for this station into out.job_id; false, with out.kind and
  // out.message saying why, when it must not run here.
  bool claim_job(const std::string& sat_id, storage::RefitTrigger trigger, int64_t scheduled_utime,
                 RefitOutcome& out);

  const DaemonConfig config_;  // a copy: callers may pass a temporary
  BatchCalibrationOptions options_;
  storage::Connection& db_;
  std::unique_ptr<storage::SampleWindowStore> samples_;
  std::unique_ptr<storage::CalibrationHistory> history_;
  std::unique_ptr<storage::RefitJobLog> jobs_;
  std::unique_ptr<storage::LeaseStore> leases_;  // which stations are live
  std::vector<storage::StoredSample> rows_;      // reused between refits
  SampleSet window_;
  // Fault injection for the tests that kill a daemon inside a refit (daemon_crash_resume_test):
  // the environment's MAGCAL_FAULT_REFIT_PAUSE_MS holds each computed refit that long before the
  // transaction that stores it and ends its job, so that a kill can land there whatever the
  // machine's speed. Unset (0) in operations.
  std::chrono::milliseconds pause_before_storing_{0};
};

}  // namespace magcal
