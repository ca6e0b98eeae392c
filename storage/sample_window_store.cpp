#include "storage/sample_window_store.hpp"

#include "storage/sqlite_stores.hpp"
#include "storage/store_columns.hpp"

#include <cmath>
#include <limits>

namespace magcal::storage {
namespace {

std::string select_window_sql() {
  return std::string("SELECT ") + columns::kSampleRead +
         " FROM samples WHERE sat_id = ?1 AND utime >= ?2 AND utime < ?3 ORDER BY utime";
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
      insert_(db, std::string("INSERT INTO samples (") + columns::kSampleInsert +
                      ") VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, "
                      "?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20, ?21) "
                      // Only a repeated key is ignored (and counted); OR IGNORE would also swallow
                      // NOT NULL violations (NaN is bound as NULL) and count them as duplicates.
                      "ON CONFLICT (sat_id, utime) DO NOTHING"),
      window_(db, select_window_sql()),
      count_window_(
          db, "SELECT count(*) FROM samples WHERE sat_id = ?1 AND utime >= ?2 AND utime < ?3"),
      count_by_station_(db,
                        "SELECT coalesce(station, '') AS s, count(*) FROM samples WHERE sat_id = "
                        "?1 AND utime >= ?2 AND utime < ?3 GROUP BY s ORDER BY s"),
      newest_(db, "SELECT max(utime) FROM samples WHERE sat_id = ?1"),
      oldest_(db, "SELECT min(utime) FROM samples WHERE sat_id = ?1"),
      count_(db, "SELECT count(*) FROM samples WHERE sat_id = ?1"),
      utime_at_rank_(
          db, "SELECT utime FROM samples WHERE sat_id = ?1 ORDER BY utime LIMIT 1 OFFSET ?2"),
      // Skip-scan over the primary key: one b-tree seek per spacecraft, not a full scan.
      spacecraft_(db,
                  "WITH RECURSIVE s(id) AS (SELECT min(sat_id) FROM samples UNION ALL "
                  "SELECT (SELECT min(sat_id) FROM samples WHERE sat_id > s.id) FROM s "
                  "WHERE s.id IS NOT NULL) SELECT id FROM s WHERE id IS NOT NULL"),
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
    const StoredSample& s = samples[row];
    auto use = insert_.use();
    // The batch and the station outlive this row's use of the statement: bound without a copy.
    insert_.bind_unowned(1, s.sat_id).bind(2, s.utime).bind(3, s.seq).bind(4, s.receive_utime);
    insert_.bind(5, s.b_sensor_nT[0]).bind(6, s.b_sensor_nT[1]).bind(7, s.b_sensor_nT[2]);
    insert_.bind(8, s.has_direction ? 1 : 0);
    if (s.has_direction) {
      insert_.bind(9, s.h_body_nT[0]).bind(10, s.h_body_nT[1]).bind(11, s.h_body_nT[2]);
    }
    insert_.bind(12, s.h_norm_nT);
    if (s.has_attitude) {
      for (int i = 0; i < 4; ++i) insert_.bind(13 + i, s.q_body_from_eci[i]);
    }
    if (s.has_position) {
      for (int i = 0; i < 3; ++i) insert_.bind(17 + i, s.r_ecef_m[i]);
    }
    insert_.bind(20, s.temperature_C);  // NaN -> NULL
    if (!station.empty()) insert_.bind_unowned(21, station);
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
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  // The hot loop (a 12 h window is 4320 rows): NOT NULL columns are read without a type check,
  // nullable groups are tested once per group.
  Statement& st = window_;
  while (st.step()) {
    StoredSample& s = out.emplace_back();
    s.sat_id = sat_id;
    s.utime = st.column_int64(0);
    s.seq = st.column_int64(1);
    s.receive_utime = st.column_int64(2);
    for (int i = 0; i < 3; ++i) s.b_sensor_nT[i] = st.column_double_not_null(3 + i);
    s.has_direction = st.column_int64(6) != 0;
    for (int i = 0; i < 3; ++i) {
      s.h_body_nT[i] = s.has_direction ? st.column_double_not_null(7 + i) : kNaN;
    }
    s.h_norm_nT = st.column_double_not_null(10);
    s.has_attitude = !st.is_null(11);
    if (s.has_attitude) {
      for (int i = 0; i < 4; ++i) s.q_body_from_eci[i] = st.column_double_not_null(11 + i);
    }
    s.has_position = !st.is_null(15);
    if (s.has_position) {
      for (int i = 0; i < 3; ++i) s.r_ecef_m[i] = st.column_double_not_null(15 + i);
    }
    s.temperature_C = st.column_double(18);
  }
}

std::vector<StoredSample> SampleWindowStore::window(std::string_view sat_id, int64_t t0_utime,
                                                    int64_t t1_utime) {
  std::vector<StoredSample> out;
  read_window(sat_id, t0_utime, t1_utime, out);
  return out;
}

void SampleWindowStore::read_windows(std::span<const WindowRequest> requests,
                                     std::vector<StoredSample>& out, std::vector<size_t>& ends) {
  out.clear();
  ends.clear();
  for (const WindowRequest& r : requests) {
    read_window(r.sat_id, r.t0_utime, r.t1_utime, window_rows_);
    out.insert(out.end(), std::make_move_iterator(window_rows_.begin()),
               std::make_move_iterator(window_rows_.end()));
    ends.push_back(out.size());
  }
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

RetentionStats SampleWindowStore::delete_before(std::string_view sat_id, int64_t cutoff_utime,
                                                int chunk_rows) {
  if (chunk_rows <= 0) {
    throw StorageError(StorageError::Kind::kInvalidArgument, "chunk_rows must be positive");
  }
  RetentionStats stats;
  for (;;) {
    const int64_t deleted = delete_chunk(sat_id, cutoff_utime, chunk_rows);
    ++stats.transactions;
    stats.deleted += deleted;
    if (deleted < chunk_rows) break;
  }
  return stats;
}

RetentionStats SampleWindowStore::apply_retention(std::string_view sat_id, int64_t window_utime,
                                                  int64_t margin_utime, int chunk_rows) {
  const auto newest = newest_utime(sat_id);
  if (!newest) return {};
  return delete_before(sat_id, *newest - window_utime - margin_utime, chunk_rows);
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
