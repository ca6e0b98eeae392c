// Table `refit_jobs`: one row per scheduled or manual refit — when it was due, when it ran, how
// it ended, and the calibration row it produced. An interface: SqliteRefitJobLog
// (storage/sqlite_stores.hpp) and PgRefitJobLog (storage/postgres/pg_stores.hpp), made by
// Connection::make_refit_job_log().
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::storage {

// Outcome strings stored in refit_jobs.outcome.
namespace job_outcome {
constexpr const char* kRunning = "running";
constexpr const char* kOk = "ok";                    // result accepted
constexpr const char* kRejected = "rejected";        // result stored but refused by the gates
constexpr const char* kFailed = "failed";            // estimator failed / error (see error)
constexpr const char* kSkipped = "skipped";          // e.g. too few samples in the window
constexpr const char* kInterrupted = "interrupted";  // process died while running
}  // namespace job_outcome

struct RefitJob {
  int64_t id = 0;
  std::string sat_id;
  std::string trigger;  // "scheduled" | "manual" | "first" | "early" (a new spacecraft's refits)
  int64_t scheduled_utime = 0;
  std::optional<int64_t> started_utime;
  std::optional<int64_t> finished_utime;
  std::string outcome;
  std::string error;
  std::optional<int64_t> calibration_id;
};

class RefitJobLog {
 public:
  virtual ~RefitJobLog() = default;

  // Inserts a 'running' job; returns its id.
  virtual int64_t start(std::string_view sat_id, std::string_view trigger, int64_t scheduled_utime,
                        int64_t started_utime) = 0;
  // Throws StorageError (kInvalidArgument) for an unknown job, (kConstraint) for a
  // calibration_id that is not in the history.
  virtual void finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                      std::string_view error = {}, std::optional<int64_t> calibration_id = {}) = 0;
  // Crash recovery, called once by the daemon at start: every 'running' job becomes
  // 'interrupted' (finished at now_utime). Returns how many.
  virtual int mark_running_interrupted(int64_t now_utime) = 0;

  // What a restarting daemon resumes from, per spacecraft:
  //   the calibration of its newest refit that ended 'ok' (accepted) and was not 'manual' (the
  //   daemon re-anchors its filter on those, never on a `magcal refit`);
  //   the newest scheduled time of a 'scheduled' refit that ran to its end (any outcome but
  //   'running' / 'interrupted'): later due times were not run.
  virtual std::optional<int64_t> newest_reanchor_calibration_id(std::string_view sat_id) = 0;
  virtual std::optional<int64_t> newest_finished_scheduled_utime(std::string_view sat_id) = 0;

  virtual std::optional<RefitJob> get(int64_t job_id) = 0;
  std::optional<RefitJob> latest(std::string_view sat_id);
  // The newest `limit` jobs of `sat_id`, newest first.
  virtual std::vector<RefitJob> recent(std::string_view sat_id, int limit) = 0;
};

}  // namespace magcal::storage
