#include "storage/refit_job_log.hpp"

namespace magcal::storage {

void RefitJobLog::check_claimant(std::string_view station) {
  if (station.empty()) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "a refit claim needs the claiming station's id");
  }
}

void RefitJobLog::throw_not_running(int64_t job_id, const std::optional<RefitJob>& job) {
  if (!job) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "no refit job with id " + std::to_string(job_id));
  }
  throw StorageError(StorageError::Kind::kInvalidArgument,
                     "refit job " + std::to_string(job_id) + " is no longer running ('" +
                         job->outcome + "': " + job->error + ")");
}

std::optional<RefitJob> RefitJobLog::latest(std::string_view sat_id) {
  auto jobs = recent(sat_id, 1);
  if (jobs.empty()) return std::nullopt;
  return jobs.front();
}

}  // namespace magcal::storage
