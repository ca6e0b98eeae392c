#include "storage/postgres/pg_calibration_history.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "storage/calibration_row.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {
namespace {

// The INSERT of `rows` records.
std::string insert_sql(size_t rows, std::string_view tail = {}) {
  return multi_row_values_sql(
      std::string("INSERT INTO calibrations (") + calibration_row::kInsertColumns + ") VALUES ",
      rows, calibration_row::kInsertValues, 1, "", tail);
}

// [k]: the INSERT of 2^k records.
const std::vector<std::string>& insert_all_sql() {
  static const std::vector<std::string> sql = [] {
    std::vector<std::string> out;
    for (size_t k = 0; k <= PgCalibrationHistory::kMaxLog2RowsPerInsert; ++k) {
      out.push_back(insert_sql(size_t{1} << k));
    }
    return out;
  }();
  return sql;
}

const std::string kRefitFilter =
    std::string("WHERE sat_id = $1 AND ") + calibration_row::kRefitMethods;

}  // namespace

int64_t PgCalibrationHistory::append(const CalibrationRecord& r) {
  calibration_row::check_appendable(r);
  const std::string reasons_json = calibration_row::json_string_array(r.rejection_reasons);
  params_.clear();
  PgBinder binder{params_};
  calibration_row::write(r, reasons_json, binder);
  static const std::string sql = insert_sql(1, " RETURNING id");
  return db_.execute_prepared(sql, params_, PgFormat::kBinary).get_int64(0, 0);
}

void PgCalibrationHistory::append_all(std::span<const CalibrationRecord> records) {
  reasons_json_.clear();
  for (const CalibrationRecord& r : records) {
    calibration_row::check_appendable(r);
    reasons_json_.push_back(calibration_row::json_string_array(r.rejection_reasons));
  }
  for_each_power_of_two_run(records.size(), kMaxLog2RowsPerInsert, [&](size_t begin, size_t k) {
    params_.clear();
    PgBinder binder{params_};
    for (size_t i = begin; i < begin + (size_t{1} << k); ++i) {
      calibration_row::write(records[i], reasons_json_[i], binder);
    }
    db_.execute_prepared(insert_all_sql()[k], params_);
  });
}

std::vector<std::string> PgCalibrationHistory::reasons(const std::string& json) {
  std::vector<std::string> out;
  if (json == "[]") return out;  // nearly every row: no round trip
  PgParams p;
  p.add(json);
  const PgResult r = db_.execute_prepared("SELECT json_array_elements_text($1::json)", p);
  for (int row = 0; row < r.rows(); ++row) out.push_back(r.get_text(row, 0));
  return out;
}

std::vector<CalibrationRecord> PgCalibrationHistory::rows(const std::string& sql,
                                                          const PgParams& params) {
  const PgResult r = db_.execute_prepared(sql, params, PgFormat::kBinary);
  std::vector<CalibrationRecord> out;
  out.reserve(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) {
    PgRow access{r, row};
    out.push_back(
        calibration_row::read(access, [this](const std::string& json) { return reasons(json); }));
  }
  return out;
}

std::vector<CalibrationRecord> PgCalibrationHistory::query(const HistoryQuery& q) {
  PgParams p;
  p.add(q.sat_id);
  p.add(q.since_utime.value_or(std::numeric_limits<int64_t>::min()));
  p.add(q.until_utime.value_or(std::numeric_limits<int64_t>::max()));
  // LIMIT NULL: no limit.
  p.add(q.limit ? std::optional<int64_t>(*q.limit) : std::nullopt);
  if (!q.method.empty()) p.add(q.method);
  // Selected newest first (so LIMIT keeps the newest); printed in the asked order.
  std::vector<CalibrationRecord> out =
      rows(calibration_row::select_sql(std::string("WHERE sat_id = $1 AND utime >= $2 AND "
                                                   "utime <= $3") +
                                       (q.method.empty() ? "" : " AND method = $5") +
                                       " ORDER BY utime DESC, id DESC LIMIT $4"),
           p);
  if (!q.descending) std::reverse(out.begin(), out.end());
  return out;
}

std::optional<CalibrationRecord> PgCalibrationHistory::latest(std::string_view sat_id,
                                                              std::string_view method) {
  PgParams p;
  p.add(sat_id).add(method);
  auto found = rows(calibration_row::select_sql(
                        "WHERE sat_id = $1 AND method = $2 ORDER BY utime DESC, id DESC LIMIT 1"),
                    p);
  if (found.empty()) return std::nullopt;
  return std::move(found.front());
}

std::optional<CalibrationRecord> PgCalibrationHistory::get(int64_t id) {
  PgParams p;
  p.add(id);
  auto found = rows(calibration_row::select_sql("WHERE id = $1"), p);
  if (found.empty()) return std::nullopt;
  return std::move(found.front());
}

std::optional<CalibrationRecord> PgCalibrationHistory::newest_refit_until(std::string_view sat_id,
                                                                          int64_t until_utime) {
  PgParams p;
  p.add(sat_id).add(until_utime);
  auto found = rows(calibration_row::select_sql(
                        kRefitFilter + " AND utime <= $2 ORDER BY utime DESC, id DESC LIMIT 1"),
                    p);
  if (found.empty()) return std::nullopt;
  return std::move(found.front());
}

std::optional<CalibrationRecord> PgCalibrationHistory::latest_accepted_refit(
    std::string_view sat_id, int64_t min_window_span_utime, int min_samples) {
  PgParams p;
  p.add(sat_id).add(min_window_span_utime).add(int64_t{min_samples});
  auto found = rows(
      calibration_row::select_sql(
          kRefitFilter + " AND verdict = 'accepted' AND window_end_utime - window_start_utime >= "
                         "$2 AND n_samples >= $3 ORDER BY utime DESC, id DESC LIMIT 1"),
      p);
  if (found.empty()) return std::nullopt;
  return std::move(found.front());
}

std::vector<std::string> PgCalibrationHistory::spacecraft() {
  const PgResult r =
      db_.execute_prepared("SELECT DISTINCT sat_id FROM calibrations ORDER BY sat_id");
  std::vector<std::string> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(r.get_text(row, 0));
  return out;
}

}  // namespace magcal::storage
