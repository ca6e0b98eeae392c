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

}  // namespace

SqliteSampleWindowStore::SqliteSampleWindowStore(Database& db)
    : SqlSampleWindowStore(db, db),
      insert_(db, insert_sql()),
      window_(db, sample_sql::window()),
      // DELETE ... LIMIT needs a compile option Debian's SQLite may lack: select the chunk.
      delete_chunk_(db,
                    "DELETE FROM samples WHERE sat_id = ?1 AND utime IN (SELECT utime FROM "
                    "samples WHERE sat_id = ?1 AND utime < ?2 ORDER BY utime LIMIT ?3)") {}

void SqliteSampleWindowStore::insert_rows(std::span<const StoredSample> samples,
                                          std::vector<size_t>* duplicate_rows,
                                          std::string_view station, InsertStats& stats) {
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
}

void SqliteSampleWindowStore::read_window(std::string_view sat_id, int64_t t0_utime,
                                          int64_t t1_utime, std::vector<StoredSample>& out) {
  out.clear();
  auto use = window_.use();
  window_.bind(1, sat_id).bind(2, t0_utime).bind(3, t1_utime);
  const SqliteRow row{window_};
  while (window_.step()) sample_row::read(row, 0, sat_id, out.emplace_back());
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
