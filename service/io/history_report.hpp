// The stored calibration history of one spacecraft as operations read it: the text of
// `magcal history` (aligned table, CSV, JSON array) and of GET /api/v1/history, built once here
// so that the CLI and the HTTP server answer byte for byte the same (design.md "Operations
// surface"), plus the downsampled view of `/api/v1/history?points=N`.
//
// JSON objects are service/io/result_json.hpp's keys for the stored fields (the same keys as
// `fit --json`) plus sat_id, id, time / window_start / window_end (ISO 8601 UTC),
// software_version and created_time. CSV has the same fields flat (design.md column names); the
// alignment's are alignment_singular, q_sensor_from_body_{w,x,y,z}, alignment_{roll,pitch,yaw}_deg,
// alignment_sigma_{roll,pitch,yaw}_deg, alignment_determined_sigma_deg and
// alignment_covariance_{11,22,33,12,13,23}_deg2 (empty without an alignment; sigmas and covariance
// empty for rows stored before the covariance was kept). Then D11_sigma..D23_sigma and the
// covariance's upper triangle cov_b1_b1, cov_b1_b2, ..., cov_D23_D23 (row-major, p = [b1 b2 b3
// D11 D22 D33 D12 D13 D23]), and field_direction_error_{rms,worst}_deg,
// field_magnitude_error_{rms,worst}_nT (empty: not computed).
#pragma once

#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"

namespace magcal {

// A history request as the user wrote it (CLI options or URL query parameters), unparsed.
struct HistoryRequest {
  std::string sat;
  std::string method;        // empty: all; else ukf | ekf | centered | twostep
  std::string since, until;  // ISO 8601 UTC, inclusive; empty: open
  std::optional<int> limit;  // only the N newest
  std::string order = "asc";
  std::string format = "table";  // table | csv | json
};

// Validates a request into a storage query. On a bad value returns nullopt and sets *error to
// one line naming the parameter as `option_prefix + name` ("--since" for the CLI, "since" for
// the HTTP query string).
std::optional<storage::HistoryQuery> parse_history_request(const HistoryRequest& request,
                                                           const std::string& option_prefix,
                                                           std::string* error);

// The rows of `query`, read in one snapshot (a short deferred read transaction) on `db`, which
// may be read-only. Throws storage::StorageError.
std::vector<storage::CalibrationRecord> read_history(storage::Connection& db,
                                                     const storage::HistoryQuery& query);

// True when the database holds anything for this spacecraft (a result or a sample).
bool spacecraft_known(storage::Connection& db, const std::string& sat_id);

// The exact stdout of `magcal history --format json|csv|table` for these rows (JSON: the
// array dumped with indent 2 and a final newline; table: header line plus one line per row).
std::string history_json_text(const std::vector<storage::CalibrationRecord>& rows);
std::string history_csv_text(const std::vector<storage::CalibrationRecord>& rows);
std::string history_table_text(const std::vector<storage::CalibrationRecord>& rows);

// Yamcs-style downsampling of `rows` into `points` equal time buckets (points >= 1) spanning
// [first_utime, last_utime] (the query's since/until when given, else the rows' own range),
// one series per method. Shape (times as history_time() strings, utimes in µs):
//   {"sat_id", "points", "rows": N, "start_utime", "end_utime", "bucket_us",
//    "fields": [names],
//    "series": [{"method": "ukf", "buckets": [{"start_utime", "end_utime", "start_time",
//                "count", "accepted", "rejected",
//                "<field>": {"n", "min", "mean", "max"}, ...}, ...]}, ...]}
// Buckets without rows are left out; sum of all "count" = rows. Per field, "n" counts the
// finite values and min/mean/max are over those (null when n = 0). Fields: n_samples,
// bias_{x,y,z}_nT, bias_sigma_{x,y,z}_nT, D11 D22 D33 D12 D13 D23 (dimensionless),
// D{11,...}_sigma (sqrt of the covariance diagonal), residual_rms_nT.
nlohmann::json downsample_history(const std::vector<storage::CalibrationRecord>& rows,
                                  const storage::HistoryQuery& query, int points);

}  // namespace magcal
