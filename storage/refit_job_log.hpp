// Table `refit_jobs`: one row per scheduled or manual refit — when it was due, when it ran, how
// it ended, and the calibration row it produced. An interface: SqlRefitJobLog
// (storage/sql_refit_job_log.hpp, both backends), made by Connection::make_refit_job_log().
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::storage {

// Why a refit ran, stored in refit_jobs.trigger_kind as to_string()'s text.
enum class RefitTrigger {
  kScheduled,  // the schedule ([refit] daily_at_utc, every_hours) on the wall or data clock
  kFirst,      // a new spacecraft's stored samples reached [refit] min_samples
  kEarly,      // ... and grew by [refit] early_growth since, while its window is not full
  kManual,     // `magcal refit`
};
inline constexpr std::string_view to_string(RefitTrigger t) {
  switch (t) {
    case RefitTrigger::kScheduled:
      return "scheduled";
    case RefitTrigger::kFirst:
      return "first";
    case RefitTrigger::kEarly:
      return "early";
    case RefitTrigger::kManual:
      return "manual";
  }
  return "scheduled";
}
// The trigger a stored trigger_kind names; nullopt for a text no version of magcal writes.
inline std::optional<RefitTrigger> refit_trigger_from_string(std::string_view text) {
  for (RefitTrigger t : {RefitTrigger::kScheduled, RefitTrigger::kFirst, RefitTrigger::kEarly,
                         RefitTrigger::kManual}) {
    if (text == to_string(t)) return t;
  }
  return std::nullopt;
}
// A new spacecraft's refits before its window is full (their job claims differ from the
// schedule's: the window ends at the N-th stored sample).
inline constexpr bool is_early_refit(RefitTrigger t) {
  return t == RefitTrigger::kFirst || t == RefitTrigger::kEarly;
}

// Outcome strings stored in refit_jobs.outcome.
namespace job_outcome {
constexpr const char* kRunning = "running";
constexpr const char* kOk = "ok";                    // result accepted
constexpr const char* kRejected = "rejected";        // result stored but refused by the gates
constexpr const char* kFailed = "failed";            // estimator failed / error (see error)
constexpr const char* kSkipped = "skipped";          // e.g. too few samples in the window
constexpr const char* kInterrupted = "interrupted";  // process died while running
// The error text of an interrupted job: why.
constexpr const char* kProcessEnded = "process ended while the refit was running";
constexpr const char* kTakenOver = "another daemon took the spacecraft over while it ran";
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
  std::string claimed_by;  // station that claimed it (claim()); "" when not claimed
};

class RefitJobLog {
 public:
  virtual ~RefitJobLog() = default;

  // Inserts a 'running' job, not claimed (a manual refit; a single daemon's); returns its id.
  virtual int64_t start(std::string_view sat_id, std::string_view trigger, int64_t scheduled_utime,
                        int64_t started_utime) = 0;
  // The fleet's start of a refit that must run once for all daemons (design.md "Fleet"): inserts
  // a 'running' job claimed by `station` and returns its id, or nullopt when another job holds
  // the claim of (sat_id, trigger, scheduled_utime): already claimed, running or ended. Of
  // concurrent claims exactly one wins. An interrupted job gives its claim up (the refit may be
  // claimed again); no other outcome does.
  virtual std::optional<int64_t> claim(std::string_view sat_id, std::string_view trigger,
                                       int64_t scheduled_utime, int64_t started_utime,
                                       std::string_view station) = 0;
  // The job holding that claim (who claimed it, how it ended), if any.
  virtual std::optional<RefitJob> claim_holder(std::string_view sat_id, std::string_view trigger,
                                               int64_t scheduled_utime) = 0;
  // Ends a 'running' job. Throws StorageError (kInvalidArgument) for an unknown job or one no
  // longer running (interrupted meanwhile: its spacecraft was taken over), (kConstraint) for a
  // calibration_id that is not in the history.
  virtual void finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                      std::string_view error = {}, std::optional<int64_t> calibration_id = {}) = 0;
  // Crash recovery, called once by a daemon at start: the 'running' jobs it may have left,
  // those claimed by `station` and the unclaimed ones (a single daemon's of schema < 7, or an
  // aborted `magcal refit`), become 'interrupted' (finished at now_utime), which gives their
  // claims up. Other stations' running jobs are theirs: untouched. Returns how many.
  virtual int mark_station_running_interrupted(std::string_view station, int64_t now_utime) = 0;
  // The same for one spacecraft: its new owner's first step after taking its lease over (the
  // jobs of the previous owner will never finish, and their claims are given up).
  virtual int mark_running_interrupted(std::string_view sat_id, int64_t now_utime) = 0;

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

 protected:
  // Both backends' argument check and error for claim() and finish().
  static void check_claimant(std::string_view station);
  [[noreturn]] static void throw_not_running(int64_t job_id, const std::optional<RefitJob>& job);
};

}  // namespace magcal::storage
