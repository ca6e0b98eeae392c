// The SQLite RefitJobLog (storage/refit_job_log.hpp) on one Database: statements prepared once in
// the constructor, reset and re-bound for every use. Made by Database::make_*(); tests and tools
// that hold a Database may construct it directly.
#pragma once

#include "storage/refit_job_log.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteRefitJobLog final : public RefitJobLog {
 public:
  explicit SqliteRefitJobLog(Database& db);

  int64_t start(std::string_view sat_id, std::string_view trigger, int64_t scheduled_utime,
                int64_t started_utime) override;
  void finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
              std::string_view error = {}, std::optional<int64_t> calibration_id = {}) override;
  std::optional<int64_t> claim(std::string_view sat_id, std::string_view trigger,
                               int64_t scheduled_utime, int64_t started_utime,
                               std::string_view station) override;
  std::optional<RefitJob> claim_holder(std::string_view sat_id, std::string_view trigger,
                                       int64_t scheduled_utime) override;
  int mark_station_running_interrupted(std::string_view station, int64_t now_utime) override;
  int mark_running_interrupted(std::string_view sat_id, int64_t now_utime) override;
  std::optional<int64_t> newest_reanchor_calibration_id(std::string_view sat_id) override;
  std::optional<int64_t> newest_finished_scheduled_utime(std::string_view sat_id) override;
  std::optional<RefitJob> get(int64_t job_id) override;
  std::vector<RefitJob> recent(std::string_view sat_id, int limit) override;

 private:
  Statement insert_;
  Statement claim_;
  Statement claim_holder_;
  Statement finish_;
  Statement interrupt_;
  Statement interrupt_sat_;
  Statement get_;
  Statement recent_;
  Statement newest_reanchor_;
  Statement newest_scheduled_;
};

}  // namespace magcal::storage
