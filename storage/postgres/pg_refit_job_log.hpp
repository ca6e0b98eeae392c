// The PostgreSQL RefitJobLog (storage/refit_job_log.hpp) on one PgDatabase, made by
// PgDatabase::make_refit_job_log().
#pragma once

#include "storage/postgres/pg_database.hpp"
#include "storage/refit_job_log.hpp"

namespace magcal::storage {

class PgRefitJobLog final : public RefitJobLog {
 public:
  explicit PgRefitJobLog(PgDatabase& db) : db_(db) {}

  int64_t start(std::string_view sat_id, std::string_view trigger, int64_t scheduled_utime,
                int64_t started_utime) override;
  void finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
              std::string_view error = {}, std::optional<int64_t> calibration_id = {}) override;
  std::optional<int64_t> claim(std::string_view sat_id, std::string_view trigger,
                               int64_t scheduled_utime, int64_t started_utime,
                               std::string_view station) override;
  std::optional<RefitJob> claim_holder(std::string_view sat_id, std::string_view trigger,
                                       int64_t scheduled_utime) override;
  int mark_station_running_interrupted(std::string_view station, int64_t now_utime) override;
  int mark_running_interrupted(std::string_view sat_id, int64_t now_utime) override;
  std::optional<int64_t> newest_reanchor_calibration_id(std::string_view sat_id) override;
  std::optional<int64_t> newest_finished_scheduled_utime(std::string_view sat_id) override;
  std::optional<RefitJob> get(int64_t job_id) override;
  std::vector<RefitJob> recent(std::string_view sat_id, int limit) override;

 private:
  PgDatabase& db_;
};

}  // namespace magcal::storage
