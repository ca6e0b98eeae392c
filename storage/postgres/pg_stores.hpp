// The PostgreSQL implementations of the stores (storage/sample_window_store.hpp,
// refit_job_log.hpp, filter_state_store.hpp, meta_store.hpp, lease_store.hpp) on one PgDatabase,
// made by PgDatabase::make_*(). Statements are prepared once per connection (PgDatabase::
// execute_prepared); numbers travel in binary.
//
// Samples are inserted sorted by the table's key (sat_id, utime), the one global order every
// writer keeps: concurrent writers of overlapping batches then wait for each other instead of
// deadlocking (toolchain.md "PostgreSQL"). Each batch is one transaction of multi-row
// INSERT ... ON CONFLICT DO NOTHING RETURNING the stored keys, so a duplicate (already stored, by
// this daemon or another station, or twice in the batch) is counted, never an error. (One
// INSERT ... SELECT FROM unnest(binary column arrays) for any batch size was measured 15 %
// slower: the server materialises each unnested array before inserting.)
#pragma once

#include <span>
#include <string>
#include <vector>

#include "storage/filter_state_store.hpp"
#include "storage/lease_store.hpp"
#include "storage/meta_store.hpp"
#include "storage/postgres/pg_database.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal::storage {

class PgSampleWindowStore final : public SampleWindowStore {
 public:
  // Rows per INSERT statement (for_each_power_of_two_run): 20 parameters each, well below
  // PostgreSQL's 65 535.
  static constexpr size_t kMaxRowsPerInsert = 512;

  explicit PgSampleWindowStore(PgDatabase& db);

  InsertStats insert_batch(std::span<const StoredSample> samples,
                           std::vector<size_t>* duplicate_rows = nullptr,
                           std::string_view station = {}) override;
  void read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                   std::vector<StoredSample>& out) override;
  void read_windows(std::span<const WindowRequest> requests, std::vector<StoredSample>& out,
                    std::vector<size_t>& ends) override;
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
  std::optional<int64_t> single_utime(const char* sql, std::string_view sat_id);

  PgDatabase& pg_;
  std::vector<std::string> insert_sql_;  // [k]: the INSERT of 2^k rows
  PgParams params_;                      // reused: no allocation per batch once warmed up
  std::vector<size_t> order_;            // batch rows in key order
  std::vector<std::pair<std::string, int64_t>> stored_keys_;  // what RETURNING reported
  std::vector<std::string> request_sats_;                     // read_windows' arrays, reused
  std::vector<int64_t> request_t0s_, request_t1s_;
};

class PgRefitJobLog final : public RefitJobLog {
 public:
  explicit PgRefitJobLog(PgDatabase& db) : db_(db) {}

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
  PgDatabase& db_;
};

class PgFilterStateStore final : public FilterStateStore {
 public:
  explicit PgFilterStateStore(PgDatabase& db) : db_(db) {}

  void save(const FilterState& state) override;
  // Statements of up to 2^kMaxLog2RowsPerUpsert states, in key order.
  void save_all(std::span<const FilterState> states) override;
  std::optional<FilterState> load(std::string_view sat_id, std::string_view method) override;
  std::vector<FilterState> load_all() override;
  static constexpr size_t kMaxLog2RowsPerUpsert = 6;

 private:
  PgDatabase& db_;
  PgParams params_;  // save_all's, reused
};

class PgLeaseStore final : public LeaseStore {
 public:
  explicit PgLeaseStore(PgDatabase& db) : db_(db) {}

  std::optional<Lease> try_acquire(std::string_view sat_id, std::string_view owner,
                                   int64_t now_utime, int64_t ttl_utime) override;
  std::optional<Lease> reclaim(std::string_view sat_id, std::string_view owner, int64_t epoch,
                               int64_t now_utime, int64_t ttl_utime) override;
  bool renew(std::string_view sat_id, std::string_view owner, int64_t epoch, int64_t now_utime,
             int64_t ttl_utime) override;
  bool release(std::string_view sat_id, std::string_view owner, int64_t epoch,
               int64_t now_utime) override;
  bool holds(std::string_view sat_id, std::string_view owner, int64_t epoch) override;
  std::vector<std::string> not_held(std::string_view owner, std::span<const Held> leases) override;
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
  PgDatabase& db_;
};

class PgMetaStore final : public MetaStore {
 public:
  explicit PgMetaStore(PgDatabase& db) : db_(db) {}
  void set(std::string_view key, std::string_view value) override;
  std::optional<std::string> get(std::string_view key) override;

 private:
  PgDatabase& db_;
};

}  // namespace magcal::storage
