// The PostgreSQL calibration history: the statements of both backends
// (storage/sql_calibration_history.hpp; bigint times and ids, double precision values and bytea
// blobs of little-endian doubles, read in binary: bit-exact), and append_all() inserting many
// records per statement. Made by PgDatabase::make_calibration_history().
#pragma once

#include <span>
#include <string>
#include <vector>

#include "storage/postgres/pg_database.hpp"
#include "storage/sql_calibration_history.hpp"

namespace magcal::storage {

class PgCalibrationHistory final : public SqlCalibrationHistory {
 public:
  explicit PgCalibrationHistory(PgDatabase& db) : SqlCalibrationHistory(db), db_(db) {}

  // Statements of up to 2^kMaxLog2RowsPerInsert rows (61 parameters each).
  void append_all(std::span<const CalibrationRecord> records) override;
  static constexpr size_t kMaxLog2RowsPerInsert = 6;

 private:
  PgDatabase& db_;
  PgParams params_;                        // reused
  std::vector<std::string> reasons_json_;  // kept alive while bound
};

}  // namespace magcal::storage
