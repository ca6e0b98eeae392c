#include "storage/sqlite/sqlite_refit_job_log.hpp"

#include "storage/refit_job_sql.hpp"
#include "storage/sqlite/sqlite_row.hpp"

namespace magcal::storage {
namespace {

// The one value of a query on sat_id (?1); nullopt when NULL (max() of no rows).
std::optional<int64_t> single_int(Statement& st, std::string_view sat_id) {
  auto use = st.use();
  st.bind(1, sat_id);
  if (!st.step() || st.is_null(0)) return std::nullopt;
  return st.column_int64(0);
}

RefitJob read_row(const Statement& st) {
  return row_codec::read<RefitJobRow>(SqliteRow{st});
}

// A statement that interrupts the running jobs it selects (?1, ?2), giving them `error`.
int interrupt(Statement& st, std::string_view selector, int64_t now_utime, const char* error) {
  auto use = st.use();
  st.bind(1, selector).bind(2, now_utime).bind(3, error);
  return st.execute();
}

}  // namespace

SqliteRefitJobLog::SqliteRefitJobLog(Database& db)
    : insert_(db, refit_job_sql::kStart),
      claim_(db, refit_job_sql::claim()),
      claim_holder_(db, refit_job_sql::claim_holder()),
      finish_(db, refit_job_sql::kFinish),
      interrupt_(db, refit_job_sql::kInterruptStation),
      interrupt_sat_(db, refit_job_sql::kInterruptSpacecraft),
      get_(db, refit_job_sql::get()),
      recent_(db, refit_job_sql::recent()),
      newest_reanchor_(db, refit_job_sql::kNewestReanchor),
      newest_scheduled_(db, refit_job_sql::kNewestScheduled) {}

int64_t SqliteRefitJobLog::start(std::string_view sat_id, std::string_view trigger,
                                 int64_t scheduled_utime, int64_t started_utime) {
  auto use = insert_.use();
  insert_.bind(1, sat_id).bind(2, trigger).bind(3, scheduled_utime).bind(4, started_utime);
  insert_.step();  // RETURNING id
  return insert_.column_int64(0);
}

std::optional<int64_t> SqliteRefitJobLog::claim(std::string_view sat_id, std::string_view trigger,
                                                int64_t scheduled_utime, int64_t started_utime,
                                                std::string_view station) {
  check_claimant(station);
  auto use = claim_.use();
  claim_.bind(1, sat_id).bind(2, trigger).bind(3, scheduled_utime).bind(4, started_utime);
  claim_.bind(5, station);
  if (!claim_.step()) return std::nullopt;  // DO NOTHING: another job holds the claim
  return claim_.column_int64(0);
}

std::optional<RefitJob> SqliteRefitJobLog::claim_holder(std::string_view sat_id,
                                                        std::string_view trigger,
                                                        int64_t scheduled_utime) {
  auto use = claim_holder_.use();
  claim_holder_.bind(1, sat_id).bind(2, trigger).bind(3, scheduled_utime);
  if (!claim_holder_.step()) return std::nullopt;
  return read_row(claim_holder_);
}

void SqliteRefitJobLog::finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                               std::string_view error, std::optional<int64_t> calibration_id) {
  int changed = 0;
  {
    auto use = finish_.use();
    finish_.bind(1, job_id).bind(2, outcome).bind(3, finished_utime).bind(4, error);
    finish_.bind(5, calibration_id);
    changed = finish_.execute();
  }
  if (changed != 1) throw_not_running(job_id, get(job_id));
}

int SqliteRefitJobLog::mark_station_running_interrupted(std::string_view station,
                                                        int64_t now_utime) {
  return interrupt(interrupt_, station, now_utime, job_outcome::kProcessEnded);
}

int SqliteRefitJobLog::mark_running_interrupted(std::string_view sat_id, int64_t now_utime) {
  return interrupt(interrupt_sat_, sat_id, now_utime, job_outcome::kTakenOver);
}

std::optional<int64_t> SqliteRefitJobLog::newest_reanchor_calibration_id(std::string_view sat_id) {
  return single_int(newest_reanchor_, sat_id);
}

std::optional<int64_t> SqliteRefitJobLog::newest_finished_scheduled_utime(std::string_view sat_id) {
  return single_int(newest_scheduled_, sat_id);
}

std::optional<RefitJob> SqliteRefitJobLog::get(int64_t job_id) {
  auto use = get_.use();
  get_.bind(1, job_id);
  if (!get_.step()) return std::nullopt;
  return read_row(get_);
}

std::vector<RefitJob> SqliteRefitJobLog::recent(std::string_view sat_id, int limit) {
  std::vector<RefitJob> out;
  auto use = recent_.use();
  recent_.bind(1, sat_id).bind(2, limit);
  while (recent_.step()) out.push_back(read_row(recent_));
  return out;
}

}  // namespace magcal::storage
