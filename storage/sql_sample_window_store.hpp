// What the SampleWindowStore (storage/sample_window_store.hpp) of both backends shares, written
// once on their SqlSession (storage/sql_statement.hpp): the counts and the key lookups. Each
// backend writes and reads the rows its own fastest way (storage/sqlite/
// sqlite_sample_window_store.hpp, storage/postgres/pg_sample_window_store.hpp).
#pragma once

#include <memory>

#include "storage/sample_window_store.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlSampleWindowStore : public SampleWindowStore {
 public:
  // The batch's accounting (duplicate_rows cleared, nothing to do for no rows), then
  // insert_rows().
  InsertStats insert_batch(std::span<const StoredSample> samples,
                           std::vector<size_t>* duplicate_rows = nullptr,
                           std::string_view station = {}) final;
  int64_t count_in_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime) override;
  std::vector<StationCount> count_by_station(std::string_view sat_id, int64_t t0_utime,
                                             int64_t t1_utime) override;
  std::optional<int64_t> newest_utime(std::string_view sat_id) override;
  std::optional<int64_t> oldest_utime(std::string_view sat_id) override;
  int64_t count(std::string_view sat_id) override;
  std::optional<int64_t> utime_at_rank(std::string_view sat_id, int64_t rank) override;
  std::vector<std::string> spacecraft() override;

 protected:
  // `db` and `sql`: one database (a backend's connection is both).
  SqlSampleWindowStore(Connection& db, SqlSession& sql);
  // insert_batch of at least one row, duplicate_rows already cleared: counts into `stats`.
  virtual void insert_rows(std::span<const StoredSample> samples,
                           std::vector<size_t>* duplicate_rows, std::string_view station,
                           InsertStats& stats) = 0;

 private:
  std::unique_ptr<SqlStatement> count_window_, count_by_station_, newest_, oldest_, count_,
      utime_at_rank_, spacecraft_;
};

}  // namespace magcal::storage
