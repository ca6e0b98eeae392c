#include "storage/calibration_history.hpp"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>

#ifndef MAGCAL_VERSION
#define MAGCAL_VERSION "unknown"
#endif

namespace magcal::storage {
namespace {

static_assert(std::endian::native == std::endian::little,
              "BLOBs hold little-endian doubles; add byte swapping for this platform");

constexpr const char* kSelect =
    "SELECT id, sat_id, method, utime, window_start_utime, window_end_utime, n_samples, "
    "bias_x_nT, bias_y_nT, bias_z_nT, bias_sigma_x_nT, bias_sigma_y_nT, bias_sigma_z_nT, "
    "D11, D22, D33, D12, D13, D23, cov, has_alignment, R11, R12, R13, R21, R22, R23, R31, R32, "
    "R33, residual_rms_nT, status, verdict, rejection_reasons, iterations, software_version, "
    "created_utime, noise_scale, residual_autocorrelation, covariance_lag_window, "
    "residual_rms_all_nT, has_nonlinearity, k3_x, k3_y, k3_z, nis_mean, measurement_noise_nT, "
    "model_error, alignment_covariance_rad2, has_temperature_model, reference_temperature_C, "
    "temperature_coefficient_x_nT_per_C, temperature_coefficient_y_nT_per_C, "
    "temperature_coefficient_z_nT_per_C, temperature_coefficient_cov, temperature_model_refit_id "
    "FROM calibrations ";
constexpr const char* kRefitMethods = "method IN ('centered', 'twostep')";

std::string sql(const std::string& tail) {
  return std::string(kSelect) + tail;
}

int64_t now_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// JSON array of strings (the schema's rejection_reasons), so sqlite3 users get json_each().
std::string json_string_array(const std::vector<std::string>& items) {
  std::string out = "[";
  for (size_t k = 0; k < items.size(); ++k) {
    if (k) out += ',';
    out += '"';
    for (const char c : items[k]) {
      switch (c) {
        case '"':
          out += "\\\"";
          break;
        case '\\':
          out += "\\\\";
          break;
        case '\n':
          out += "\\n";
          break;
        case '\t':
          out += "\\t";
          break;
        case '\r':
          out += "\\r";
          break;
        default:
          if (static_cast<unsigned char>(c) < 0x20) {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\u%04x", c);
            out += buf;
          } else {
            out += c;
          }
      }
    }
    out += '"';
  }
  return out + "]";
}

}  // namespace

const char* status_name(int status) {
  switch (status) {
    case 0:
      return "ok";
    case 1:
      return "not_converged";
    case 2:
      return "unobservable";
    case 3:
      return "failed";
    case 4:
      return "rejected";
    default:
      return "unknown";
  }
}

bool is_refit_method(std::string_view method) {
  return method == "centered" || method == "twostep";
}

CalibrationHistory::CalibrationHistory(Database& db)
    : db_(db),
      insert_(db,
              "INSERT INTO calibrations (sat_id, method, utime, window_start_utime, "
              "window_end_utime, n_samples, bias_x_nT, bias_y_nT, bias_z_nT, bias_sigma_x_nT, "
              "bias_sigma_y_nT, bias_sigma_z_nT, D11, D22, D33, D12, D13, D23, cov, "
              "has_alignment, R11, R12, R13, R21, R22, R23, R31, R32, R33, residual_rms_nT, "
              "status, verdict, rejection_reasons, iterations, software_version, created_utime, "
              "noise_scale, residual_autocorrelation, covariance_lag_window, residual_rms_all_nT, "
              "has_nonlinearity, k3_x, k3_y, k3_z, nis_mean, measurement_noise_nT, model_error, "
              "alignment_covariance_rad2, has_temperature_model, reference_temperature_C, "
              "temperature_coefficient_x_nT_per_C, temperature_coefficient_y_nT_per_C, "
              "temperature_coefficient_z_nT_per_C, temperature_coefficient_cov, "
              "temperature_model_refit_id) "
              "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, "
              "?17, ?18, ?19, ?20, ?21, ?22, ?23, ?24, ?25, ?26, ?27, ?28, ?29, ?30, ?31, ?32, "
              "?33, ?34, ?35, ?36, ?37, ?38, ?39, ?40, ?41, ?42, ?43, ?44, ?45, ?46, ?47, ?48, "
              "?49, ?50, ?51, ?52, ?53, ?54, ?55)"),
      query_all_(db, sql("WHERE sat_id = ?1 AND utime >= ?2 AND utime <= ?3 "
                         "ORDER BY utime DESC, id DESC LIMIT ?4")),
      query_method_(db, sql("WHERE sat_id = ?1 AND utime >= ?2 AND utime <= ?3 AND method = ?5 "
                            "ORDER BY utime DESC, id DESC LIMIT ?4")),
      latest_(db, sql("WHERE sat_id = ?1 AND method = ?2 ORDER BY utime DESC, id DESC LIMIT 1")),
      get_(db, sql("WHERE id = ?1")),
      refits_(db, sql(std::string("WHERE sat_id = ?1 AND ") + kRefitMethods +
                      " ORDER BY utime DESC, id DESC LIMIT 2")),
      accepted_refit_(
          db, sql(std::string("WHERE sat_id = ?1 AND ") + kRefitMethods +
                  " AND verdict = 'accepted' AND window_end_utime - window_start_utime >= ?2 "
                  "AND n_samples >= ?3 ORDER BY utime DESC, id DESC LIMIT 1")),
      spacecraft_(db, "SELECT DISTINCT sat_id FROM calibrations ORDER BY sat_id"),
      reasons_(db, "SELECT value FROM json_each(?1)") {}

int64_t CalibrationHistory::append(const CalibrationRecord& r) {
  if (r.verdict != "accepted" && r.verdict != "rejected") {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "verdict must be 'accepted' or 'rejected', not '" + r.verdict + "'");
  }
  if (r.status < 0 || r.status > 4) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "status out of range: " + std::to_string(r.status));
  }
  auto use = insert_.use();
  insert_.bind(1, r.sat_id).bind(2, r.method).bind(3, r.utime);
  insert_.bind(4, r.window_start_utime).bind(5, r.window_end_utime).bind(6, r.n_samples);
  for (int i = 0; i < 3; ++i) insert_.bind(7 + i, r.bias_nT[i]);
  // Derived from cov, never taken from the caller: one source of truth.
  for (int i = 0; i < 3; ++i) insert_.bind(10 + i, std::sqrt(r.cov[cov_index(i, i)]));
  for (int i = 0; i < 6; ++i) insert_.bind(13 + i, r.D[i]);
  insert_.bind_blob(19, r.cov.data(), sizeof(double) * r.cov.size());
  insert_.bind(20, r.has_alignment ? 1 : 0);
  if (r.has_alignment) {
    for (int i = 0; i < 9; ++i) insert_.bind(21 + i, r.R_sensor_from_body[i]);
  }
  insert_.bind(30, r.residual_rms_nT).bind(31, r.status).bind(32, r.verdict);
  insert_.bind(33, json_string_array(r.rejection_reasons)).bind(34, r.iterations);
  insert_.bind(35, r.software_version.empty() ? std::string_view(MAGCAL_VERSION)
                                              : std::string_view(r.software_version));
  insert_.bind(36, r.created_utime != 0 ? r.created_utime : now_utime());
  // NaN binds as NULL; negative integer codes mean unknown.
  insert_.bind(37, r.noise_scale).bind(38, r.residual_autocorrelation);
  if (r.covariance_lag_window >= 0)
    insert_.bind(39, r.covariance_lag_window);
  else
    insert_.bind_null(39);
  insert_.bind(40, r.residual_rms_all_nT);
  if (r.has_nonlinearity >= 0)
    insert_.bind(41, r.has_nonlinearity != 0 ? 1 : 0);
  else
    insert_.bind_null(41);
  for (int i = 0; i < 3; ++i) {
    if (r.has_nonlinearity == 1)
      insert_.bind(42 + i, r.k3[static_cast<size_t>(i)]);
    else
      insert_.bind_null(42 + i);
  }
  insert_.bind(45, r.nis_mean).bind(46, r.measurement_noise_nT);
  if (std::any_of(r.model_error.begin(), r.model_error.end(), [](double v) { return v != 0.0; }))
    insert_.bind_blob(47, r.model_error.data(), sizeof(double) * r.model_error.size());
  else
    insert_.bind_null(47);
  if (r.has_alignment && r.alignment_covariance_rad2) {
    insert_.bind_blob(48, r.alignment_covariance_rad2->data(),
                      sizeof(double) * r.alignment_covariance_rad2->size());
  } else {
    insert_.bind_null(48);
  }
  const bool temperature_model = r.has_temperature_model == 1;
  if (r.has_temperature_model >= 0)
    insert_.bind(49, temperature_model ? 1 : 0);
  else
    insert_.bind_null(49);
  // Without a model its numbers are NULL whatever the record holds (NaN binds as NULL too).
  const double unknown = std::numeric_limits<double>::quiet_NaN();
  insert_.bind(50, temperature_model ? r.reference_temperature_C : unknown);
  for (int i = 0; i < 3; ++i)
    insert_.bind(51 + i, temperature_model ? r.temperature_coefficient_nT_per_C[i] : unknown);
  if (temperature_model) {
    insert_.bind_blob(54, r.temperature_coefficient_cov.data(),
                      sizeof(double) * r.temperature_coefficient_cov.size());
  } else {
    insert_.bind_null(54);
  }
  if (temperature_model && r.temperature_model_refit_id > 0)
    insert_.bind(55, r.temperature_model_refit_id);
  else
    insert_.bind_null(55);
  insert_.execute();
  return db_.last_insert_id();
}

CalibrationRecord CalibrationHistory::read_row(Statement& st) {
  CalibrationRecord r;
  r.id = st.column_int64(0);
  r.sat_id = st.column_text(1);
  r.method = st.column_text(2);
  r.utime = st.column_int64(3);
  r.window_start_utime = st.column_int64(4);
  r.window_end_utime = st.column_int64(5);
  r.n_samples = static_cast<int32_t>(st.column_int64(6));
  for (int i = 0; i < 3; ++i) r.bias_nT[i] = st.column_double(7 + i);
  for (int i = 0; i < 3; ++i) r.bias_sigma_nT[i] = st.column_double(10 + i);
  for (int i = 0; i < 6; ++i) r.D[i] = st.column_double(13 + i);
  const auto blob = st.column_blob(19);
  if (blob.size() != sizeof(double) * r.cov.size()) {
    throw StorageError(StorageError::Kind::kEngine,
                       "calibrations.cov of row " + std::to_string(r.id) + " has " +
                           std::to_string(blob.size()) + " bytes, expected 360");
  }
  std::memcpy(r.cov.data(), blob.data(), blob.size());
  r.has_alignment = st.column_int64(20) != 0;
  if (r.has_alignment) {
    for (int i = 0; i < 9; ++i) r.R_sensor_from_body[i] = st.column_double(21 + i);
  }
  r.residual_rms_nT = st.column_double(30);
  r.status = static_cast<int>(st.column_int64(31));
  r.verdict = st.column_text(32);
  {
    auto use = reasons_.use();
    reasons_.bind(1, st.column_text_view(33));
    while (reasons_.step()) r.rejection_reasons.push_back(reasons_.column_text(0));
  }
  r.iterations = static_cast<int>(st.column_int64(34));
  r.software_version = st.column_text(35);
  r.created_utime = st.column_int64(36);
  r.noise_scale = st.column_double(37);
  r.residual_autocorrelation = st.column_double(38);
  r.covariance_lag_window = st.is_null(39) ? -1 : static_cast<int>(st.column_int64(39));
  r.residual_rms_all_nT = st.column_double(40);
  r.has_nonlinearity = st.is_null(41) ? -1 : (st.column_int64(41) != 0 ? 1 : 0);
  for (int i = 0; i < 3; ++i) r.k3[static_cast<size_t>(i)] = st.column_double(42 + i);
  r.nis_mean = st.column_double(45);
  r.measurement_noise_nT = st.column_double(46);
  if (const auto model_error = st.column_blob(47); !model_error.empty()) {  // NULL: zero
    if (model_error.size() != sizeof(double) * r.model_error.size()) {
      throw StorageError(StorageError::Kind::kEngine,
                         "calibrations.model_error of row " + std::to_string(r.id) + " has " +
                             std::to_string(model_error.size()) + " bytes, expected 72");
    }
    std::memcpy(r.model_error.data(), model_error.data(), model_error.size());
  }
  if (const auto covariance = st.column_blob(48); r.has_alignment && !covariance.empty()) {
    std::array<double, 6> c{};
    if (covariance.size() != sizeof(double) * c.size()) {
      throw StorageError(StorageError::Kind::kEngine,
                         "calibrations.alignment_covariance_rad2 of row " + std::to_string(r.id) +
                             " has " + std::to_string(covariance.size()) + " bytes, expected 48");
    }
    std::memcpy(c.data(), covariance.data(), covariance.size());
    r.alignment_covariance_rad2 = c;
  }
  r.has_temperature_model = st.is_null(49) ? -1 : (st.column_int64(49) != 0 ? 1 : 0);
  if (r.has_temperature_model == 1) {
    r.reference_temperature_C = st.column_double(50);
    for (int i = 0; i < 3; ++i) r.temperature_coefficient_nT_per_C[i] = st.column_double(51 + i);
    const auto cov = st.column_blob(54);
    if (cov.size() != sizeof(double) * r.temperature_coefficient_cov.size()) {
      throw StorageError(StorageError::Kind::kEngine,
                         "calibrations.temperature_coefficient_cov of row " + std::to_string(r.id) +
                             " has " + std::to_string(cov.size()) + " bytes, expected 48");
    }
    std::memcpy(r.temperature_coefficient_cov.data(), cov.data(), cov.size());
    r.temperature_model_refit_id = st.is_null(55) ? 0 : st.column_int64(55);
  }
  return r;
}

std::vector<CalibrationRecord> CalibrationHistory::query(const HistoryQuery& q) {
  Statement& st = q.method.empty() ? query_all_ : query_method_;
  std::vector<CalibrationRecord> out;
  {
    auto use = st.use();
    st.bind(1, q.sat_id);
    st.bind(2, q.since_utime.value_or(std::numeric_limits<int64_t>::min()));
    st.bind(3, q.until_utime.value_or(std::numeric_limits<int64_t>::max()));
    st.bind(4, q.limit ? static_cast<int64_t>(*q.limit) : int64_t{-1});  // -1: no limit
    if (!q.method.empty()) st.bind(5, q.method);
    while (st.step()) out.push_back(read_row(st));
  }
  // Selected newest first (so LIMIT keeps the newest); printed in the asked order.
  if (!q.descending) std::reverse(out.begin(), out.end());
  return out;
}

std::optional<CalibrationRecord> CalibrationHistory::first(Statement& st) {
  if (!st.step()) return std::nullopt;
  return read_row(st);
}

std::optional<CalibrationRecord> CalibrationHistory::latest(std::string_view sat_id,
                                                            std::string_view method) {
  auto use = latest_.use();
  latest_.bind(1, sat_id).bind(2, method);
  return first(latest_);
}

std::optional<CalibrationRecord> CalibrationHistory::get(int64_t id) {
  auto use = get_.use();
  get_.bind(1, id);
  return first(get_);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_refit(std::string_view sat_id) {
  auto use = refits_.use();
  refits_.bind(1, sat_id);
  return first(refits_);
}

std::optional<CalibrationRecord> CalibrationHistory::previous_refit(std::string_view sat_id) {
  auto use = refits_.use();
  refits_.bind(1, sat_id);
  if (!refits_.step()) return std::nullopt;
  return first(refits_);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_accepted_refit(
    std::string_view sat_id, int64_t min_window_span_utime, int min_samples) {
  auto use = accepted_refit_.use();
  accepted_refit_.bind(1, sat_id).bind(2, min_window_span_utime).bind(3, int64_t{min_samples});
  return first(accepted_refit_);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_accepted_refit(
    std::string_view sat_id) {
  return latest_accepted_refit(sat_id, std::numeric_limits<int64_t>::min(), 0);
}

std::vector<std::string> CalibrationHistory::spacecraft() {
  std::vector<std::string> out;
  auto use = spacecraft_.use();
  while (spacecraft_.step()) out.push_back(spacecraft_.column_text(0));
  return out;
}

}  // namespace magcal::storage
