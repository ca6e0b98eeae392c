#include "storage/postgres/pg_stores.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <tuple>

#include "storage/blob_doubles.hpp"
#include "storage/store_columns.hpp"

namespace magcal::storage {
namespace {

constexpr int kParamsPerSample = 20;

// NaN is stored as NULL, as on SQLite (a NOT NULL column then refuses it).
void add_value(PgParams& p, double value) {
  if (std::isnan(value)) {
    p.add_null();
  } else {
    p.add(value);
  }
}

// A group of columns stored together or not at all (NULL when the sample lacks it).
void add_group(PgParams& p, std::span<const double> values, bool present) {
  for (const double v : values) {
    if (present) {
      add_value(p, v);
    } else {
      p.add_null();
    }
  }
}

void add_sample(PgParams& p, const StoredSample& s) {
  p.add(s.sat_id).add(s.utime).add(s.seq).add(s.receive_utime);
  add_group(p, s.b_sensor_nT, true);
  p.add(int64_t{s.has_direction ? 1 : 0});
  add_group(p, s.h_body_nT, s.has_direction);
  add_value(p, s.h_norm_nT);
  add_group(p, s.q_body_from_eci, s.has_attitude);
  add_group(p, s.r_ecef_m, s.has_position);
  add_value(p, s.temperature_C);
}

// INSERT of `rows` samples (parameters: $1 the station, the same for every row, then 20 per
// row), returning the keys it stored. Only a repeated key is ignored (and counted); a NOT NULL
// violation is an error.
std::string insert_sql(size_t rows) {
  return multi_row_values_sql(
      std::string("INSERT INTO samples (") + columns::kSampleInsert + ") VALUES ", rows,
      kParamsPerSample, 2, ", $1::text",
      " ON CONFLICT (sat_id, utime) DO NOTHING RETURNING sat_id, utime");
}

std::optional<int64_t> optional_int(const PgResult& r, int row, int column) {
  return r.get_optional_int64(row, column);
}

}  // namespace

PgSampleWindowStore::PgSampleWindowStore(PgDatabase& db) : SampleWindowStore(db), pg_(db) {
  for (size_t rows = 1; rows <= kMaxRowsPerInsert; rows *= 2)
    insert_sql_.push_back(insert_sql(rows));
}

InsertStats PgSampleWindowStore::insert_batch(std::span<const StoredSample> samples,
                                              std::vector<size_t>* duplicate_rows,
                                              std::string_view station) {
  InsertStats stats;
  if (duplicate_rows) duplicate_rows->clear();
  if (samples.empty()) return stats;
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
    for (size_t row = begin; row < begin + (size_t{1} << k); ++row) {
      add_sample(params_, samples[order_[row]]);
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
  return stats;
}

namespace {

// The sample columns (columns::kSampleRead) of `r` from column `first` on, read in binary:
// column types checked once, NOT NULL columns read without a NULL test, nullable groups tested
// once per group (the hot loop: a 12 h window is 4320 rows).
class SampleRows {
 public:
  SampleRows(const PgResult& r, int first) : r_(r), c_(first) {
    using Column = PgResult::BinaryColumn;
    for (int c = 0; c < 19; ++c) {
      const bool bigint = c < 3 || c == 6;  // utime, seq, receive_utime, has_direction
      r.check_binary_column(first + c, bigint ? Column::kBigint : Column::kDouble);
    }
  }
  void read(int row, std::string_view sat_id, StoredSample& s) const {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    auto bigint = [&](int c) { return r_.bigint_at(row, c_ + c); };
    auto real = [&](int c) { return r_.double_at(row, c_ + c); };
    s.sat_id = sat_id;
    s.utime = bigint(0);
    s.seq = bigint(1);
    s.receive_utime = bigint(2);
    for (int i = 0; i < 3; ++i) s.b_sensor_nT[i] = real(3 + i);
    s.has_direction = bigint(6) != 0;
    for (int i = 0; i < 3; ++i) s.h_body_nT[i] = s.has_direction ? real(7 + i) : kNaN;
    s.h_norm_nT = real(10);
    s.has_attitude = !r_.is_null(row, c_ + 11);
    if (s.has_attitude) {
      for (int i = 0; i < 4; ++i) s.q_body_from_eci[i] = real(11 + i);
    }
    s.has_position = !r_.is_null(row, c_ + 15);
    if (s.has_position) {
      for (int i = 0; i < 3; ++i) s.r_ecef_m[i] = real(15 + i);
    }
    s.temperature_C = r_.is_null(row, c_ + 18) ? kNaN : real(18);
  }

 private:
  const PgResult& r_;
  int c_;
};

}  // namespace

void PgSampleWindowStore::read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                                      std::vector<StoredSample>& out) {
  out.clear();
  PgParams p;
  p.add(sat_id).add(t0_utime).add(t1_utime);
  const PgResult r = pg_.execute_prepared(
      std::string("SELECT ") + columns::kSampleRead +
          " FROM samples WHERE sat_id = $1 AND utime >= $2 AND utime < $3 ORDER BY utime",
      p, PgFormat::kBinary);
  const SampleRows rows(r, 0);
  out.resize(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) rows.read(row, sat_id, out[static_cast<size_t>(row)]);
}

void PgSampleWindowStore::read_windows(std::span<const WindowRequest> requests,
                                       std::vector<StoredSample>& out, std::vector<size_t>& ends) {
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
  // Column 0: the request's ordinal (1-based); each request's rows by the primary key.
  const PgResult r = pg_.execute_prepared(
      std::string("SELECT q.i, w.* FROM unnest($1::text[], $2::bigint[], $3::bigint[]) WITH "
                  "ORDINALITY AS q(sat_id, t0, t1, i) CROSS JOIN LATERAL (SELECT ") +
          columns::kSampleRead +
          " FROM samples WHERE samples.sat_id = q.sat_id COLLATE \"C\" AND utime >= q.t0 AND "
          "utime < q.t1 ORDER BY utime) w ORDER BY q.i, w.utime",
      p, PgFormat::kBinary);
  r.check_binary_column(0, PgResult::BinaryColumn::kBigint);
  const SampleRows rows(r, 1);
  out.resize(static_cast<size_t>(r.rows()));
  size_t request = 0;
  for (int row = 0; row < r.rows(); ++row) {
    const auto of = static_cast<size_t>(r.bigint_at(row, 0) - 1);
    while (request < of) {
      ends.push_back(static_cast<size_t>(row));
      ++request;
    }
    rows.read(row, requests[of].sat_id, out[static_cast<size_t>(row)]);
  }
  while (ends.size() < requests.size()) ends.push_back(out.size());
}

int64_t PgSampleWindowStore::count_in_window(std::string_view sat_id, int64_t t0_utime,
                                             int64_t t1_utime) {
  PgParams p;
  p.add(sat_id).add(t0_utime).add(t1_utime);
  return pg_
      .execute_prepared(
          "SELECT count(*) FROM samples WHERE sat_id = $1 AND utime >= $2 AND utime < $3", p,
          PgFormat::kBinary)
      .get_int64(0, 0);
}

std::vector<StationCount> PgSampleWindowStore::count_by_station(std::string_view sat_id,
                                                                int64_t t0_utime,
                                                                int64_t t1_utime) {
  PgParams p;
  p.add(sat_id).add(t0_utime).add(t1_utime);
  const PgResult r = pg_.execute_prepared(
      // Sorted in byte order, as SQLite's.
      "SELECT coalesce(station, '') COLLATE \"C\" AS s, count(*) FROM samples WHERE sat_id = $1 "
      "AND utime >= $2 AND utime < $3 GROUP BY s ORDER BY s",
      p, PgFormat::kBinary);
  std::vector<StationCount> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back({r.get_text(row, 0), r.get_int64(row, 1)});
  return out;
}

std::optional<int64_t> PgSampleWindowStore::single_utime(const char* sql, std::string_view sat_id) {
  PgParams p;
  p.add(sat_id);
  const PgResult r = pg_.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return optional_int(r, 0, 0);
}

std::optional<int64_t> PgSampleWindowStore::newest_utime(std::string_view sat_id) {
  return single_utime("SELECT max(utime) FROM samples WHERE sat_id = $1", sat_id);
}

std::optional<int64_t> PgSampleWindowStore::oldest_utime(std::string_view sat_id) {
  return single_utime("SELECT min(utime) FROM samples WHERE sat_id = $1", sat_id);
}

int64_t PgSampleWindowStore::count(std::string_view sat_id) {
  PgParams p;
  p.add(sat_id);
  return pg_
      .execute_prepared("SELECT count(*) FROM samples WHERE sat_id = $1", p, PgFormat::kBinary)
      .get_int64(0, 0);
}

std::optional<int64_t> PgSampleWindowStore::utime_at_rank(std::string_view sat_id, int64_t rank) {
  if (rank < 0) return std::nullopt;
  PgParams p;
  p.add(sat_id).add(rank);
  const PgResult r = pg_.execute_prepared(
      "SELECT utime FROM samples WHERE sat_id = $1 ORDER BY utime LIMIT 1 OFFSET $2", p,
      PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return r.get_int64(0, 0);
}

std::vector<std::string> PgSampleWindowStore::spacecraft() {
  // Skip-scan over the primary key: one index descent per spacecraft, not a full scan.
  const PgResult r = pg_.execute_prepared(
      "WITH RECURSIVE s(id) AS (SELECT min(sat_id) FROM samples UNION ALL "
      "SELECT (SELECT min(sat_id) FROM samples WHERE sat_id > s.id) FROM s "
      "WHERE s.id IS NOT NULL) SELECT id FROM s WHERE id IS NOT NULL");
  std::vector<std::string> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(r.get_text(row, 0));
  return out;
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

namespace {

const std::string kJobSelect = std::string("SELECT ") + columns::kRefitJob + " FROM refit_jobs ";

RefitJob job_from_row(const PgResult& r, int row) {
  RefitJob j;
  j.id = r.get_int64(row, 0);
  j.sat_id = r.get_text(row, 1);
  j.trigger = r.get_text(row, 2);
  j.scheduled_utime = r.get_int64(row, 3);
  j.started_utime = r.get_optional_int64(row, 4);
  j.finished_utime = r.get_optional_int64(row, 5);
  j.outcome = r.get_text(row, 6);
  j.error = r.get_text(row, 7);
  j.calibration_id = r.get_optional_int64(row, 8);
  if (!r.is_null(row, 9)) j.claimed_by = r.get_text(row, 9);
  return j;
}

// The one value of a query on sat_id ($1); nullopt when NULL (max() of no rows).
std::optional<int64_t> single_int(PgDatabase& db, const char* sql, std::string_view sat_id) {
  PgParams p;
  p.add(sat_id);
  const PgResult r = db.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return r.get_optional_int64(0, 0);
}

}  // namespace

int64_t PgRefitJobLog::start(std::string_view sat_id, std::string_view trigger,
                             int64_t scheduled_utime, int64_t started_utime) {
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime).add(started_utime);
  return db_
      .execute_prepared(
          "INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, started_utime, "
          "outcome) VALUES ($1, $2, $3, $4, 'running') RETURNING id",
          p, PgFormat::kBinary)
      .get_int64(0, 0);
}

std::optional<int64_t> PgRefitJobLog::claim(std::string_view sat_id, std::string_view trigger,
                                            int64_t scheduled_utime, int64_t started_utime,
                                            std::string_view station) {
  check_claimant(station);
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime).add(started_utime).add(station);
  const PgResult r = db_.execute_prepared(
      std::string("INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, started_utime, "
                  "outcome, claimed_by) VALUES ($1, $2, $3, $4, 'running', $5) ON CONFLICT "
                  "(sat_id, trigger_kind, scheduled_utime) WHERE ") +
          columns::kHoldsRefitClaim + " DO NOTHING RETURNING id",
      p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;  // DO NOTHING: another job holds the claim
  return r.get_int64(0, 0);
}

std::optional<RefitJob> PgRefitJobLog::claim_holder(std::string_view sat_id,
                                                    std::string_view trigger,
                                                    int64_t scheduled_utime) {
  PgParams p;
  p.add(sat_id).add(trigger).add(scheduled_utime);
  const PgResult r = db_.execute_prepared(
      kJobSelect + "WHERE sat_id = $1 AND trigger_kind = $2 AND scheduled_utime = $3 AND " +
          columns::kHoldsRefitClaim,
      p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return job_from_row(r, 0);
}

void PgRefitJobLog::finish(int64_t job_id, std::string_view outcome, int64_t finished_utime,
                           std::string_view error, std::optional<int64_t> calibration_id) {
  PgParams p;
  p.add(job_id).add(outcome).add(finished_utime).add(error).add(calibration_id);
  const PgResult r = db_.execute_prepared(
      "UPDATE refit_jobs SET outcome = $2, finished_utime = $3, error = $4, calibration_id = $5 "
      "WHERE id = $1 AND outcome = 'running'",
      p);
  if (r.affected_rows() != 1) throw_not_running(job_id, get(job_id));
}

int PgRefitJobLog::mark_station_running_interrupted(std::string_view station, int64_t now_utime) {
  PgParams p;
  p.add(station).add(now_utime).add(job_outcome::kProcessEnded);
  return static_cast<int>(
      db_.execute_prepared("UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = $2, "
                           "error = $3 WHERE outcome = 'running' AND (claimed_by = $1 OR "
                           "claimed_by IS NULL)",
                           p)
          .affected_rows());
}

int PgRefitJobLog::mark_running_interrupted(std::string_view sat_id, int64_t now_utime) {
  PgParams p;
  p.add(sat_id).add(now_utime).add(job_outcome::kTakenOver);
  return static_cast<int>(
      db_.execute_prepared("UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = $2, "
                           "error = $3 WHERE sat_id = $1 AND outcome = 'running'",
                           p)
          .affected_rows());
}

std::optional<int64_t> PgRefitJobLog::newest_reanchor_calibration_id(std::string_view sat_id) {
  return single_int(db_,
                    "SELECT max(calibration_id) FROM refit_jobs WHERE sat_id = $1 AND "
                    "outcome = 'ok' AND trigger_kind <> 'manual'",
                    sat_id);
}

std::optional<int64_t> PgRefitJobLog::newest_finished_scheduled_utime(std::string_view sat_id) {
  return single_int(db_,
                    "SELECT max(scheduled_utime) FROM refit_jobs WHERE sat_id = $1 AND "
                    "trigger_kind = 'scheduled' AND outcome NOT IN ('running', 'interrupted')",
                    sat_id);
}

std::optional<RefitJob> PgRefitJobLog::get(int64_t job_id) {
  PgParams p;
  p.add(job_id);
  const PgResult r = db_.execute_prepared(kJobSelect + "WHERE id = $1", p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return job_from_row(r, 0);
}

std::vector<RefitJob> PgRefitJobLog::recent(std::string_view sat_id, int limit) {
  PgParams p;
  p.add(sat_id).add(int64_t{limit});
  const PgResult r = db_.execute_prepared(
      kJobSelect + "WHERE sat_id = $1 ORDER BY id DESC LIMIT $2", p, PgFormat::kBinary);
  std::vector<RefitJob> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(job_from_row(r, row));
  return out;
}

namespace {

const std::string kFilterSelect =
    std::string("SELECT ") + columns::kFilterState + " FROM filter_states ";

FilterState filter_state_from_row(const PgResult& r, int row) {
  FilterState s;
  s.sat_id = r.get_text(row, 0);
  s.method = r.get_text(row, 1);
  const auto x = r.get_bytes(row, 2);
  doubles_from_blob(x.data(), x.size(), s.x, "filter_states.x");
  const auto P = r.get_bytes(row, 3);
  doubles_from_blob(P.data(), P.size(), s.P, "filter_states.P");
  s.last_utime = r.get_int64(row, 4);
  s.n_samples = r.get_int64(row, 5);
  if (!r.is_null(row, 6)) {
    const auto counters = r.get_bytes(row, 6);
    s.counters.resize(counters.size());
    std::transform(counters.begin(), counters.end(), s.counters.begin(),
                   [](std::byte b) { return static_cast<uint8_t>(b); });
  }
  s.updated_utime = r.get_int64(row, 7);
  s.anchor_calibration_id = r.get_optional_int64(row, 8);
  return s;
}

std::span<const std::byte> bytes_of(const void* data, size_t size) {
  return {static_cast<const std::byte*>(data), size};
}

constexpr int kFilterStateColumns = 9;

void add_filter_state(PgParams& p, const FilterState& s) {
  p.add(s.sat_id).add(s.method);
  p.add_bytes(bytes_of(s.x.data(), sizeof(double) * s.x.size()));
  p.add_bytes(bytes_of(s.P.data(), sizeof(double) * s.P.size()));
  p.add(s.last_utime).add(s.n_samples);
  p.add_bytes(bytes_of(s.counters.data(), s.counters.size()));
  p.add(save_utime(s)).add(s.anchor_calibration_id);
}

// The upsert of `rows` states (distinct keys: a statement cannot update one row twice).
std::string filter_state_upsert_sql(size_t rows) {
  return multi_row_values_sql(
      std::string("INSERT INTO filter_states (") + columns::kFilterState + ") VALUES ", rows,
      kFilterStateColumns, 1, "",
      " ON CONFLICT (sat_id, method) DO UPDATE SET x = excluded.x, P = excluded.P, "
      "last_utime = excluded.last_utime, n_samples = excluded.n_samples, "
      "counters = excluded.counters, updated_utime = excluded.updated_utime, "
      "anchor_calibration_id = excluded.anchor_calibration_id");
}

}  // namespace

void PgFilterStateStore::save(const FilterState& s) {
  save_all(std::span(&s, 1));
}

void PgFilterStateStore::save_all(std::span<const FilterState> states) {
  static const std::vector<std::string> sql = [] {
    std::vector<std::string> out;
    for (size_t k = 0; k <= kMaxLog2RowsPerUpsert; ++k) {
      out.push_back(filter_state_upsert_sql(size_t{1} << k));
    }
    return out;
  }();
  // Key order (stable: the later of two states of one key is the one kept, as by successive
  // saves), each key once.
  std::vector<size_t> order(states.size());
  std::iota(order.begin(), order.end(), size_t{0});
  auto key = [&](size_t i) { return std::tie(states[i].sat_id, states[i].method); };
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return key(a) < key(b); });
  size_t kept = 0;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i + 1 < order.size() && key(order[i]) == key(order[i + 1])) continue;
    order[kept++] = order[i];
  }
  order.resize(kept);
  for_each_power_of_two_run(order.size(), kMaxLog2RowsPerUpsert, [&](size_t begin, size_t k) {
    params_.clear();
    for (size_t i = begin; i < begin + (size_t{1} << k); ++i) {
      add_filter_state(params_, states[order[i]]);
    }
    db_.execute_prepared(sql[k], params_);
  });
}

std::optional<FilterState> PgFilterStateStore::load(std::string_view sat_id,
                                                    std::string_view method) {
  PgParams p;
  p.add(sat_id).add(method);
  const PgResult r = db_.execute_prepared(kFilterSelect + "WHERE sat_id = $1 AND method = $2", p,
                                          PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return filter_state_from_row(r, 0);
}

std::vector<FilterState> PgFilterStateStore::load_all() {
  const PgResult r =
      db_.execute_prepared(kFilterSelect + "ORDER BY sat_id, method", {}, PgFormat::kBinary);
  std::vector<FilterState> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(filter_state_from_row(r, row));
  return out;
}

namespace {

Lease lease_from_row(const PgResult& r, int row) {
  return {r.get_text(row, 0), r.get_text(row, 1), r.get_int64(row, 2), r.get_int64(row, 3),
          r.get_int64(row, 4)};
}

// SQL written for SQLite's ?N parameters in PostgreSQL's $N (no other '?' in it).
std::string dollar_params(std::string sql) {
  std::replace(sql.begin(), sql.end(), '?', '$');
  return sql;
}

}  // namespace

std::optional<Lease> PgLeaseStore::try_acquire(std::string_view sat_id, std::string_view owner,
                                               int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  static const std::string sql = dollar_params(columns::kLeaseAcquire);
  PgParams p;
  p.add(sat_id).add(owner).add(now_utime).add(ttl_utime);
  const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;  // another owner holds it
  return lease_from_row(r, 0);
}

bool PgLeaseStore::renew(std::string_view sat_id, std::string_view owner, int64_t epoch,
                         int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  PgParams p;
  p.add(sat_id).add(owner).add(epoch).add(now_utime).add(ttl_utime);
  return db_.execute_prepared(
                "UPDATE leases SET expires_utime = $4 + $5 WHERE sat_id = $1 AND "
                "owner = $2 AND epoch = $3",
                p)
             .affected_rows() == 1;
}

std::optional<Lease> PgLeaseStore::reclaim(std::string_view sat_id, std::string_view owner,
                                           int64_t epoch, int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  static const std::string sql = dollar_params(columns::kLeaseReclaim);
  PgParams p;
  p.add(sat_id).add(owner).add(epoch).add(now_utime).add(ttl_utime);
  const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return lease_from_row(r, 0);
}

bool PgLeaseStore::release(std::string_view sat_id, std::string_view owner, int64_t epoch,
                           int64_t now_utime) {
  PgParams p;
  p.add(sat_id).add(owner).add(epoch).add(now_utime);
  return db_.execute_prepared(
                "UPDATE leases SET expires_utime = least(expires_utime, $4) WHERE "
                "sat_id = $1 AND owner = $2 AND epoch = $3",
                p)
             .affected_rows() == 1;
}

bool PgLeaseStore::holds(std::string_view sat_id, std::string_view owner, int64_t epoch) {
  PgParams p;
  p.add(sat_id).add(owner).add(epoch);
  // FOR SHARE: a takeover's upsert waits until the caller's transaction ends.
  return db_.execute_prepared(
                "SELECT 1 FROM leases WHERE sat_id = $1 AND owner = $2 AND "
                "epoch = $3 FOR SHARE",
                p)
             .rows() == 1;
}

std::vector<std::string> PgLeaseStore::not_held(std::string_view owner,
                                                std::span<const Held> leases) {
  if (leases.empty()) return {};
  std::vector<std::string> sats;
  std::vector<int64_t> epochs;
  for (const Held& l : leases) {
    sats.push_back(l.sat_id);
    epochs.push_back(l.epoch);
  }
  PgParams p;
  p.add(owner).add_array(sats).add_array(epochs);
  // Locked in one order (sat_id, as renew_all and the takeovers' single rows need no other), so
  // two fences never wait for each other crosswise.
  const PgResult r = db_.execute_prepared(
      "SELECT l.sat_id FROM leases l JOIN unnest($2::text[], $3::bigint[]) AS q(sat_id, epoch) "
      "ON l.sat_id = q.sat_id AND l.epoch = q.epoch WHERE l.owner = $1 ORDER BY l.sat_id "
      "FOR SHARE OF l",
      p);
  std::vector<std::string> held;
  held.reserve(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) held.push_back(r.get_text(row, 0));
  std::sort(held.begin(), held.end());
  std::vector<std::string> out;
  for (const Held& l : leases) {
    if (!std::binary_search(held.begin(), held.end(), l.sat_id)) out.push_back(l.sat_id);
  }
  return out;
}

std::optional<Lease> PgLeaseStore::get(std::string_view sat_id) {
  PgParams p;
  p.add(sat_id);
  const PgResult r = db_.execute_prepared(
      std::string("SELECT ") + columns::kLease + " FROM leases WHERE sat_id = $1", p,
      PgFormat::kBinary);
  if (r.rows() == 0) return std::nullopt;
  return lease_from_row(r, 0);
}

std::vector<Lease> PgLeaseStore::list() {
  const PgResult r = db_.execute_prepared(
      std::string("SELECT ") + columns::kLease + " FROM leases ORDER BY sat_id COLLATE \"C\"", {},
      PgFormat::kBinary);
  std::vector<Lease> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(lease_from_row(r, row));
  return out;
}

void PgLeaseStore::ensure(std::string_view sat_id) {
  static const std::string sql = dollar_params(columns::kLeaseEnsure);
  PgParams p;
  p.add(sat_id);
  db_.execute_prepared(sql, p);
}

std::vector<Lease> PgLeaseStore::renew_all(std::string_view owner, int64_t now_utime,
                                           int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  static const std::string sql = dollar_params(columns::kLeaseRenewAll);
  PgParams p;
  p.add(owner).add(now_utime).add(ttl_utime);
  const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
  std::vector<Lease> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(lease_from_row(r, row));
  return out;
}

std::optional<StationBeat> PgLeaseStore::heartbeat(std::string_view station,
                                                   std::string_view instance,
                                                   const StationSettings& settings,
                                                   int64_t now_utime, int64_t ttl_utime) {
  check_request(station, ttl_utime);
  std::optional<StationBeat> before;
  {
    static const std::string sql = dollar_params(columns::kStationBeat);
    PgParams p;
    p.add(station);
    const PgResult r = db_.execute_prepared(sql, p, PgFormat::kBinary);
    if (r.rows() > 0) before = StationBeat{r.get_text(0, 0), r.get_int64(0, 1), r.get_int64(0, 2)};
  }
  static const std::string sql = dollar_params(columns::kStationHeartbeat);
  PgParams p;
  p.add(station).add(now_utime).add(ttl_utime).add(instance);
  if (settings.text.empty()) {
    p.add_null().add_null();
  } else {
    p.add(settings.text).add(settings.hash);
  }
  db_.execute_prepared(sql, p);
  return before;
}

void PgLeaseStore::leave(std::string_view station, int64_t now_utime) {
  PgParams p;
  p.add(station).add(now_utime);
  db_.execute_prepared(
      "UPDATE stations SET expires_utime = least(expires_utime, $2) WHERE station = $1", p);
}

std::vector<std::string> PgLeaseStore::live_stations(int64_t now_utime) {
  PgParams p;
  p.add(now_utime);
  const PgResult r = db_.execute_prepared(
      "SELECT station FROM stations WHERE expires_utime > $1 ORDER BY station COLLATE \"C\"", p);
  std::vector<std::string> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(r.get_text(row, 0));
  return out;
}

std::vector<StationRow> PgLeaseStore::stations() {
  static const std::string sql = std::string(columns::kStationList) + " COLLATE \"C\"";
  const PgResult r = db_.execute_prepared(sql, PgParams{}, PgFormat::kBinary);
  std::vector<StationRow> out;
  for (int row = 0; row < r.rows(); ++row) {
    StationRow& station =
        out.emplace_back(StationRow{r.get_text(row, 0), r.get_text(row, 1), r.get_int64(row, 2),
                                    r.get_int64(row, 3), std::nullopt});
    if (!r.is_null(row, 4)) {
      station.settings = StationSettings{r.get_text(row, 4), r.get_text(row, 5)};
    }
  }
  return out;
}

void PgMetaStore::set(std::string_view key, std::string_view value) {
  PgParams p;
  p.add(key).add(value);
  db_.execute_prepared(
      "INSERT INTO meta (key, value) VALUES ($1, $2) "
      "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
      p);
}

std::optional<std::string> PgMetaStore::get(std::string_view key) {
  PgParams p;
  p.add(key);
  const PgResult r = db_.execute_prepared("SELECT value FROM meta WHERE key = $1", p);
  if (r.rows() == 0) return std::nullopt;
  return r.get_text(0, 0);
}

}  // namespace magcal::storage
