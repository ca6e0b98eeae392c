#include "storage/postgres/pg_refit_job_log.hpp"

#include "storage/postgres/pg_row.hpp"
#include "storage/refit_job_sql.hpp"

namespace magcal::storage {
namespace {

// The first job of `r`; nullopt without rows.
std::optional<RefitJob> first_job(const PgResult& r) {
  if (r.rows() == 0) return std::nullopt;
  return row_codec::read<RefitJobRow>(PgRow{r, 0});
}

// The one value of a query on sat_id ($1); nullopt when NULL (max() of no rows).
std::optional<int64_t> single_int(PgDatabase& db, const std::string& sql, std::string_view sat_id) {
  PgParams p;
  p.add(sat_id);
  const PgResult r = db.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return r.get_optional_int64(0, 0);
}

// Interrupts the running jobs a statement selects ($1, $2), giving them `error`.
int interrupt(PgDatabase& db, const std::string& sql, std::string_view selector, int64_t now_utime,
              const char* error) {
  PgParams p;
  p.add(selector).add(now_utime).add(error);
  return static_cast<int>(db.execute_prepared(sql, p).affected_rows());
}

}  // namespace

int64_t PgRefitJobLog::start(std::string_view sat_id, std::string_view trigger,
                             int64_t scheduled_utime, int64_t started_utime) {
  static const std::string sql = dollar_params(refit_job_sql::kStart);
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime).add(started_utime);
  return db_.execute_prepared(sql, p, PgFormat::kBinary).get_int64(0, 0);
}

std::optional<int64_t> PgRefitJobLog::claim(std::string_view sat_id, std::string_view trigger,
                                            int64_t scheduled_utime, int64_t started_utime,
                                            std::string_view station) {
  static const std::string sql = dollar_params(refit_job_sql::claim());
  check_claimant(station);
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime).add(started_utime).add(station);
  const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;  // DO NOTHING: another job holds the claim
  return r.get_int64(0, 0);
}

std::optional<RefitJob> PgRefitJobLog::claim_holder(std::string_view sat_id,
                                                    std::string_view trigger,
                                                    int64_t scheduled_utime) {
  static const std::string sql = dollar_params(refit_job_sql::claim_holder());
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime);
  return first_job(db_.execute_prepared(sql, p, PgFormat::kBinary));
}

void PgRefitJobLog::finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                           std::string_view error, std::optional<int64_t> calibration_id) {
  static const std::string sql = dollar_params(refit_job_sql::kFinish);
  PgParams p;
  p.add(job_id).add(outcome).add(finished_utime).add(error).add(calibration_id);
  if (db_.execute_prepared(sql, p).affected_rows() != 1) throw_not_running(job_id, get(job_id));
}

int PgRefitJobLog::mark_station_running_interrupted(std::string_view station, int64_t now_utime) {
  static const std::string sql = dollar_params(refit_job_sql::kInterruptStation);
  return interrupt(db_, sql, station, now_utime, job_outcome::kProcessEnded);
}

int PgRefitJobLog::mark_running_interrupted(std::string_view sat_id, int64_t now_utime) {
  static const std::string sql = dollar_params(refit_job_sql::kInterruptSpacecraft);
  return interrupt(db_, sql, sat_id, now_utime, job_outcome::kTakenOver);
}

std::optional<int64_t> PgRefitJobLog::newest_reanchor_calibration_id(std::string_view sat_id) {
  static const std::string sql = dollar_params(refit_job_sql::kNewestReanchor);
  return single_int(db_, sql, sat_id);
}

std::optional<int64_t> PgRefitJobLog::newest_finished_scheduled_utime(std::string_view sat_id) {
  static const std::string sql = dollar_params(refit_job_sql::kNewestScheduled);
  return single_int(db_, sql, sat_id);
}

std::optional<RefitJob> PgRefitJobLog::get(int64_t job_id) {
  static const std::string sql = dollar_params(refit_job_sql::get());
  PgParams p;
  p.add(job_id);
  return first_job(db_.execute_prepared(sql, p, PgFormat::kBinary));
}

std::vector<RefitJob> PgRefitJobLog::recent(std::string_view sat_id, int limit) {
  static const std::string sql = dollar_params(refit_job_sql::recent());
  PgParams p;
  p.add(sat_id).add(int64_t{limit});
  const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
  std::vector<RefitJob> out;
  for (int row = 0; row < r.rows(); ++row)
    out.push_back(row_codec::read<RefitJobRow>(PgRow{r, row}));
  return out;
}

}  // namespace magcal::storage
