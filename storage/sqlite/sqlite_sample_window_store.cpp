#include "storage/sqlite/sqlite_sample_window_store.hpp"

#include "storage/sample_row.hpp"
#include "storage/sample_sql.hpp"
#include "storage/sqlite/sqlite_row.hpp"

namespace magcal::storage {
namespace {

std::string insert_sql() {
  std::string sql = "INSERT INTO samples (" + sample_row::insert_columns() + ") VALUES (";
  const int values = sample_row::column_count(true) + 1;  // and the station
  for (int i = 1; i <= values; ++i) sql += (i > 1 ? ", ?" : "?") + std::to_string(i);
  // Only a repeated key is ignored (and counted); OR IGNORE would also swallow NOT NULL
  // violations (NaN is bound as NULL) and count them as duplicates.
  return sql + ") " + sample_sql::kIgnoreDuplicate;
}

// The one value of `st` (a min/max over sat_id = ?1); nullopt when NULL (no rows).
std::optional<int64_t> single_utime(Statement& st, std::string_view sat_id) {
  auto use = st.use();
  st.bind(1, sat_id);
  if (!st.step() || st.is_null(0)) return std::nullopt;
  return st.column_int64(0);
}

}  // namespace

SqliteSampleWindowStore::SqliteSampleWindowStore(Database& db)
    : SampleWindowStore(db),
      insert_(db, insert_sql()),
      window_(db, sample_sql::window()),
      count_window_(db, sample_sql::kCountInWindow),
      count_by_station_(db, sample_sql::count_by_station("")),
      newest_(db, sample_sql::kNewest),
      oldest_(db, sample_sql::kOldest),
      count_(db, sample_sql::kCount),
      utime_at_rank_(db, sample_sql::kUtimeAtRank),
      spacecraft_(db, sample_sql::kSpacecraft),
      // DELETE ... LIMIT needs a compile option Debian's SQLite may lack: select the chunk.
      delete_chunk_(db,
                    "DELETE FROM samples WHERE sat_id = ?1 AND utime IN (SELECT utime FROM "
                    "samples WHERE sat_id = ?1 AND utime < ?2 ORDER BY utime LIMIT ?3)") {}

InsertStats SqliteSampleWindowStore::insert_batch(std::span<const StoredSample> samples,
                                                  std::vector<size_t>* duplicate_rows,
                                                  std::string_view station) {
  InsertStats stats;
  if (duplicate_rows) duplicate_rows->clear();
  if (samples.empty()) return stats;
  Transaction tx(db_);
  for (size_t row = 0; row < samples.size(); ++row) {
    auto use = insert_.use();
    // The batch and the station outlive this row's use of the statement: bound without a copy.
    SqliteBinder binder{insert_, 1, true};
    sample_row::write(samples[row], binder);
    if (!station.empty()) binder.text(station);
    if (insert_.execute() == 1) {
      ++stats.inserted;
    } else {
      ++stats.duplicates;
      if (duplicate_rows) duplicate_rows->push_back(row);
    }
  }
  tx.commit();
  return stats;
}

void SqliteSampleWindowStore::read_window(std::string_view sat_id, int64_t t0_utime,
                                          int64_t t1_utime, std::vector<StoredSample>& out) {
  out.clear();
  auto use = window_.use();
  window_.bind(1, sat_id).bind(2, t0_utime).bind(3, t1_utime);
  const SqliteRow row{window_};
  while (window_.step()) sample_row::read(row, 0, sat_id, out.emplace_back());
}

int64_t SqliteSampleWindowStore::count_in_window(std::string_view sat_id, int64_t t0_utime,
                                                 int64_t t1_utime) {
  auto use = count_window_.use();
  count_window_.bind(1, sat_id).bind(2, t0_utime).bind(3, t1_utime);
  return count_window_.step() ? count_window_.column_int64(0) : 0;
}

std::vector<StationCount> SqliteSampleWindowStore::count_by_station(std::string_view sat_id,
                                                                    int64_t t0_utime,
                                                                    int64_t t1_utime) {
  std::vector<StationCount> out;
  auto use = count_by_station_.use();
  count_by_station_.bind(1, sat_id).bind(2, t0_utime).bind(3, t1_utime);
  while (count_by_station_.step()) {
    out.push_back({count_by_station_.column_text(0), count_by_station_.column_int64(1)});
  }
  return out;
}

std::optional<int64_t> SqliteSampleWindowStore::newest_utime(std::string_view sat_id) {
  return single_utime(newest_, sat_id);
}

std::optional<int64_t> SqliteSampleWindowStore::oldest_utime(std::string_view sat_id) {
  return single_utime(oldest_, sat_id);
}

int64_t SqliteSampleWindowStore::count(std::string_view sat_id) {
  auto use = count_.use();
  count_.bind(1, sat_id);
  return count_.step() ? count_.column_int64(0) : 0;
}

std::optional<int64_t> SqliteSampleWindowStore::utime_at_rank(std::string_view sat_id,
                                                              int64_t rank) {
  if (rank < 0) return std::nullopt;
  auto use = utime_at_rank_.use();
  utime_at_rank_.bind(1, sat_id).bind(2, rank);
  if (!utime_at_rank_.step()) return std::nullopt;
  return utime_at_rank_.column_int64(0);
}

std::vector<std::string> SqliteSampleWindowStore::spacecraft() {
  std::vector<std::string> out;
  auto use = spacecraft_.use();
  while (spacecraft_.step()) out.push_back(spacecraft_.column_text(0));
  return out;
}

int64_t SqliteSampleWindowStore::delete_chunk(std::string_view sat_id, int64_t cutoff_utime,
                                              int chunk_rows) {
  Transaction tx(db_);
  int64_t deleted = 0;
  {
    auto use = delete_chunk_.use();
    delete_chunk_.bind(1, sat_id).bind(2, cutoff_utime).bind(3, chunk_rows);
    deleted = delete_chunk_.execute();
  }
  tx.commit();
  return deleted;
}

}  // namespace magcal::storage
