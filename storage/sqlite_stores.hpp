// The SQLite implementations of the stores (storage/sample_window_store.hpp, refit_job_log.hpp,
// filter_state_store.hpp, meta_store.hpp, calibration_history.hpp, lease_store.hpp) on one
// Database: statements prepared once in the constructor, reset and re-bound for every use. Made by
// Database::make_*(); tests and tools that hold a Database may construct them directly.
#pragma once

#include <span>
#include <vector>

#include "storage/calibration_history.hpp"
#include "storage/database.hpp"
#include "storage/filter_state_store.hpp"
#include "storage/lease_store.hpp"
#include "storage/meta_store.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/statement.hpp"

namespace magcal::storage {

class SqliteSampleWindowStore final : public SampleWindowStore {
 public:
  explicit SqliteSampleWindowStore(Database& db);  // prepares its statements; throws StorageError

  InsertStats insert_batch(std::span<const StoredSample> samples,
                           std::vector<size_t>* duplicate_rows = nullptr,
                           std::string_view station = {}) override;
  void read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                   std::vector<StoredSample>& out) override;
  int64_t count_in_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime) override;
  std::vector<StationCount> count_by_station(std::string_view sat_id, int64_t t0_utime,
                                             int64_t t1_utime) override;
  std::optional<int64_t> newest_utime(std::string_view sat_id) override;
  std::optional<int64_t> oldest_utime(std::string_view sat_id) override;
  int64_t count(std::string_view sat_id) override;
  std::optional<int64_t> utime_at_rank(std::string_view sat_id, int64_t rank) override;
  std::vector<std::string> spacecraft() override;

 private:
  int64_t delete_chunk(std::string_view sat_id, int64_t cutoff_utime, int chunk_rows) override;

  Statement insert_;
  Statement window_;
  Statement count_window_;
  Statement count_by_station_;
  Statement newest_;
  Statement oldest_;
  Statement count_;
  Statement utime_at_rank_;
  Statement spacecraft_;
  Statement delete_chunk_;
};

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
  Database& db_;
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

class SqliteFilterStateStore final : public FilterStateStore {
 public:
  explicit SqliteFilterStateStore(Database& db);

  void save(const FilterState& state) override;
  std::optional<FilterState> load(std::string_view sat_id, std::string_view method) override;
  std::vector<FilterState> load_all() override;

 private:
  FilterState read_row(Statement& st);
  Statement upsert_;
  Statement load_;
  Statement load_all_;
};

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

class SqliteLeaseStore final : public LeaseStore {
 public:
  explicit SqliteLeaseStore(Database& db);

  std::optional<Lease> try_acquire(std::string_view sat_id, std::string_view owner,
                                   int64_t now_utime, int64_t ttl_utime) override;
  std::optional<Lease> reclaim(std::string_view sat_id, std::string_view owner, int64_t epoch,
                               int64_t now_utime, int64_t ttl_utime) override;
  bool renew(std::string_view sat_id, std::string_view owner, int64_t epoch, int64_t now_utime,
             int64_t ttl_utime) override;
  bool release(std::string_view sat_id, std::string_view owner, int64_t epoch,
               int64_t now_utime) override;
  bool holds(std::string_view sat_id, std::string_view owner, int64_t epoch) override;
  std::optional<Lease> get(std::string_view sat_id) override;
  std::vector<Lease> list() override;
  void ensure(std::string_view sat_id) override;
  std::vector<Lease> renew_all(std::string_view owner, int64_t now_utime,
                               int64_t ttl_utime) override;
  std::optional<StationBeat> heartbeat(std::string_view station, std::string_view instance,
                                       const StationSettings& settings, int64_t now_utime,
                                       int64_t ttl_utime) override;
  void leave(std::string_view station, int64_t now_utime) override;
  std::vector<std::string> live_stations(int64_t now_utime) override;
  std::vector<StationRow> stations() override;

 private:
  Statement acquire_;
  Statement renew_;
  Statement reclaim_;
  Statement release_;
  Statement holds_;
  Statement get_;
  Statement list_;
  Statement ensure_;
  Statement renew_all_;
  Statement heartbeat_;
  Statement beat_;
  Statement leave_;
  Statement live_;
  Statement stations_;
};

class SqliteMetaStore final : public MetaStore {
 public:
  explicit SqliteMetaStore(Database& db);
  void set(std::string_view key, std::string_view value) override;
  std::optional<std::string> get(std::string_view key) override;

 private:
  Statement set_;
  Statement get_;
};

}  // namespace magcal::storage
