#include "storage/sql_refit_job_log.hpp"

#include "storage/refit_job_sql.hpp"

namespace magcal::storage {
namespace {

RefitJob read_job(const SqlRow& row) {
  return row_codec::read<RefitJobRow>(row);
}

}  // namespace

SqlRefitJobLog::SqlRefitJobLog(SqlSession& db)
    : start_(db.prepare(refit_job_sql::kStart)),
      claim_(db.prepare(refit_job_sql::claim())),
      claim_holder_(db.prepare(refit_job_sql::claim_holder())),
      finish_(db.prepare(refit_job_sql::kFinish)),
      interrupt_station_(db.prepare(refit_job_sql::kInterruptStation)),
      interrupt_spacecraft_(db.prepare(refit_job_sql::kInterruptSpacecraft)),
      newest_reanchor_(db.prepare(refit_job_sql::kNewestReanchor)),
      newest_scheduled_(db.prepare(refit_job_sql::kNewestScheduled)),
      get_(db.prepare(refit_job_sql::get())),
      recent_(db.prepare(refit_job_sql::recent())) {}

int64_t SqlRefitJobLog::start(std::string_view sat_id, std::string_view trigger,
                              int64_t scheduled_utime, int64_t started_utime) {
  SqlRun run(*start_, sat_id, trigger, scheduled_utime, started_utime);
  return run.single_integer().value();  // RETURNING id
}

std::optional<int64_t> SqlRefitJobLog::claim(std::string_view sat_id, std::string_view trigger,
                                             int64_t scheduled_utime, int64_t started_utime,
                                             std::string_view station) {
  check_claimant(station);
  SqlRun run(*claim_, sat_id, trigger, scheduled_utime, started_utime, station);
  return run.single_integer();  // nothing (DO NOTHING): another job holds the claim
}

std::optional<RefitJob> SqlRefitJobLog::claim_holder(std::string_view sat_id,
                                                     std::string_view trigger,
                                                     int64_t scheduled_utime) {
  SqlRun run(*claim_holder_, sat_id, trigger, scheduled_utime);
  return run.first<RefitJob>(read_job);
}

void SqlRefitJobLog::finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                            std::string_view error, std::optional<int64_t> calibration_id) {
  int64_t changed = 0;
  {
    SqlRun run(*finish_, job_id, outcome, finished_utime, error, calibration_id);
    changed = run.changes();
  }
  if (changed != 1) throw_not_running(job_id, get(job_id));
}

int SqlRefitJobLog::mark_station_running_interrupted(std::string_view station, int64_t now_utime) {
  SqlRun run(*interrupt_station_, station, now_utime, job_outcome::kProcessEnded);
  return static_cast<int>(run.changes());
}

int SqlRefitJobLog::mark_running_interrupted(std::string_view sat_id, int64_t now_utime) {
  SqlRun run(*interrupt_spacecraft_, sat_id, now_utime, job_outcome::kTakenOver);
  return static_cast<int>(run.changes());
}

std::optional<int64_t> SqlRefitJobLog::newest_reanchor_calibration_id(std::string_view sat_id) {
  return SqlRun(*newest_reanchor_, sat_id).single_integer();
}

std::optional<int64_t> SqlRefitJobLog::newest_finished_scheduled_utime(std::string_view sat_id) {
  return SqlRun(*newest_scheduled_, sat_id).single_integer();
}

std::optional<RefitJob> SqlRefitJobLog::get(int64_t job_id) {
  return SqlRun(*get_, job_id).first<RefitJob>(read_job);
}

std::vector<RefitJob> SqlRefitJobLog::recent(std::string_view sat_id, int limit) {
  return SqlRun(*recent_, sat_id, limit).all<RefitJob>(read_job);
}

}  // namespace magcal::storage
