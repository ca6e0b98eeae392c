// The SQLite SampleWindowStore (storage/sample_window_store.hpp) on one Database: statements
// prepared once in the constructor, reset and re-bound for every use. Made by Database::make_*();
// tests and tools that hold a Database may construct it directly.
#pragma once

#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

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

}  // namespace magcal::storage
