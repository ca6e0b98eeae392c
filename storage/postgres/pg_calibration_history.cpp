#include "storage/postgres/pg_calibration_history.hpp"

#include "storage/calibration_row.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {

void PgCalibrationHistory::append_all(std::span<const CalibrationRecord> records) {
  // [k]: the INSERT of 2^k records.
  static const std::vector<std::string> sql = [] {
    std::vector<std::string> out;
    for (size_t k = 0; k <= kMaxLog2RowsPerInsert; ++k) {
      out.push_back(multi_row_values_sql(
          std::string("INSERT INTO calibrations (") + calibration_row::kInsertColumns + ") VALUES ",
          size_t{1} << k, calibration_row::kInsertValues, 1, "", ""));
    }
    return out;
  }();
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
    db_.execute_prepared(sql[k], params_);
  });
}

}  // namespace magcal::storage
