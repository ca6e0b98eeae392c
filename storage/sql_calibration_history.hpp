// The CalibrationHistory (storage/calibration_history.hpp) of both backends, written once on
// their SqlSession (storage/sql_statement.hpp): rows written and read by calibration_row.
// PostgreSQL's appends many records per statement (storage/postgres/pg_calibration_history.hpp).
// Made by Connection::make_calibration_history(); tests and tools that hold a database may
// construct it.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "storage/calibration_history.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlCalibrationHistory : public CalibrationHistory {
 public:
  explicit SqlCalibrationHistory(SqlSession& db);  // prepares its statements; throws StorageError

  int64_t append(const CalibrationRecord& record) override;
  std::vector<CalibrationRecord> query(const HistoryQuery& q) override;
  std::optional<CalibrationRecord> latest(std::string_view sat_id,
                                          std::string_view method) override;
  std::optional<CalibrationRecord> get(int64_t id) override;
  using CalibrationHistory::latest_accepted_refit;
  std::optional<CalibrationRecord> latest_accepted_refit(std::string_view sat_id,
                                                         int64_t min_window_span_utime,
                                                         int min_samples) override;
  std::vector<std::string> spacecraft() override;

 private:
  std::optional<CalibrationRecord> newest_refit_until(std::string_view sat_id,
                                                      int64_t until_utime) override;
  CalibrationRecord read_row(const SqlRow& row);
  std::vector<std::string> reasons(const std::string& json);

  std::unique_ptr<SqlStatement> insert_, query_all_, query_method_, latest_, get_, refits_,
      accepted_refit_, spacecraft_, reasons_;
};

}  // namespace magcal::storage
