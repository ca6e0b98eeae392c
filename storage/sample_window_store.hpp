// Table `samples`: the per-spacecraft sample windows the daemon refits and restarts from.
//
// One row per (sat_id, utime), the primary key: a spacecraft's window is read by key range in
// time order. Each row keeps its reference field
// (h_body_nT in the body frame, or only |h| when there was no direction), so a refit never
// recomputes IGRF. Duplicate (sat_id, utime) rows are refused and counted, never stored twice:
// the first station to deliver a sample stores it (and is recorded as its station).
//
// An interface: SqliteSampleWindowStore (storage/sqlite/sqlite_sample_window_store.hpp) and
// PgSampleWindowStore (storage/postgres/pg_sample_window_store.hpp), made by
// Connection::make_sample_window_store().
//
// Units: nT for fields, metres for r_ecef_m, microseconds since 1970-01-01Z (utime) for times,
// quaternion (w, x, y, z) body-from-ECI as in mag_sample_t (estimation.md section 0).
#pragma once

#include <array>
#include <cstdint>
#include <limits>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::storage {

struct StoredSample {
  std::string sat_id;
  int64_t utime = 0;                    // sample time
  int64_t seq = 0;                      // per-spacecraft sequence number
  int64_t receive_utime = 0;            // wall time the ground received it
  std::array<double, 3> b_sensor_nT{};  // measured field, sensor frame
  // Reference field. has_direction: h_body_nT is the body-frame vector (|h| = its norm);
  // otherwise only h_norm_nT is known and h_body_nT is not stored (reads back as NaN).
  bool has_direction = false;
  std::array<double, 3> h_body_nT{};
  double h_norm_nT = 0.0;
  bool has_attitude = false;
  std::array<double, 4> q_body_from_eci{1.0, 0.0, 0.0, 0.0};  // w, x, y, z
  bool has_position = false;
  std::array<double, 3> r_ecef_m{};
  double temperature_C = std::numeric_limits<double>::quiet_NaN();  // NaN = unknown (NULL)
};

struct InsertStats {
  int64_t inserted = 0;
  int64_t duplicates = 0;  // (sat_id, utime) already stored (or twice in the batch)
};

// Samples of one station in a window (SampleWindowStore::count_by_station).
struct StationCount {
  std::string station;  // "" for samples stored without one (before schema 7)
  int64_t samples = 0;
};

struct RetentionStats {
  int64_t deleted = 0;
  int transactions = 0;
};

class SampleWindowStore {
 public:
  virtual ~SampleWindowStore() = default;

  // All samples in one transaction (or inside the caller's), stored by `station` (the daemon's
  // [station] id; "" = none). Throws StorageError (the transaction is rolled back: nothing of
  // the batch is stored). `duplicate_rows` (optional, cleared first): the indices of the rows
  // that were duplicates, for per-row accounting. A duplicate changes nothing of the stored row,
  // whichever station sent it.
  virtual InsertStats insert_batch(std::span<const StoredSample> samples,
                                   std::vector<size_t>* duplicate_rows = nullptr,
                                   std::string_view station = {}) = 0;

  // Samples of `sat_id` with t0 <= utime < t1, ascending utime, into `out` (cleared first; its
  // capacity is reused). A refit window (t_ref - W, t_ref] is [t_ref - W + 1, t_ref + 1).
  virtual void read_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime,
                           std::vector<StoredSample>& out) = 0;
  std::vector<StoredSample> window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime);
  // read_window of several spacecraft at once (PostgreSQL: one statement for the lot instead of
  // a round trip each): `out` (cleared first) holds the rows of requests[0], then of
  // requests[1], ...; ends[i] (cleared first) is the end in `out` of requests[i]'s rows.
  struct WindowRequest {
    std::string_view sat_id;
    int64_t t0_utime = 0;
    int64_t t1_utime = 0;
  };
  virtual void read_windows(std::span<const WindowRequest> requests, std::vector<StoredSample>& out,
                            std::vector<size_t>& ends);

  virtual int64_t count_in_window(std::string_view sat_id, int64_t t0_utime, int64_t t1_utime) = 0;
  // The samples of `sat_id` with t0 <= utime < t1 per station that stored them, sorted by
  // station (those without one first, as "").
  virtual std::vector<StationCount> count_by_station(std::string_view sat_id, int64_t t0_utime,
                                                     int64_t t1_utime) = 0;
  virtual std::optional<int64_t> newest_utime(std::string_view sat_id) = 0;
  virtual std::optional<int64_t> oldest_utime(std::string_view sat_id) = 0;
  virtual int64_t count(std::string_view sat_id) = 0;
  // Time of the stored sample of `sat_id` with `rank` older ones (0 = the oldest); nullopt when
  // fewer are stored. Keys a refit by the sample count it covers (an early refit).
  virtual std::optional<int64_t> utime_at_rank(std::string_view sat_id, int64_t rank) = 0;
  // Spacecraft with at least one stored sample, sorted.
  virtual std::vector<std::string> spacecraft() = 0;

  // Deletes the samples of `sat_id` with utime < cutoff_utime, at most `chunk_rows` per
  // transaction so a concurrent writer waits at most one small chunk.
  RetentionStats delete_before(std::string_view sat_id, int64_t cutoff_utime,
                               int chunk_rows = 2000);
  // Retention rule (design.md): cutoff = newest sample of sat_id - window - margin (data time).
  // Samples exactly at the cutoff are kept.
  RetentionStats apply_retention(std::string_view sat_id, int64_t window_utime,
                                 int64_t margin_utime, int chunk_rows = 2000);

 protected:
  explicit SampleWindowStore(Connection& db) : db_(db) {}
  // One chunk of delete_before, a transaction of its own (nested in the caller's, if any): at
  // most chunk_rows of the oldest samples below the cutoff. Returns how many were deleted.
  // (PostgreSQL: one statement, atomic without BEGIN and COMMIT round trips.)
  virtual int64_t delete_chunk(std::string_view sat_id, int64_t cutoff_utime, int chunk_rows) = 0;

  Connection& db_;

 private:
  std::vector<StoredSample> window_rows_;  // read_windows' (default), reused
};

}  // namespace magcal::storage
