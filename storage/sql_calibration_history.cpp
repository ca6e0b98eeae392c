#include "storage/sql_calibration_history.hpp"

#include <algorithm>
#include <limits>

#include "storage/calibration_row.hpp"

namespace magcal::storage {
namespace {

// The INSERT of one record, returning its id.
std::string insert_sql() {
  std::string sql =
      std::string("INSERT INTO calibrations (") + calibration_row::kInsertColumns + ") VALUES (";
  for (int i = 1; i <= calibration_row::kInsertValues; ++i) {
    sql += (i > 1 ? ", ?" : "?") + std::to_string(i);
  }
  return sql + ") RETURNING id";
}

const std::string kRefitFilter =
    std::string("WHERE sat_id = ?1 AND ") + calibration_row::kRefitMethods;

}  // namespace

SqlCalibrationHistory::SqlCalibrationHistory(SqlSession& db)
    : insert_(db.prepare(insert_sql())),
      query_all_(db.prepare(calibration_row::select_sql(
          "WHERE sat_id = ?1 AND utime >= ?2 AND utime <= ?3 ORDER BY utime DESC, id DESC "
          "LIMIT ?4"))),
      query_method_(db.prepare(calibration_row::select_sql(
          "WHERE sat_id = ?1 AND utime >= ?2 AND utime <= ?3 AND method = ?5 ORDER BY utime "
          "DESC, id DESC LIMIT ?4"))),
      latest_(db.prepare(calibration_row::select_sql(
          "WHERE sat_id = ?1 AND method = ?2 ORDER BY utime DESC, id DESC LIMIT 1"))),
      get_(db.prepare(calibration_row::select_sql("WHERE id = ?1"))),
      refits_(db.prepare(calibration_row::select_sql(
          kRefitFilter + " AND utime <= ?2 ORDER BY utime DESC, id DESC LIMIT 1"))),
      accepted_refit_(db.prepare(calibration_row::select_sql(
          kRefitFilter +
          " AND verdict = 'accepted' AND window_end_utime - window_start_utime >= ?2 AND "
          "n_samples >= ?3 ORDER BY utime DESC, id DESC LIMIT 1"))),
      spacecraft_(db.prepare("SELECT DISTINCT sat_id FROM calibrations ORDER BY sat_id")),
      reasons_(db.prepare(db.json_array_texts())) {}

int64_t SqlCalibrationHistory::append(const CalibrationRecord& r) {
  calibration_row::check_appendable(r);
  const std::string reasons_json = calibration_row::json_string_array(r.rejection_reasons);
  SqlRun run(*insert_);
  calibration_row::write(r, reasons_json, *insert_);
  return run.single_integer().value();  // RETURNING id
}

std::vector<std::string> SqlCalibrationHistory::reasons(const std::string& json) {
  if (json == "[]") return {};  // nearly every row: no statement
  return SqlRun(*reasons_, json).all<std::string>([](const SqlRow& row) { return row.text(0); });
}

CalibrationRecord SqlCalibrationHistory::read_row(const SqlRow& row) {
  return calibration_row::read(row, [this](const std::string& json) { return reasons(json); });
}

std::vector<CalibrationRecord> SqlCalibrationHistory::query(const HistoryQuery& q) {
  SqlStatement& st = q.method.empty() ? *query_all_ : *query_method_;
  const auto read = [this](const SqlRow& row) { return read_row(row); };
  // No limit: the largest (LIMIT -1 and LIMIT NULL each mean none in one dialect only).
  const int64_t limit =
      q.limit ? static_cast<int64_t>(*q.limit) : std::numeric_limits<int64_t>::max();
  const int64_t since = q.since_utime.value_or(std::numeric_limits<int64_t>::min());
  const int64_t until = q.until_utime.value_or(std::numeric_limits<int64_t>::max());
  // Selected newest first (so LIMIT keeps the newest); printed in the asked order.
  std::vector<CalibrationRecord> out =
      q.method.empty()
          ? SqlRun(st, q.sat_id, since, until, limit).all<CalibrationRecord>(read)
          : SqlRun(st, q.sat_id, since, until, limit, q.method).all<CalibrationRecord>(read);
  if (!q.descending) std::reverse(out.begin(), out.end());
  return out;
}

std::optional<CalibrationRecord> SqlCalibrationHistory::latest(std::string_view sat_id,
                                                               std::string_view method) {
  return SqlRun(*latest_, sat_id, method).first<CalibrationRecord>([this](const SqlRow& row) {
    return read_row(row);
  });
}

std::optional<CalibrationRecord> SqlCalibrationHistory::get(int64_t id) {
  return SqlRun(*get_, id).first<CalibrationRecord>(
      [this](const SqlRow& row) { return read_row(row); });
}

std::optional<CalibrationRecord> SqlCalibrationHistory::newest_refit_until(std::string_view sat_id,
                                                                           int64_t until_utime) {
  return SqlRun(*refits_, sat_id, until_utime).first<CalibrationRecord>([this](const SqlRow& row) {
    return read_row(row);
  });
}

std::optional<CalibrationRecord> SqlCalibrationHistory::latest_accepted_refit(
    std::string_view sat_id, int64_t min_window_span_utime, int min_samples) {
  return SqlRun(*accepted_refit_, sat_id, min_window_span_utime, min_samples)
      .first<CalibrationRecord>([this](const SqlRow& row) { return read_row(row); });
}

std::vector<std::string> SqlCalibrationHistory::spacecraft() {
  return SqlRun(*spacecraft_).all<std::string>([](const SqlRow& row) { return row.text(0); });
}

}  // namespace magcal::storage
