// Table `refit_jobs`: one row per scheduled or manual refit — when it was due, when it ran, how
// it ended, and the calibration row it produced.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "storage/database.hpp"
#include "storage/statement.hpp"

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
  explicit RefitJobLog(Database& db);

  // Inserts a 'running' job; returns its id.
  int64_t start(std::string_view sat_id, std::string_view trigger, int64_t scheduled_utime,
                int64_t started_utime);
  void finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
              std::string_view error = {}, std::optional<int64_t> calibration_id = {});
  // Crash recovery, called once by the daemon at start: every 'running' job becomes
  // 'interrupted' (finished at now_utime). Returns how many.
  int mark_running_interrupted(int64_t now_utime);

  // What a restarting daemon resumes from, per spacecraft:
  //   the calibration of its newest refit that ended 'ok' (accepted) and was not 'manual' (the
  //   daemon re-anchors its filter on those, never on a `magcal refit`);
  //   the newest scheduled time of a 'scheduled' refit that ran to its end (any outcome but
  //   'running' / 'interrupted'): later due times were not run.
  std::optional<int64_t> newest_reanchor_calibration_id(std::string_view sat_id);
  std::optional<int64_t> newest_finished_scheduled_utime(std::string_view sat_id);

  std::optional<RefitJob> get(int64_t job_id);
  std::optional<RefitJob> latest(std::string_view sat_id);
  std::vector<RefitJob> recent(std::string_view sat_id, int limit);

 private:
  Database& db_;
  Statement insert_;
  Statement finish_;
  Statement interrupt_;
  Statement get_;
  Statement recent_;
  Statement newest_reanchor_;
  Statement newest_scheduled_;
};

}  // namespace magcal::storage
