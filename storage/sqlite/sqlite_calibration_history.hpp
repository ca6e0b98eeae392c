// The SQLite CalibrationHistory (storage/calibration_history.hpp) on one Database: statements
// prepared once in the constructor, reset and re-bound for every use. Made by Database::make_*();
// tests and tools that hold a Database may construct it directly.
#pragma once

#include "storage/calibration_history.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteCalibrationHistory final : public CalibrationHistory {
 public:
  explicit SqliteCalibrationHistory(Database& db);

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
  static std::string insert_sql();
  CalibrationRecord read_row(Statement& st);
  std::vector<CalibrationRecord> rows(Statement& st);
  std::optional<CalibrationRecord> first(Statement& st);

  Database& db_;
  Statement insert_;
  Statement query_all_;
  Statement query_method_;
  Statement latest_;
  Statement get_;
  Statement refits_;
  Statement accepted_refit_;
  Statement spacecraft_;
  Statement reasons_;
};

}  // namespace magcal::storage
