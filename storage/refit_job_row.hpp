// One `refit_jobs` row, the same on both backends (storage/row_codec.hpp walks the list). A job
// is written by its own statements (start, claim, finish), so the codec only reads it back.
// Internal to storage/.
#pragma once

#include "storage/refit_job_log.hpp"
#include "storage/row_codec.hpp"

namespace magcal::storage {

struct RefitJobRow {
  using Record = RefitJob;
  static constexpr const char* kTable = "refit_jobs";
  template <typename Job, typename Fields>
  static void fields(Job& j, Fields& f) {
    f("id", j.id);
    f("sat_id", j.sat_id);
    f("trigger_kind", j.trigger);
    f("scheduled_utime", j.scheduled_utime);
    f("started_utime", j.started_utime);
    f("finished_utime", j.finished_utime);
    f("outcome", j.outcome);
    f("error", j.error);
    f("calibration_id", j.calibration_id);
    f("claimed_by", j.claimed_by);  // NULL (not claimed) reads as ""
  }
};

// refit_jobs: the job holding the claim of its (sat_id, trigger_kind, scheduled_utime), the
// predicate of the unique index refit_jobs_one_claim, which an upsert names to use that index.
inline constexpr const char* kHoldsRefitClaim =
    "claimed_by IS NOT NULL AND outcome <> 'interrupted'";

}  // namespace magcal::storage
