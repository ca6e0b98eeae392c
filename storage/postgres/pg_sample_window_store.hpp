// The PostgreSQL SampleWindowStore (storage/sample_window_store.hpp) on one PgDatabase, made by
// PgDatabase::make_sample_window_store(). Statements are prepared once per connection
// (PgDatabase::execute_prepared); numbers travel in binary.
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
#include <utility>
#include <vector>

#include "storage/postgres/pg_database.hpp"
#include "storage/sql_sample_window_store.hpp"

namespace magcal::storage {

class PgSampleWindowStore final : public SqlSampleWindowStore {
 public:
  // Rows per INSERT statement (for_each_power_of_two_run): 20 parameters each, well below
  // PostgreSQL's 65 535.
  static constexpr size_t kMaxRowsPerInsert = 512;

  explicit PgSampleWindowStore(PgDatabase& db);

  void read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                   std::vector<StoredSample>& out) override;
  void read_windows(std::span<const WindowRequest> requests, std::vector<StoredSample>& out,
                    std::vector<size_t>& ends) override;

 private:
  void insert_rows(std::span<const StoredSample> samples, std::vector<size_t>* duplicate_rows,
                   std::string_view station, InsertStats& stats) override;
  int64_t delete_chunk(std::string_view sat_id, int64_t cutoff_utime, int chunk_rows) override;

  PgDatabase& pg_;
  std::vector<std::string> insert_sql_;  // [k]: the INSERT of 2^k rows
  PgParams params_;                      // reused: no allocation per batch once warmed up
  std::vector<size_t> order_;            // batch rows in key order
  std::vector<std::pair<std::string, int64_t>> stored_keys_;  // what RETURNING reported
  std::vector<std::string> request_sats_;                     // read_windows' arrays, reused
  std::vector<int64_t> request_t0s_, request_t1s_;
};

}  // namespace magcal::storage
