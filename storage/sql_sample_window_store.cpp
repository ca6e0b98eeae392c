#include "storage/sql_sample_window_store.hpp"

#include "storage/sample_sql.hpp"

namespace magcal::storage {

SqlSampleWindowStore::SqlSampleWindowStore(Connection& db, SqlSession& sql)
    : SampleWindowStore(db),
      count_window_(sql.prepare(sample_sql::kCountInWindow)),
      count_by_station_(sql.prepare(sample_sql::count_by_station(sql.byte_order()))),
      newest_(sql.prepare(sample_sql::kNewest)),
      oldest_(sql.prepare(sample_sql::kOldest)),
      count_(sql.prepare(sample_sql::kCount)),
      utime_at_rank_(sql.prepare(sample_sql::kUtimeAtRank)),
      spacecraft_(sql.prepare(sample_sql::kSpacecraft)) {}

InsertStats SqlSampleWindowStore::insert_batch(std::span<const StoredSample> samples,
                                               std::vector<size_t>* duplicate_rows,
                                               std::string_view station) {
  InsertStats stats;
  if (duplicate_rows) duplicate_rows->clear();
  if (!samples.empty()) insert_rows(samples, duplicate_rows, station, stats);
  return stats;
}

int64_t SqlSampleWindowStore::count_in_window(std::string_view sat_id, int64_t t0_utime,
                                              int64_t t1_utime) {
  return SqlRun(*count_window_, sat_id, t0_utime, t1_utime).single_integer().value_or(0);
}

std::vector<StationCount> SqlSampleWindowStore::count_by_station(std::string_view sat_id,
                                                                 int64_t t0_utime,
                                                                 int64_t t1_utime) {
  return SqlRun(*count_by_station_, sat_id, t0_utime, t1_utime)
      .all<StationCount>([](const SqlRow& row) {
        return StationCount{row.text(0), row.integer(1)};
      });
}

std::optional<int64_t> SqlSampleWindowStore::newest_utime(std::string_view sat_id) {
  return SqlRun(*newest_, sat_id).single_integer();
}

std::optional<int64_t> SqlSampleWindowStore::oldest_utime(std::string_view sat_id) {
  return SqlRun(*oldest_, sat_id).single_integer();
}

int64_t SqlSampleWindowStore::count(std::string_view sat_id) {
  return SqlRun(*count_, sat_id).single_integer().value_or(0);
}

std::optional<int64_t> SqlSampleWindowStore::utime_at_rank(std::string_view sat_id, int64_t rank) {
  if (rank < 0) return std::nullopt;
  return SqlRun(*utime_at_rank_, sat_id, rank).single_integer();
}

std::vector<std::string> SqlSampleWindowStore::spacecraft() {
  return SqlRun(*spacecraft_).all<std::string>([](const SqlRow& row) { return row.text(0); });
}

}  // namespace magcal::storage
