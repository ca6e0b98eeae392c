#include "storage/sqlite/sqlite_calibration_history.hpp"

#include <algorithm>
#include <limits>

#include "storage/calibration_row.hpp"
#include "storage/sqlite/sqlite_row.hpp"

namespace magcal::storage {

SqliteCalibrationHistory::SqliteCalibrationHistory(Database& db)
    : db_(db),
      insert_(db, insert_sql()),
      query_all_(db, calibration_row::select_sql("WHERE sat_id = ?1 AND utime >= ?2 AND "
                                                 "utime <= ?3 ORDER BY utime DESC, id DESC "
                                                 "LIMIT ?4")),
      query_method_(db, calibration_row::select_sql("WHERE sat_id = ?1 AND utime >= ?2 AND "
                                                    "utime <= ?3 AND method = ?5 ORDER BY utime "
                                                    "DESC, id DESC LIMIT ?4")),
      latest_(db, calibration_row::select_sql(
                      "WHERE sat_id = ?1 AND method = ?2 ORDER BY utime DESC, id DESC LIMIT 1")),
      get_(db, calibration_row::select_sql("WHERE id = ?1")),
      refits_(db, calibration_row::select_sql(std::string("WHERE sat_id = ?1 AND ") +
                                              calibration_row::kRefitMethods +
                                              " AND utime <= ?2 ORDER BY utime DESC, id DESC "
                                              "LIMIT 1")),
      accepted_refit_(db,
                      calibration_row::select_sql(
                          std::string("WHERE sat_id = ?1 AND ") + calibration_row::kRefitMethods +
                          " AND verdict = 'accepted' AND window_end_utime - "
                          "window_start_utime >= ?2 AND n_samples >= ?3 ORDER BY utime DESC, "
                          "id DESC LIMIT 1")),
      spacecraft_(db, "SELECT DISTINCT sat_id FROM calibrations ORDER BY sat_id"),
      reasons_(db, "SELECT value FROM json_each(?1)") {}

std::string SqliteCalibrationHistory::insert_sql() {
  std::string sql =
      std::string("INSERT INTO calibrations (") + calibration_row::kInsertColumns + ") VALUES (";
  for (int i = 1; i <= calibration_row::kInsertValues; ++i) {
    sql += (i > 1 ? ", ?" : "?") + std::to_string(i);
  }
  return sql + ")";
}

int64_t SqliteCalibrationHistory::append(const CalibrationRecord& r) {
  calibration_row::check_appendable(r);
  const std::string reasons = calibration_row::json_string_array(r.rejection_reasons);
  auto use = insert_.use();
  SqliteBinder binder{insert_};
  calibration_row::write(r, reasons, binder);
  insert_.execute();
  return db_.last_insert_id();
}

CalibrationRecord SqliteCalibrationHistory::read_row(Statement& st) {
  SqliteRow row{st};
  return calibration_row::read(row, [this](const std::string& json) {
    std::vector<std::string> out;
    auto use = reasons_.use();
    reasons_.bind(1, json);
    while (reasons_.step()) out.push_back(reasons_.column_text(0));
    return out;
  });
}

std::vector<CalibrationRecord> SqliteCalibrationHistory::rows(Statement& st) {
  std::vector<CalibrationRecord> out;
  while (st.step()) out.push_back(read_row(st));
  return out;
}

std::vector<CalibrationRecord> SqliteCalibrationHistory::query(const HistoryQuery& q) {
  Statement& st = q.method.empty() ? query_all_ : query_method_;
  std::vector<CalibrationRecord> out;
  {
    auto use = st.use();
    st.bind(1, q.sat_id);
    st.bind(2, q.since_utime.value_or(std::numeric_limits<int64_t>::min()));
    st.bind(3, q.until_utime.value_or(std::numeric_limits<int64_t>::max()));
    st.bind(4, q.limit ? static_cast<int64_t>(*q.limit) : int64_t{-1});  // -1: no limit
    if (!q.method.empty()) st.bind(5, q.method);
    out = rows(st);
  }
  // Selected newest first (so LIMIT keeps the newest); printed in the asked order.
  if (!q.descending) std::reverse(out.begin(), out.end());
  return out;
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::first(Statement& st) {
  if (!st.step()) return std::nullopt;
  return read_row(st);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::latest(std::string_view sat_id,
                                                                  std::string_view method) {
  auto use = latest_.use();
  latest_.bind(1, sat_id).bind(2, method);
  return first(latest_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::get(int64_t id) {
  auto use = get_.use();
  get_.bind(1, id);
  return first(get_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::newest_refit_until(
    std::string_view sat_id, int64_t until_utime) {
  auto use = refits_.use();
  refits_.bind(1, sat_id).bind(2, until_utime);
  return first(refits_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::latest_accepted_refit(
    std::string_view sat_id, int64_t min_window_span_utime, int min_samples) {
  auto use = accepted_refit_.use();
  accepted_refit_.bind(1, sat_id).bind(2, min_window_span_utime).bind(3, int64_t{min_samples});
  return first(accepted_refit_);
}

std::vector<std::string> SqliteCalibrationHistory::spacecraft() {
  std::vector<std::string> out;
  auto use = spacecraft_.use();
  while (spacecraft_.step()) out.push_back(spacecraft_.column_text(0));
  return out;
}

}  // namespace magcal::storage
