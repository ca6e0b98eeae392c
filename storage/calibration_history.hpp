// Table `calibrations`: every calibration result the service produces (UKF/EKF snapshots and
// every refit), never deleted by retention. An interface: SqlCalibrationHistory
// (storage/sql_calibration_history.hpp, both backends) and PgCalibrationHistory
// (storage/postgres/pg_calibration_history.hpp), made by Connection::make_calibration_history();
// both store the same columns under the same rules (storage/calibration_row.hpp).
//
// Parameters as in calibration_t / estimation.md: p = [b1 b2 b3 D11 D22 D33 D12 D13 D23]
// (nT, nT, nT, 1, 1, 1, 1, 1, 1); cov = upper triangle, row-major, of the 9x9 covariance of p;
// bias_sigma_nT = sqrt of its first three diagonal entries (stored as columns for sqlite3 users).
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

struct CalibrationRecord {
  int64_t id = 0;  // assigned by append()
  std::string sat_id;
  std::string method;  // "ukf", "ekf", "centered", "twostep"
  int64_t utime = 0;   // time the estimate refers to
  int64_t window_start_utime = 0;
  int64_t window_end_utime = 0;
  int32_t n_samples = 0;
  std::array<double, 3> bias_nT{};
  std::array<double, 6> D{};  // D11 D22 D33 D12 D13 D23
  std::array<double, 45> cov{};
  std::array<double, 3> bias_sigma_nT{};  // filled by append() from cov
  bool has_alignment = false;
  std::array<double, 9> R_sensor_from_body{1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major
  // Schema 5, with an alignment: covariance of the rotation error (rotation vector, sensor frame,
  // rad^2; pipeline/calibration_result.hpp AlignmentEstimate) in the order 11 22 33 12 13 23 (as
  // D). nullopt: no alignment, or unknown (rows stored before schema 5).
  std::optional<std::array<double, 6>> alignment_covariance_rad2;
  double residual_rms_nT = 0.0;
  int status = 0;  // calibration_t.status: 0 ok, 1 not converged, 2 unobservable, 3 failed,
                   // 4 rejected by acceptance gates
  std::string verdict = "accepted";  // "accepted" | "rejected"
  std::vector<std::string> rejection_reasons;
  int iterations = 0;
  // Uncertainty evidence (schema 3; NaN / -1 = NULL = unknown; estimation.md section 7).
  double noise_scale = std::numeric_limits<double>::quiet_NaN();
  double residual_autocorrelation = std::numeric_limits<double>::quiet_NaN();
  int covariance_lag_window = -1;  // -1: unknown
  double residual_rms_all_nT = std::numeric_limits<double>::quiet_NaN();
  int has_nonlinearity = -1;  // -1 unknown, 0 no, 1 yes (then k3 holds the coefficients)
  std::array<double, 3> k3{std::numeric_limits<double>::quiet_NaN(),
                           std::numeric_limits<double>::quiet_NaN(),
                           std::numeric_limits<double>::quiet_NaN()};
  double nis_mean = std::numeric_limits<double>::quiet_NaN();
  double measurement_noise_nT = std::numeric_limits<double>::quiet_NaN();
  // Refits (schema 4): p_9 - p, the model error an online filter re-anchored on it takes
  // (CalibrationResult::model_error); zero when none or unknown.
  std::array<double, 9> model_error{};
  // Refits (schema 11): the bias's variance about its window average where the window's
  // short-block biases show it moving (CalibrationResult::bias_variability_nT2), nT^2 per axis;
  // zero when none or unknown.
  std::array<double, 3> bias_variability_nT2{};
  // Bias temperature model: b(T) = bias_nT + k_T (T - reference_temperature_C), so
  // bias_nT is the bias at reference_temperature_C. -1 unknown / not modelled (NULL), 0 a refit
  // whose data did not support it, 1 modelled (then the fields below are set).
  int has_temperature_model = -1;
  double reference_temperature_C = std::numeric_limits<double>::quiet_NaN();
  std::array<double, 3> temperature_coefficient_nT_per_C{std::numeric_limits<double>::quiet_NaN(),
                                                         std::numeric_limits<double>::quiet_NaN(),
                                                         std::numeric_limits<double>::quiet_NaN()};
  // Covariance of k_T, (nT/degC)^2, upper triangle row-major: xx xy xz yy yz zz.
  std::array<double, 6> temperature_coefficient_cov{};
  // Online results that applied a refit's model: that refit's id (0: none, or a refit's own).
  int64_t temperature_model_refit_id = 0;
  // Linear bias rate (schema 10): b(t) = bias_nT + r (t - window_end_utime), so bias_nT is the
  // bias at the window's end. -1 unknown / not modelled (NULL), 0 a refit whose data did not
  // support it, 1 modelled (then the fields below are set).
  int has_bias_rate = -1;
  std::array<double, 3> bias_rate_nT_per_h{std::numeric_limits<double>::quiet_NaN(),
                                           std::numeric_limits<double>::quiet_NaN(),
                                           std::numeric_limits<double>::quiet_NaN()};
  // Covariance of r, (nT/h)^2: xx yy zz xy xz yz (pack_symmetric).
  std::array<double, 6> bias_rate_cov{};
  // Schema 12: the field error the result leaves on its window (pipeline/field_error.hpp), rms
  // and worst of the direction error (deg) and of the magnitude error (nT); NaN (NULL): not
  // computed (filter snapshots, rows stored before schema 12, a window without directions).
  double field_direction_error_rms_deg = std::numeric_limits<double>::quiet_NaN();
  double field_direction_error_worst_deg = std::numeric_limits<double>::quiet_NaN();
  double field_magnitude_error_rms_nT = std::numeric_limits<double>::quiet_NaN();
  double field_magnitude_error_worst_nT = std::numeric_limits<double>::quiet_NaN();
  std::string software_version;  // empty: this build's MAGCAL_VERSION
  int64_t created_utime = 0;     // 0: wall-clock now
};

// "ok", "not_converged", "unobservable", "failed", "rejected" (design.md); "unknown" otherwise.
const char* status_name(int status);
// Index of (i, j) in a row-major upper triangle of a 9x9 matrix (i, j in any order).
constexpr int cov_index(int i, int j) {
  return i <= j ? i * 9 - i * (i - 1) / 2 + (j - i) : cov_index(j, i);
}
// True for the offline methods ("centered", "twostep"): a refit; false for online filters.
bool is_refit_method(std::string_view method);

struct HistoryQuery {
  std::string sat_id;
  std::string method;                  // empty: all methods
  std::optional<int64_t> since_utime;  // inclusive
  std::optional<int64_t> until_utime;  // inclusive
  std::optional<int> limit;            // only the N newest (by utime)...
  bool descending = false;             // ...returned in this order
};

class CalibrationHistory {
 public:
  virtual ~CalibrationHistory() = default;

  // Stores one result; returns its id. Throws StorageError.
  virtual int64_t append(const CalibrationRecord& record) = 0;
  // Stores every record, in order, without returning their ids (the UKF snapshots of a commit:
  // nothing refers to them). On PostgreSQL a few statements for the lot instead of a round trip
  // each. Throws StorageError (call it inside a transaction to store all or nothing).
  virtual void append_all(std::span<const CalibrationRecord> records);
  virtual std::vector<CalibrationRecord> query(const HistoryQuery& q) = 0;

  virtual std::optional<CalibrationRecord> latest(std::string_view sat_id,
                                                  std::string_view method) = 0;
  virtual std::optional<CalibrationRecord> get(int64_t id) = 0;
  // Newest refit (centered or twostep), any verdict / only accepted ones.
  std::optional<CalibrationRecord> latest_refit(std::string_view sat_id);
  std::optional<CalibrationRecord> latest_accepted_refit(std::string_view sat_id);
  // Newest accepted refit whose window spans at least min_window_span_utime (end - start) and
  // holds at least min_samples samples: the reference later full-window refits are judged by.
  virtual std::optional<CalibrationRecord> latest_accepted_refit(std::string_view sat_id,
                                                                 int64_t min_window_span_utime,
                                                                 int min_samples) = 0;
  // The newest refit with an earlier data time than the newest one (any verdict): the window
  // before. Refits at the newest one's data time (a manual refit run again) are skipped, as
  // they fit the same window.
  std::optional<CalibrationRecord> previous_refit(std::string_view sat_id);
  // Spacecraft with at least one stored result, sorted.
  virtual std::vector<std::string> spacecraft() = 0;

 protected:
  // The newest refit of sat_id (any verdict) at or before until_utime (data time).
  virtual std::optional<CalibrationRecord> newest_refit_until(std::string_view sat_id,
                                                              int64_t until_utime) = 0;
};

}  // namespace magcal::storage
