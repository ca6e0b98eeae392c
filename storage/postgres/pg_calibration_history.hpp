// The PostgreSQL implementation of the calibration history (storage/calibration_history.hpp) on
// one PgDatabase, made by PgDatabase::make_calibration_history(): the same columns and NULL
// rules as SQLite's (storage/calibration_row.hpp), bigint times and ids, double precision values
// and bytea blobs of little-endian doubles, read in binary (bit-exact).
#pragma once

#include <string>
#include <vector>

#include "storage/calibration_history.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

class PgCalibrationHistory final : public CalibrationHistory {
 public:
  explicit PgCalibrationHistory(PgDatabase& db) : db_(db) {}

  int64_t append(const CalibrationRecord& record) override;
  // Statements of up to 2^kMaxLog2RowsPerInsert rows (55 parameters each).
  void append_all(std::span<const CalibrationRecord> records) override;
  static constexpr size_t kMaxLog2RowsPerInsert = 6;
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
  // The rows of a calibration_row::select_sql() statement.
  std::vector<CalibrationRecord> rows(const std::string& sql, const PgParams& params);
  std::vector<std::string> reasons(const std::string& json);

  PgDatabase& db_;
  PgParams params_;                        // append's, reused
  std::vector<std::string> reasons_json_;  // append_all's, kept alive while bound
};

}  // namespace magcal::storage
