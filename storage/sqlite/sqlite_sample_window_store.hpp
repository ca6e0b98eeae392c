// The SQLite SampleWindowStore (storage/sample_window_store.hpp) on one Database: a row per
// statement in one transaction (an SQLite statement costs no round trip), the window read by
// the sample codec without a NULL test per NOT NULL column. Made by
// Database::make_sample_window_store(); tests and tools that hold a Database may construct it.
#pragma once

#include "storage/sql_sample_window_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteSampleWindowStore final : public SqlSampleWindowStore {
 public:
  explicit SqliteSampleWindowStore(Database& db);  // prepares its statements; throws StorageError

  void read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                   std::vector<StoredSample>& out) override;

 private:
  void insert_rows(std::span<const StoredSample> samples, std::vector<size_t>* duplicate_rows,
                   std::string_view station, InsertStats& stats) override;
  int64_t delete_chunk(std::string_view sat_id, int64_t cutoff_utime, int chunk_rows) override;

  Statement insert_;
  Statement window_;
  Statement delete_chunk_;
};

}  // namespace magcal::storage
