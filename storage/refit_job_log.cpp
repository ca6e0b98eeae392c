#include "storage/refit_job_log.hpp"

#include "storage/sqlite_stores.hpp"
#include "storage/store_columns.hpp"

namespace magcal::storage {
namespace {

const std::string kSelect = std::string("SELECT ") + columns::kRefitJob + " FROM refit_jobs ";

std::optional<int64_t> optional_int(const Statement& st, int col) {
  if (st.is_null(col)) return std::nullopt;
  return st.column_int64(col);
}

// The one value of a query on sat_id (?1); nullopt when NULL (max() of no rows).
std::optional<int64_t> single_int(Statement& st, std::string_view sat_id) {
  auto use = st.use();
  st.bind(1, sat_id);
  if (!st.step()) return std::nullopt;
  return optional_int(st, 0);
}

RefitJob read_row(const Statement& st) {
  RefitJob j;
  j.id = st.column_int64(0);
  j.sat_id = st.column_text(1);
  j.trigger = st.column_text(2);
  j.scheduled_utime = st.column_int64(3);
  j.started_utime = optional_int(st, 4);
  j.finished_utime = optional_int(st, 5);
  j.outcome = st.column_text(6);
  j.error = st.column_text(7);
  j.calibration_id = optional_int(st, 8);
  j.claimed_by = st.column_text(9);
  return j;
}

}  // namespace

SqliteRefitJobLog::SqliteRefitJobLog(Database& db)
    : db_(db),
      insert_(db,
              "INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, started_utime, "
              "outcome) VALUES (?1, ?2, ?3, ?4, 'running')"),
      claim_(db, std::string("INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, "
                             "started_utime, outcome, claimed_by) VALUES (?1, ?2, ?3, ?4, "
                             "'running', ?5) ON CONFLICT (sat_id, trigger_kind, scheduled_utime) "
                             "WHERE ") +
                     columns::kHoldsRefitClaim + " DO NOTHING RETURNING id"),
      claim_holder_(
          db, kSelect + "WHERE sat_id = ?1 AND trigger_kind = ?2 AND scheduled_utime = ?3 AND " +
                  columns::kHoldsRefitClaim),
      finish_(db,
              "UPDATE refit_jobs SET outcome = ?2, finished_utime = ?3, error = ?4, "
              "calibration_id = ?5 WHERE id = ?1 AND outcome = 'running'"),
      interrupt_(db,
                 std::string("UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = ?2, "
                             "error = '") +
                     job_outcome::kProcessEnded +
                     "' WHERE outcome = 'running' AND (claimed_by = ?1 OR claimed_by IS NULL)"),
      interrupt_sat_(db,
                     std::string("UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = "
                                 "?2, error = '") +
                         job_outcome::kTakenOver + "' WHERE sat_id = ?1 AND outcome = 'running'"),
      get_(db, kSelect + "WHERE id = ?1"),
      recent_(db, kSelect + "WHERE sat_id = ?1 ORDER BY id DESC LIMIT ?2"),
      newest_reanchor_(db,
                       "SELECT max(calibration_id) FROM refit_jobs WHERE sat_id = ?1 AND "
                       "outcome = 'ok' AND trigger_kind <> 'manual'"),
      newest_scheduled_(db,
                        "SELECT max(scheduled_utime) FROM refit_jobs WHERE sat_id = ?1 AND "
                        "trigger_kind = 'scheduled' AND outcome NOT IN ('running', "
                        "'interrupted')") {}

int64_t SqliteRefitJobLog::start(std::string_view sat_id, std::string_view trigger,
                                 int64_t scheduled_utime, int64_t started_utime) {
  auto use = insert_.use();
  insert_.bind(1, sat_id).bind(2, trigger).bind(3, scheduled_utime).bind(4, started_utime);
  insert_.execute();
  return db_.last_insert_id();
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
  auto use = interrupt_.use();
  interrupt_.bind(1, station).bind(2, now_utime);
  return interrupt_.execute();
}

int SqliteRefitJobLog::mark_running_interrupted(std::string_view sat_id, int64_t now_utime) {
  auto use = interrupt_sat_.use();
  interrupt_sat_.bind(1, sat_id).bind(2, now_utime);
  return interrupt_sat_.execute();
}

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

std::optional<RefitJob> RefitJobLog::latest(std::string_view sat_id) {
  auto jobs = recent(sat_id, 1);
  if (jobs.empty()) return std::nullopt;
  return jobs.front();
}

std::vector<RefitJob> SqliteRefitJobLog::recent(std::string_view sat_id, int limit) {
  std::vector<RefitJob> out;
  auto use = recent_.use();
  recent_.bind(1, sat_id).bind(2, limit);
  while (recent_.step()) out.push_back(read_row(recent_));
  return out;
}

}  // namespace magcal::storage
