// The RefitJobLog (storage/refit_job_log.hpp) of both backends, written once on their SqlSession
// (storage/sql_statement.hpp): statements prepared once, rows read by RefitJobRow. Made by
// Connection::make_refit_job_log(); tests and tools that hold a database may construct it.
#pragma once

#include <memory>

#include "storage/refit_job_log.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlRefitJobLog final : public RefitJobLog {
 public:
  explicit SqlRefitJobLog(SqlSession& db);  // prepares its statements; throws StorageError

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
  std::unique_ptr<SqlStatement> start_, claim_, claim_holder_, finish_, interrupt_station_,
      interrupt_spacecraft_, newest_reanchor_, newest_scheduled_, get_, recent_;
};

}  // namespace magcal::storage
