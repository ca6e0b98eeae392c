// One `calibrations` row, the same on both backends (storage/calibration_history.hpp): the
// columns, what an append stores for a CalibrationRecord (derived values, NULL for unknown or
// absent) and how a row reads back. Each backend supplies only its binding and its row access,
// so the NULL rules live here once. Internal to storage/.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/blob_doubles.hpp"
#include "storage/calibration_history.hpp"

namespace magcal::storage::calibration_row {

// What an append binds, in order (kInsertValues values); a read selects `id, ` + these.
inline constexpr const char* kInsertColumns =
    "sat_id, method, utime, window_start_utime, window_end_utime, n_samples, bias_x_nT, "
    "bias_y_nT, bias_z_nT, bias_sigma_x_nT, bias_sigma_y_nT, bias_sigma_z_nT, D11, D22, D33, D12, "
    "D13, D23, cov, has_alignment, R11, R12, R13, R21, R22, R23, R31, R32, R33, residual_rms_nT, "
    "status, verdict, rejection_reasons, iterations, software_version, created_utime, "
    "noise_scale, residual_autocorrelation, covariance_lag_window, residual_rms_all_nT, "
    "has_nonlinearity, k3_x, k3_y, k3_z, nis_mean, measurement_noise_nT, model_error, "
    "alignment_covariance_rad2, has_temperature_model, reference_temperature_C, "
    "temperature_coefficient_x_nT_per_C, temperature_coefficient_y_nT_per_C, "
    "temperature_coefficient_z_nT_per_C, temperature_coefficient_cov, temperature_model_refit_id, "
    "has_bias_rate, bias_rate_x_nT_per_h, bias_rate_y_nT_per_h, bias_rate_z_nT_per_h, "
    "bias_rate_cov, bias_variability_nT2, field_direction_error_rms_deg, "
    "field_direction_error_worst_deg, field_magnitude_error_rms_nT, field_magnitude_error_worst_nT";
inline constexpr int kInsertValues = 65;
// `SELECT <kSelectColumns> FROM calibrations ...`: id, then kInsertColumns.
inline std::string select_sql(std::string_view tail) {
  return std::string("SELECT id, ") + kInsertColumns + " FROM calibrations " + std::string(tail);
}
inline constexpr const char* kRefitMethods = "method IN ('centered', 'twostep')";

// Throws StorageError (kInvalidArgument) for a record the table refuses.
void check_appendable(const CalibrationRecord& r);
// JSON array of strings (the column rejection_reasons), so sqlite3 and psql users can query it.
std::string json_string_array(const std::vector<std::string>& items);
// The record's created_utime, or now when it is 0.
int64_t created_utime(const CalibrationRecord& r);
// The record's software_version, or this build's MAGCAL_VERSION when it is empty.
std::string_view software_version(const CalibrationRecord& r);

// Writes the kInsertValues values of `r` into `out`, in kInsertColumns order. Sink:
//   integer(int64_t), real(double) (NaN: NULL), text(std::string_view),
//   doubles(std::span<const double>) (a blob), null().
// `reasons_json`: json_string_array(r.rejection_reasons), kept alive by the caller.
template <typename Sink>
void write(const CalibrationRecord& r, const std::string& reasons_json, Sink& out) {
  constexpr double kUnknown = std::numeric_limits<double>::quiet_NaN();
  out.text(r.sat_id);
  out.text(r.method);
  out.integer(r.utime);
  out.integer(r.window_start_utime);
  out.integer(r.window_end_utime);
  out.integer(r.n_samples);
  for (int i = 0; i < 3; ++i) out.real(r.bias_nT[i]);
  // Derived from cov, never taken from the caller: one source of truth.
  for (int i = 0; i < 3; ++i) out.real(std::sqrt(r.cov[cov_index(i, i)]));
  for (int i = 0; i < 6; ++i) out.real(r.D[i]);
  out.doubles(r.cov);
  out.integer(r.has_alignment ? 1 : 0);
  for (int i = 0; i < 9; ++i) {
    if (r.has_alignment) {
      out.real(r.R_sensor_from_body[i]);
    } else {
      out.null();
    }
  }
  out.real(r.residual_rms_nT);
  out.integer(r.status);
  out.text(r.verdict);
  out.text(reasons_json);
  out.integer(r.iterations);
  out.text(software_version(r));
  out.integer(created_utime(r));
  // NaN is NULL; negative integer codes mean unknown.
  out.real(r.noise_scale);
  out.real(r.residual_autocorrelation);
  if (r.covariance_lag_window >= 0) {
    out.integer(r.covariance_lag_window);
  } else {
    out.null();
  }
  out.real(r.residual_rms_all_nT);
  if (r.has_nonlinearity >= 0) {
    out.integer(r.has_nonlinearity != 0 ? 1 : 0);
  } else {
    out.null();
  }
  for (int i = 0; i < 3; ++i) out.real(r.has_nonlinearity == 1 ? r.k3[i] : kUnknown);
  out.real(r.nis_mean);
  out.real(r.measurement_noise_nT);
  if (std::any_of(r.model_error.begin(), r.model_error.end(), [](double v) { return v != 0.0; })) {
    out.doubles(r.model_error);
  } else {
    out.null();
  }
  if (r.has_alignment && r.alignment_covariance_rad2) {
    out.doubles(*r.alignment_covariance_rad2);
  } else {
    out.null();
  }
  // Without a model its numbers are NULL whatever the record holds.
  const bool temperature_model = r.has_temperature_model == 1;
  if (r.has_temperature_model >= 0) {
    out.integer(temperature_model ? 1 : 0);
  } else {
    out.null();
  }
  out.real(temperature_model ? r.reference_temperature_C : kUnknown);
  for (int i = 0; i < 3; ++i) {
    out.real(temperature_model ? r.temperature_coefficient_nT_per_C[i] : kUnknown);
  }
  if (temperature_model) {
    out.doubles(r.temperature_coefficient_cov);
  } else {
    out.null();
  }
  if (temperature_model && r.temperature_model_refit_id > 0) {
    out.integer(r.temperature_model_refit_id);
  } else {
    out.null();
  }
  const bool bias_rate = r.has_bias_rate == 1;
  if (r.has_bias_rate >= 0) {
    out.integer(bias_rate ? 1 : 0);
  } else {
    out.null();
  }
  for (int i = 0; i < 3; ++i) out.real(bias_rate ? r.bias_rate_nT_per_h[i] : kUnknown);
  if (bias_rate) {
    out.doubles(r.bias_rate_cov);
  } else {
    out.null();
  }
  if (std::any_of(r.bias_variability_nT2.begin(), r.bias_variability_nT2.end(),
                  [](double v) { return v != 0.0; })) {
    out.doubles(r.bias_variability_nT2);
  } else {
    out.null();
  }
  out.real(r.field_direction_error_rms_deg);
  out.real(r.field_direction_error_worst_deg);
  out.real(r.field_magnitude_error_rms_nT);
  out.real(r.field_magnitude_error_worst_nT);
}

// A row of `SELECT select_sql(...)` read back. Row:
//   is_null(c), integer(c), real(c) (NULL: NaN), text(c), and
//   blob(c, std::span<double> out, const std::string& what) -> false when NULL, else exactly
//   out.size() doubles (doubles_from_blob).
// `reasons(json_text)`: the strings of a rejection_reasons JSON array (each backend's own
// JSON functions read it).
template <typename Row, typename Reasons>
CalibrationRecord read(Row& row, Reasons&& reasons) {
  CalibrationRecord r;
  r.id = row.integer(0);
  const auto what = [&r](const char* column) {
    return std::string("calibrations.") + column + " of row " + std::to_string(r.id);
  };
  r.sat_id = row.text(1);
  r.method = row.text(2);
  r.utime = row.integer(3);
  r.window_start_utime = row.integer(4);
  r.window_end_utime = row.integer(5);
  r.n_samples = static_cast<int32_t>(row.integer(6));
  for (int i = 0; i < 3; ++i) r.bias_nT[i] = row.real(7 + i);
  for (int i = 0; i < 3; ++i) r.bias_sigma_nT[i] = row.real(10 + i);
  for (int i = 0; i < 6; ++i) r.D[i] = row.real(13 + i);
  if (!row.blob(19, r.cov, what("cov"))) doubles_from_blob(nullptr, 0, r.cov, what("cov"));
  r.has_alignment = row.integer(20) != 0;
  if (r.has_alignment) {
    for (int i = 0; i < 9; ++i) r.R_sensor_from_body[i] = row.real(21 + i);
  }
  r.residual_rms_nT = row.real(30);
  r.status = static_cast<int>(row.integer(31));
  r.verdict = row.text(32);
  r.rejection_reasons = reasons(row.text(33));
  r.iterations = static_cast<int>(row.integer(34));
  r.software_version = row.text(35);
  r.created_utime = row.integer(36);
  r.noise_scale = row.real(37);
  r.residual_autocorrelation = row.real(38);
  r.covariance_lag_window = row.is_null(39) ? -1 : static_cast<int>(row.integer(39));
  r.residual_rms_all_nT = row.real(40);
  r.has_nonlinearity = row.is_null(41) ? -1 : (row.integer(41) != 0 ? 1 : 0);
  for (int i = 0; i < 3; ++i) r.k3[i] = row.real(42 + i);
  r.nis_mean = row.real(45);
  r.measurement_noise_nT = row.real(46);
  if (!row.blob(47, r.model_error, what("model_error"))) r.model_error = {};  // NULL: zero
  if (std::array<double, 6> c{};
      r.has_alignment && row.blob(48, c, what("alignment_covariance_rad2"))) {
    r.alignment_covariance_rad2 = c;  // NULL: unknown (stored before schema 5)
  }
  r.has_temperature_model = row.is_null(49) ? -1 : (row.integer(49) != 0 ? 1 : 0);
  if (r.has_temperature_model == 1) {
    r.reference_temperature_C = row.real(50);
    for (int i = 0; i < 3; ++i) r.temperature_coefficient_nT_per_C[i] = row.real(51 + i);
    const std::string cov = what("temperature_coefficient_cov");
    if (!row.blob(54, r.temperature_coefficient_cov, cov)) {
      doubles_from_blob(nullptr, 0, r.temperature_coefficient_cov, cov);  // NULL: corrupt
    }
    r.temperature_model_refit_id = row.is_null(55) ? 0 : row.integer(55);
  }
  r.has_bias_rate = row.is_null(56) ? -1 : (row.integer(56) != 0 ? 1 : 0);
  if (r.has_bias_rate == 1) {
    for (int i = 0; i < 3; ++i) r.bias_rate_nT_per_h[i] = row.real(57 + i);
    const std::string cov = what("bias_rate_cov");
    if (!row.blob(60, r.bias_rate_cov, cov)) {
      doubles_from_blob(nullptr, 0, r.bias_rate_cov, cov);  // NULL: corrupt
    }
  }
  if (!row.blob(61, r.bias_variability_nT2, what("bias_variability_nT2"))) {
    r.bias_variability_nT2 = {};  // NULL: none
  }
  r.field_direction_error_rms_deg = row.real(62);
  r.field_direction_error_worst_deg = row.real(63);
  r.field_magnitude_error_rms_nT = row.real(64);
  r.field_magnitude_error_worst_nT = row.real(65);
  return r;
}

}  // namespace magcal::storage::calibration_row
