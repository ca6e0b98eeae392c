#include "service/io/history_report.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>
#include <optional>
#include <tuple>

#include "pipeline/roll_pitch_yaw_report.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/printf_string.hpp"
#include "service/io/result_json.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

namespace {

// Shortest text that reads back to the same double; empty for NaN (absent).
std::string csv_number(double v) {
  if (v != v) return "";
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

std::string csv_quoted(const std::string& s) {
  if (s.find_first_of(",\"\n\r") == std::string::npos) return s;
  std::string out = "\"";
  for (const char c : s) {
    if (c == '"') out += '"';
    out += c;
  }
  return out + '"';
}

// "D11_sigma,...,D23_sigma,cov_b1_b1,cov_b1_b2,...,cov_D23_D23": the D sigmas, then the
// covariance of p = [b1 b2 b3 D11 D22 D33 D12 D13 D23] as its upper triangle, row-major (the
// order of storage::cov_index).
std::string covariance_csv_header() {
  static constexpr const char* kNames[9] = {"b1",  "b2",  "b3",  "D11", "D22",
                                            "D33", "D12", "D13", "D23"};
  std::string header;
  for (int i = 3; i < 9; ++i) header += std::string(i == 3 ? "" : ",") + kNames[i] + "_sigma";
  for (int i = 0; i < 9; ++i) {
    for (int j = i; j < 9; ++j) header += std::string(",cov_") + kNames[i] + "_" + kNames[j];
  }
  return header;
}

// The 1-sigma of p_i (sqrt of the covariance's diagonal; NaN where it is not a variance).
double parameter_sigma(const storage::CalibrationRecord& r, int i) {
  const double var = r.cov[storage::cov_index(i, i)];
  return var >= 0.0 ? std::sqrt(var) : std::numeric_limits<double>::quiet_NaN();
}

bool known_method(const std::string& m) {
  return m == "ukf" || m == "ekf" || m == "centered" || m == "twostep";
}

}  // namespace

std::optional<storage::HistoryQuery> parse_history_request(const HistoryRequest& request,
                                                           const std::string& option_prefix,
                                                           std::string* error) {
  storage::HistoryQuery q;
  q.sat_id = request.sat;
  if (!request.method.empty() && !known_method(request.method)) {
    *error = "unknown " + option_prefix + "method '" + request.method +
             "' (ukf, ekf, centered, twostep)";
    return std::nullopt;
  }
  q.method = request.method;
  for (auto [text, out, name] : {std::tuple{&request.since, &q.since_utime, "since"},
                                 std::tuple{&request.until, &q.until_utime, "until"}}) {
    if (text->empty()) continue;
    *out = parse_iso8601_utc(*text);
    if (!*out) {
      *error = option_prefix + name + " '" + *text +
               "' is not an ISO 8601 UTC time (e.g. 2026-01-01T12:00:00Z)";
      return std::nullopt;
    }
  }
  // Both bounds are inclusive: since > until selects nothing, which is a mistake, not a query.
  if (q.since_utime && q.until_utime && *q.since_utime > *q.until_utime) {
    *error = option_prefix + "since '" + request.since + "' is after " + option_prefix + "until '" +
             request.until + "'";
    return std::nullopt;
  }
  if (request.limit && *request.limit <= 0) {
    *error = option_prefix + "limit must be at least 1";
    return std::nullopt;
  }
  if (request.order != "asc" && request.order != "desc") {
    *error = option_prefix + "order must be asc or desc";
    return std::nullopt;
  }
  if (request.format != "table" && request.format != "csv" && request.format != "json") {
    *error = option_prefix + "format must be table, csv or json";
    return std::nullopt;
  }
  q.limit = request.limit;
  q.descending = request.order == "desc";
  return q;
}

std::vector<storage::CalibrationRecord> read_history(storage::Connection& db,
                                                     const storage::HistoryQuery& query) {
  storage::Transaction snapshot(db, storage::Transaction::Mode::kReadSnapshot);
  return db.make_calibration_history()->query(query);
}

bool spacecraft_known(storage::Connection& db, const std::string& sat_id) {
  storage::Transaction snapshot(db, storage::Transaction::Mode::kReadSnapshot);
  storage::HistoryQuery any;
  any.sat_id = sat_id;
  any.limit = 1;
  if (!db.make_calibration_history()->query(any).empty()) return true;
  return db.make_sample_window_store()->newest_utime(sat_id).has_value();
}

std::string history_json_text(const std::vector<storage::CalibrationRecord>& rows) {
  nlohmann::json out = nlohmann::json::array();
  for (const auto& r : rows) out.push_back(history_record_json(r));
  return out.dump(2) + "\n";
}

std::string history_csv_text(const std::vector<storage::CalibrationRecord>& rows) {
  std::string text =
      "time,utime,sat_id,method,window_start,window_end,window_start_utime,"
      "window_end_utime,n_samples,bias_x_nT,bias_y_nT,bias_z_nT,bias_sigma_x_nT,"
      "bias_sigma_y_nT,bias_sigma_z_nT,D11,D22,D33,D12,D13,D23,R11,R12,R13,R21,R22,R23,"
      "R31,R32,R33,residual_rms_nT,iterations,status,verdict,rejection_reasons,"
      "software_version,id,noise_scale,residual_autocorrelation,covariance_lag_window,"
      "residual_rms_all_nT,has_nonlinearity,k3_x,k3_y,k3_z,nis_mean,"
      "measurement_noise_nT,alignment_singular,q_sensor_from_body_w,q_sensor_from_body_x,"
      "q_sensor_from_body_y,q_sensor_from_body_z,alignment_roll_deg,alignment_pitch_deg,"
      "alignment_yaw_deg,alignment_sigma_roll_deg,alignment_sigma_pitch_deg,"
      "alignment_sigma_yaw_deg,alignment_determined_sigma_deg,alignment_covariance_11_deg2,"
      "alignment_covariance_22_deg2,alignment_covariance_33_deg2,alignment_covariance_12_deg2,"
      "alignment_covariance_13_deg2,alignment_covariance_23_deg2,has_temperature_model,"
      "reference_temperature_C,temperature_coefficient_x_nT_per_C,"
      "temperature_coefficient_y_nT_per_C,temperature_coefficient_z_nT_per_C,"
      "temperature_coefficient_sigma_x_nT_per_C,temperature_coefficient_sigma_y_nT_per_C,"
      "temperature_coefficient_sigma_z_nT_per_C,temperature_model_refit_id,"
      "alignment_determined_name,alignment_determined_deg,has_bias_rate,bias_rate_x_nT_per_h,"
      "bias_rate_y_nT_per_h,bias_rate_z_nT_per_h,bias_rate_sigma_x_nT_per_h,"
      "bias_rate_sigma_y_nT_per_h,bias_rate_sigma_z_nT_per_h," +
      covariance_csv_header() +
      ",field_direction_error_rms_deg,field_direction_error_worst_deg,"
      "field_magnitude_error_rms_nT,field_magnitude_error_worst_nT\n";
  for (const auto& r : rows) {
    std::string line = history_time(r.utime) + ',' + std::to_string(r.utime) + ',' +
                       csv_quoted(r.sat_id) + ',' + csv_quoted(r.method) + ',' +
                       history_time(r.window_start_utime) + ',' + history_time(r.window_end_utime) +
                       ',' + std::to_string(r.window_start_utime) + ',' +
                       std::to_string(r.window_end_utime) + ',' + std::to_string(r.n_samples);
    for (const double v : r.bias_nT) line += ',' + csv_number(v);
    for (const double v : r.bias_sigma_nT) line += ',' + csv_number(v);
    for (const double v : r.D) line += ',' + csv_number(v);
    for (const double v : r.R_sensor_from_body) {
      line += ',' + (r.has_alignment ? csv_number(v) : std::string());
    }
    std::string reasons;
    for (const auto& reason : r.rejection_reasons)
      reasons += (reasons.empty() ? "" : "; ") + reason;
    line += ',' + csv_number(r.residual_rms_nT) + ',' + std::to_string(r.iterations) + ',' +
            storage::status_name(r.status) + ',' + r.verdict + ',' + csv_quoted(reasons) + ',' +
            csv_quoted(r.software_version) + ',' + std::to_string(r.id);
    // The noise and residual evidence, appended after the design.md columns (empty = unknown).
    line += ',' + csv_number(r.noise_scale) + ',' + csv_number(r.residual_autocorrelation) + ',' +
            (r.covariance_lag_window >= 0 ? std::to_string(r.covariance_lag_window) : "") + ',' +
            csv_number(r.residual_rms_all_nT) + ',' +
            (r.has_nonlinearity >= 0 ? std::to_string(r.has_nonlinearity) : "");
    for (const double v : r.k3) line += ',' + (r.has_nonlinearity == 1 ? csv_number(v) : "");
    line += ',' + csv_number(r.nis_mean) + ',' + csv_number(r.measurement_noise_nT);
    // Appended, empty without an alignment: alignment_singular (1 when roll/yaw are
    // the canonical split near pitch +-90 deg), the quaternion, the angles and their sigmas
    // (empty when unknown: rows stored before schema 5; the combination's sigma only when
    // singular), the rotation-vector covariance in deg^2 (as D: 11 22 33 12 13 23). The same
    // numbers as the JSON keys (result_json.hpp).
    std::optional<RollPitchYawReport> rpy_report;
    if (!r.has_alignment) {
      line += std::string(18, ',');
    } else {
      const AlignmentEstimate a = result_from_record(r).alignment;
      const RollPitchYawReport& rpy = rpy_report.emplace(roll_pitch_yaw_report(
          a.R_sensor_from_body, a.angle_covariance_rad2, kDefaultGimbalLockMargin_deg * kDegToRad));
      line += rpy.singular ? ",1" : ",0";
      for (const double v : quaternion_from_dcm(a.R_sensor_from_body)) line += ',' + csv_number(v);
      for (const double v : {rpy.rpy.roll_rad, rpy.rpy.pitch_rad, rpy.rpy.yaw_rad})
        line += ',' + csv_number(v * kRadToDeg);
      for (const double v : rpy.sigma_rad) line += ',' + csv_number(v * kRadToDeg);
      line += ',' + csv_number(rpy.combination_sigma_rad * kRadToDeg);
      for (const double v : pack_symmetric(a.angle_covariance_rad2))
        line += ',' + csv_number(v * (kRadToDeg * kRadToDeg));
    }
    // Appended: the bias temperature model; bias_x_nT.. are then at its T0.
    line += ',' + (r.has_temperature_model >= 0 ? std::to_string(r.has_temperature_model) : "");
    const bool modelled = r.has_temperature_model == 1;
    line += ',' + (modelled ? csv_number(r.reference_temperature_C) : "");
    for (const double v : r.temperature_coefficient_nT_per_C)
      line += ',' + (modelled ? csv_number(v) : "");
    const Eigen::Vector3d sigma =
        modelled ? result_from_record(r).temperature_coefficient_sigma_nT_per_C()
                 : Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
    for (int i = 0; i < 3; ++i) line += ',' + csv_number(sigma(i));
    line += ',' +
            (r.temperature_model_refit_id > 0 ? std::to_string(r.temperature_model_refit_id) : "");
    // Appended: at gimbal lock the one roll/yaw combination the data determine, by name
    // (yaw_minus_roll, yaw_plus_roll) and value, as the JSON's alignment_determined_deg; empty
    // when not singular.
    if (rpy_report && rpy_report->singular) {
      line += ',' + std::string(rpy_report->combination_name) + ',' +
              csv_number(rpy_report->combination_rad * kRadToDeg);
    } else {
      line += ",,";
    }
    // Appended: the linear bias rate; bias_x_nT.. are then at window_end_utime.
    line += ',' + (r.has_bias_rate >= 0 ? std::to_string(r.has_bias_rate) : "");
    const bool drifting = r.has_bias_rate == 1;
    for (const double v : r.bias_rate_nT_per_h) line += ',' + (drifting ? csv_number(v) : "");
    const Eigen::Vector3d rate_sigma =
        drifting ? result_from_record(r).bias_rate_sigma_nT_per_h()
                 : Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());
    for (int i = 0; i < 3; ++i) line += ',' + csv_number(rate_sigma(i));
    // Appended: the D sigmas and the covariance's upper triangle (as the JSON's D_sigma and
    // covariance; empty where unknown), then the field error on the window.
    for (int i = 3; i < 9; ++i) line += ',' + csv_number(parameter_sigma(r, i));
    for (const double v : r.cov) line += ',' + csv_number(v);
    for (const double v : {r.field_direction_error_rms_deg, r.field_direction_error_worst_deg,
                           r.field_magnitude_error_rms_nT, r.field_magnitude_error_worst_nT})
      line += ',' + csv_number(v);
    text += line + '\n';
  }
  return text;
}

std::string history_table_text(const std::vector<storage::CalibrationRecord>& rows) {
  std::string text;
  append_printf(&text, "%-20s  %-8s  %6s  %27s  %20s  %8s  %-13s  %s\n", "time (UTC)", "method",
                "n", "bias x, y, z (nT)", "1-sigma (nT)", "rms (nT)", "status", "verdict");
  for (const auto& r : rows) {
    append_printf(&text, "%-20s  %-8s  %6d  %8.2f %8.2f %9.2f  %6.2f %6.2f %6.2f  %8.3f  %-13s  %s",
                  format_iso8601_utc(r.utime).c_str(), r.method.c_str(), r.n_samples, r.bias_nT[0],
                  r.bias_nT[1], r.bias_nT[2], r.bias_sigma_nT[0], r.bias_sigma_nT[1],
                  r.bias_sigma_nT[2], r.residual_rms_nT, storage::status_name(r.status),
                  r.verdict.c_str());
    for (size_t k = 0; k < r.rejection_reasons.size(); ++k) {
      text += (k == 0 ? ": " : "; ") + r.rejection_reasons[k];
    }
    // The bias of a result with a temperature model is the bias at its T0 (k_T: JSON and CSV).
    if (r.has_temperature_model == 1)
      append_printf(&text, "  (bias at T0 = %.2f degC)", r.reference_temperature_C);
    // The bias of a result with a bias rate is the bias at its window's end (the rate: JSON, CSV).
    if (r.has_bias_rate == 1)
      append_printf(&text, "  (bias at the window's end, moving %.2f %.2f %.2f nT/h)",
                    r.bias_rate_nT_per_h[0], r.bias_rate_nT_per_h[1], r.bias_rate_nT_per_h[2]);
    text += '\n';
  }
  return text;
}

namespace {

// The numeric fields of a downsampled bucket, in output order.
constexpr int kFieldCount = 20;
constexpr std::array<const char*, kFieldCount> kFieldNames = {"n_samples",
                                                              "bias_x_nT",
                                                              "bias_y_nT",
                                                              "bias_z_nT",
                                                              "bias_sigma_x_nT",
                                                              "bias_sigma_y_nT",
                                                              "bias_sigma_z_nT",
                                                              "D11",
                                                              "D22",
                                                              "D33",
                                                              "D12",
                                                              "D13",
                                                              "D23",
                                                              "D11_sigma",
                                                              "D22_sigma",
                                                              "D33_sigma",
                                                              "D12_sigma",
                                                              "D13_sigma",
                                                              "D23_sigma",
                                                              "residual_rms_nT"};

std::array<double, kFieldCount> field_values(const storage::CalibrationRecord& r) {
  std::array<double, kFieldCount> v{};
  v[0] = r.n_samples;
  for (int i = 0; i < 3; ++i) v[1 + i] = r.bias_nT[i];
  for (int i = 0; i < 3; ++i) v[4 + i] = r.bias_sigma_nT[i];
  for (int i = 0; i < 6; ++i) v[7 + i] = r.D[i];
  for (int i = 0; i < 6; ++i) v[13 + i] = parameter_sigma(r, 3 + i);
  v[19] = r.residual_rms_nT;
  return v;
}

struct Bucket {
  int64_t count = 0, accepted = 0;
  std::array<int64_t, kFieldCount> n{};
  std::array<double, kFieldCount> sum{}, min{}, max{};
};

}  // namespace

nlohmann::json downsample_history(const std::vector<storage::CalibrationRecord>& rows,
                                  const storage::HistoryQuery& query, int points) {
  nlohmann::json out;
  out["sat_id"] = query.sat_id;
  out["points"] = points;
  out["rows"] = rows.size();
  nlohmann::json fields = nlohmann::json::array();
  for (const char* name : kFieldNames) fields.push_back(name);
  out["fields"] = fields;
  out["series"] = nlohmann::json::array();
  if (rows.empty() || points < 1) {
    out["start_utime"] = query.since_utime ? nlohmann::json(*query.since_utime) : nullptr;
    out["end_utime"] = query.until_utime ? nlohmann::json(*query.until_utime) : nullptr;
    out["bucket_us"] = nullptr;
    return out;
  }
  int64_t first = rows.front().utime, last = rows.front().utime;
  for (const auto& r : rows) {
    first = std::min(first, r.utime);
    last = std::max(last, r.utime);
  }
  const int64_t start = query.since_utime.value_or(first);
  const int64_t end = query.until_utime.value_or(last);
  // Buckets of equal width covering [start, end]; unsigned: the span of any two int64 fits.
  const uint64_t span = static_cast<uint64_t>(end) - static_cast<uint64_t>(start) + 1;
  const uint64_t width = std::max<uint64_t>(
      1, span / static_cast<uint64_t>(points) + (span % static_cast<uint64_t>(points) != 0));
  out["start_utime"] = start;
  out["end_utime"] = end;
  out["bucket_us"] = width;

  // One series per method, in the order methods first appear.
  std::vector<std::string> methods;
  std::vector<std::vector<Bucket>> buckets;
  for (const auto& r : rows) {
    auto it = std::find(methods.begin(), methods.end(), r.method);
    if (it == methods.end()) {
      methods.push_back(r.method);
      buckets.emplace_back(static_cast<size_t>(points));
      it = methods.end() - 1;
    }
    const uint64_t offset = static_cast<uint64_t>(r.utime) - static_cast<uint64_t>(start);
    const size_t index =
        static_cast<size_t>(std::min<uint64_t>(offset / width, static_cast<uint64_t>(points - 1)));
    Bucket& b = buckets[static_cast<size_t>(it - methods.begin())][index];
    ++b.count;
    if (r.verdict == "accepted") ++b.accepted;
    const auto values = field_values(r);
    for (int f = 0; f < kFieldCount; ++f) {
      const double v = values[f];
      if (!std::isfinite(v)) continue;
      if (b.n[f] == 0 || v < b.min[f]) b.min[f] = v;
      if (b.n[f] == 0 || v > b.max[f]) b.max[f] = v;
      b.sum[f] += v;
      ++b.n[f];
    }
  }
  for (size_t m = 0; m < methods.size(); ++m) {
    nlohmann::json list = nlohmann::json::array();
    for (int i = 0; i < points; ++i) {
      const size_t k = static_cast<size_t>(query.descending ? points - 1 - i : i);
      const Bucket& b = buckets[m][k];
      if (b.count == 0) continue;
      // Offsets from start stay unsigned (no overflow); the last bucket ends at `end`.
      const uint64_t lo_offset = width * k;
      const uint64_t hi_offset = std::min(lo_offset + (width - 1), span - 1);
      const auto lo = static_cast<int64_t>(static_cast<uint64_t>(start) + lo_offset);
      const auto hi = static_cast<int64_t>(static_cast<uint64_t>(start) + hi_offset);
      nlohmann::json j;
      j["start_utime"] = lo;
      j["end_utime"] = hi;
      j["start_time"] = history_time(lo);
      j["count"] = b.count;
      j["accepted"] = b.accepted;
      j["rejected"] = b.count - b.accepted;
      for (int f = 0; f < kFieldCount; ++f) {
        const bool any = b.n[f] > 0;
        j[kFieldNames[f]] = {{"n", b.n[f]},
                             {"min", any ? json_number(b.min[f]) : nlohmann::json(nullptr)},
                             {"mean", any ? json_number(b.sum[f] / static_cast<double>(b.n[f]))
                                          : nlohmann::json(nullptr)},
                             {"max", any ? json_number(b.max[f]) : nlohmann::json(nullptr)}};
      }
      list.push_back(std::move(j));
    }
    out["series"].push_back({{"method", methods[m]}, {"buckets", std::move(list)}});
  }
  return out;
}

}  // namespace magcal
