#include "storage/postgres/pg_sample_window_store.hpp"

#include <algorithm>
#include <numeric>

#include "storage/postgres/pg_row.hpp"
#include "storage/sample_row.hpp"
#include "storage/sample_sql.hpp"

namespace magcal::storage {
namespace {

// INSERT of `rows` samples (parameters: $1 the station, the same for every row, then the
// sample's columns per row), returning the keys it stored.
std::string insert_sql(size_t rows) {
  return multi_row_values_sql(
      "INSERT INTO samples (" + sample_row::insert_columns() + ") VALUES ", rows,
      sample_row::column_count(true), 2, ", $1::text",
      std::string(" ") + sample_sql::kIgnoreDuplicate + " RETURNING sat_id, utime");
}

// The columns of a result holding read_columns() from `first` on, checked once: the hot loop
// then reads them without a check each.
void check_sample_columns(const PgResult& r, int first) {
  int c = first;
  sample_row::for_each_column(false, [&](const char*, sample_row::ColumnType type) {
    r.check_binary_column(c++, type == sample_row::ColumnType::kInteger
                                   ? PgResult::BinaryColumn::kBigint
                                   : PgResult::BinaryColumn::kDouble);
  });
}

}  // namespace

PgSampleWindowStore::PgSampleWindowStore(PgDatabase& db) : SqlSampleWindowStore(db, db), pg_(db) {
  for (size_t rows = 1; rows <= kMaxRowsPerInsert; rows *= 2)
    insert_sql_.push_back(insert_sql(rows));
}

void PgSampleWindowStore::insert_rows(std::span<const StoredSample> samples,
                                      std::vector<size_t>* duplicate_rows, std::string_view station,
                                      InsertStats& stats) {
  // One global key order; stable, so of two copies of a key in the batch the first is stored.
  order_.resize(samples.size());
  std::iota(order_.begin(), order_.end(), size_t{0});
  std::stable_sort(order_.begin(), order_.end(), [&](size_t a, size_t b) {
    const StoredSample& x = samples[a];
    const StoredSample& y = samples[b];
    if (const int c = x.sat_id.compare(y.sat_id); c != 0) return c < 0;
    return x.utime < y.utime;
  });
  Transaction tx(pg_);
  stored_keys_.clear();
  for_each_power_of_two_run(order_.size(), insert_sql_.size() - 1, [&](size_t begin, size_t k) {
    params_.clear();
    if (station.empty()) {
      params_.add_null();
    } else {
      params_.add(station);
    }
    PgBinder binder{params_};
    for (size_t row = begin; row < begin + (size_t{1} << k); ++row) {
      sample_row::write(samples[order_[row]], binder);
    }
    const PgResult r = pg_.execute_prepared(insert_sql_[k], params_, PgFormat::kBinary);
    for (int row = 0; row < r.rows(); ++row) {
      stored_keys_.emplace_back(r.get_text(row, 0), r.get_int64(row, 1));
    }
  });
  tx.commit();
  // The stored keys against the batch, both in key order: a row whose key was stored and not
  // yet claimed by an earlier copy was inserted; any other row is a duplicate.
  std::sort(stored_keys_.begin(), stored_keys_.end());
  size_t next = 0;
  for (const size_t row : order_) {
    const StoredSample& s = samples[row];
    if (next < stored_keys_.size() && stored_keys_[next].first == s.sat_id &&
        stored_keys_[next].second == s.utime) {
      ++next;
      ++stats.inserted;
    } else {
      ++stats.duplicates;
      if (duplicate_rows) duplicate_rows->push_back(row);
    }
  }
  if (duplicate_rows) std::sort(duplicate_rows->begin(), duplicate_rows->end());
}

void PgSampleWindowStore::read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                                      std::vector<StoredSample>& out) {
  static const std::string sql = dollar_params(sample_sql::window());
  out.clear();
  PgParams p;
  p.add(sat_id).add(t0_utime).add(t1_utime);
  const PgResult r = pg_.execute_prepared(sql, p, PgFormat::kBinary);
  check_sample_columns(r, 0);
  out.resize(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) {
    sample_row::read(PgBinaryRow{r, row}, 0, sat_id, out[static_cast<size_t>(row)]);
  }
}

void PgSampleWindowStore::read_windows(std::span<const WindowRequest> requests,
                                       std::vector<StoredSample>& out, std::vector<size_t>& ends) {
  // Column 0: the request's ordinal (1-based); each request's rows by the primary key.
  static const std::string sql =
      "SELECT q.i, w.* FROM unnest($1::text[], $2::bigint[], $3::bigint[]) WITH ORDINALITY AS "
      "q(sat_id, t0, t1, i) CROSS JOIN LATERAL (SELECT " +
      sample_row::read_columns() +
      " FROM samples WHERE samples.sat_id = q.sat_id COLLATE \"C\" AND utime >= q.t0 AND "
      "utime < q.t1 ORDER BY utime) w ORDER BY q.i, w.utime";
  out.clear();
  ends.clear();
  if (requests.empty()) return;
  request_sats_.resize(requests.size());
  request_t0s_.clear();
  request_t1s_.clear();
  for (size_t i = 0; i < requests.size(); ++i) {
    request_sats_[i].assign(requests[i].sat_id);
    request_t0s_.push_back(requests[i].t0_utime);
    request_t1s_.push_back(requests[i].t1_utime);
  }
  PgParams p;
  p.add_array(request_sats_).add_array(request_t0s_).add_array(request_t1s_);
  const PgResult r = pg_.execute_prepared(sql, p, PgFormat::kBinary);
  r.check_binary_column(0, PgResult::BinaryColumn::kBigint);
  check_sample_columns(r, 1);
  out.resize(static_cast<size_t>(r.rows()));
  size_t request = 0;
  for (int row = 0; row < r.rows(); ++row) {
    const auto of = static_cast<size_t>(r.bigint_at(row, 0) - 1);
    while (request < of) {
      ends.push_back(static_cast<size_t>(row));
      ++request;
    }
    sample_row::read(PgBinaryRow{r, row}, 1, requests[of].sat_id, out[static_cast<size_t>(row)]);
  }
  while (ends.size() < requests.size()) ends.push_back(out.size());
}

int64_t PgSampleWindowStore::delete_chunk(std::string_view sat_id, int64_t cutoff_utime,
                                          int chunk_rows) {
  PgParams p;
  p.add(sat_id).add(cutoff_utime).add(int64_t{chunk_rows});
  return pg_
      .execute_prepared(
          // The chunk as a key range (its last key from the index): two index range scans in
          // any plan. (utime IN (... LIMIT $3) was planned, once analysed, as a scan of all the
          // spacecraft's rows, each probed against the chunk: 1 ms for a DELETE of nothing.)
          "DELETE FROM samples WHERE sat_id = $1 AND utime < $2 AND utime <= coalesce((SELECT "
          "utime FROM samples WHERE sat_id = $1 AND utime < $2 ORDER BY utime OFFSET $3 - 1 "
          "LIMIT 1), $2)",
          p)
      .affected_rows();
}

}  // namespace magcal::storage
