#include "service/io/calibration_export.hpp"

#include <cmath>
#include <limits>

#include <fmt/format.h>

#include "pipeline/calibration_table.hpp"
#include "pipeline/rotation.hpp"
#include "service/io/result_json.hpp"

namespace magcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
const Eigen::Vector3d kNoValues = Eigen::Vector3d::Constant(kNaN);  // an absent term
constexpr const char* kEquation = "B_cal = M B - o - o_T (T - T0) - o_r (t - t_ref)";
constexpr const char* kFrames =
    "B: measured field, sensor frame, nT; B_cal: calibrated field, body frame, nT; T: sensor "
    "temperature, degC; t - t_ref: hours";

template <typename Mat>
nlohmann::json json_rows(const Mat& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (Eigen::Index r = 0; r < m.rows(); ++r) {
    nlohmann::json row = nlohmann::json::array();
    for (Eigen::Index c = 0; c < m.cols(); ++c) row.push_back(json_number(m(r, c)));
    rows.push_back(m.cols() == 1 ? row.front() : row);
  }
  return rows;
}

// The table's values as JSON (null for an absent term).
nlohmann::json table_json(const CalibrationTable& t) {
  nlohmann::json j;
  j["M"] = json_rows(t.M);
  j["o_nT"] = json_rows(t.offset_nT);
  j["T0_C"] = t.has_temperature_term ? json_number(t.reference_temperature_C) : nullptr;
  j["o_T_nT_per_C"] = t.has_temperature_term ? json_rows(t.offset_per_C_nT) : nullptr;
  j["t_ref"] = t.has_rate_term ? nlohmann::json(history_time(t.rate_reference_utime)) : nullptr;
  j["t_ref_utime"] = t.has_rate_term ? nlohmann::json(t.rate_reference_utime) : nullptr;
  j["o_r_nT_per_h"] = t.has_rate_term ? json_rows(t.offset_rate_nT_per_h) : nullptr;
  return j;
}

// One `name,value,unit` row per value; the float32 ones printed so that they read back exactly.
class CsvRows {
 public:
  void text(const std::string& name, const std::string& value, const char* unit = "") {
    out_ += name + ',' + quoted(value) + ',' + unit + '\n';
  }
  void float32(const std::string& name, double value, const char* unit) {
    text(name, std::isfinite(value) ? fmt::format("{:.9g}", value) : "", unit);
  }
  void float64(const std::string& name, double value, const char* unit) {
    text(name, std::isfinite(value) ? fmt::format("{:.17g}", value) : "", unit);
  }
  template <typename Vec>
  void vector(const std::string& name, const Vec& v, const char* unit, bool single) {
    static constexpr const char* kAxes[3] = {"_x", "_y", "_z"};
    for (int i = 0; i < 3; ++i) {
      if (single)
        float32(name + kAxes[i], v(i), unit);
      else
        float64(name + kAxes[i], v(i), unit);
    }
  }
  void matrix(const std::string& name, const Eigen::Matrix3d& m, const char* unit, bool single) {
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        const std::string cell = name + std::to_string(r + 1) + std::to_string(c + 1);
        if (single)
          float32(cell, m(r, c), unit);
        else
          float64(cell, m(r, c), unit);
      }
    }
  }
  const std::string& str() const { return out_; }

 private:
  static std::string quoted(const std::string& s) {
    if (s.find_first_of(",\"\n") == std::string::npos) return s;
    std::string q = "\"";
    for (const char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
    return q + '"';
  }
  std::string out_ = "name,value,unit\n";
};

Eigen::Matrix3d rotation_of(const CalibrationResult& r) {
  return r.has_alignment ? r.alignment.R_sensor_from_body : Eigen::Matrix3d::Identity();
}

// Reading --------------------------------------------------------------------------------------

double number_or_nan(const nlohmann::json& j) {
  return j.is_number() ? j.get<double>() : kNaN;
}

template <int Rows, int Cols>
bool read_matrix(const nlohmann::json& j, Eigen::Matrix<double, Rows, Cols>* out) {
  if (!j.is_array() || j.size() != Rows) return false;
  for (int r = 0; r < Rows; ++r) {
    if constexpr (Cols == 1) {
      (*out)(r) = number_or_nan(j[static_cast<size_t>(r)]);
    } else {
      const nlohmann::json& row = j[static_cast<size_t>(r)];
      if (!row.is_array() || row.size() != Cols) return false;
      for (int c = 0; c < Cols; ++c) (*out)(r, c) = number_or_nan(row[static_cast<size_t>(c)]);
    }
  }
  return true;
}

}  // namespace

nlohmann::json export_table_json(const CalibrationResult& result, const CalibrationOrigin& origin,
                                 double rounding_field_nT) {
  const CalibrationTable exact = calibration_table(result);
  const CalibrationTable rounded = float32_rounded(exact);
  const TableRoundingError e = rounding_error(exact, rounded, rounding_field_nT);
  nlohmann::json j;
  j["format"] = "magcal-calibration-table";
  j["format_version"] = kExportFormatVersion;
  j["equation"] = kEquation;
  j["frames"] = kFrames;
  j["sat_id"] = origin.sat_id.empty() ? nlohmann::json(nullptr) : nlohmann::json(origin.sat_id);
  j["calibration_id"] = origin.id > 0 ? nlohmann::json(origin.id) : nullptr;
  j["source"] = origin.source;
  j["method"] = result.method;
  j["verdict"] = result.accepted ? "accepted" : "rejected";
  j["epoch"] = history_time(result.utime);
  j["epoch_utime"] = result.utime;
  j["window_start"] = history_time(result.window_start_utime);
  j["window_end"] = history_time(result.window_end_utime);
  j["has_alignment"] = result.has_alignment;
  j["table_float32"] = table_json(rounded);
  j["rounding_error_nT"] = {{"field_nT", e.field_nT},
                            {"at_field", e.at_field_nT},
                            {"per_C", e.per_C_nT},
                            {"per_h", e.per_h_nT}};
  j["table_float64"] = table_json(exact);
  nlohmann::json p;
  p["b_nT"] = json_rows(result.parameters.bias_nT);
  p["D"] = json_rows(result.parameters.D);
  p["R_sensor_from_body"] = json_rows(rotation_of(result));
  p["b_sigma_nT"] = json_rows(result.bias_sigma_nT());
  if (result.has_temperature_model) {
    p["T0_C"] = json_number(result.reference_temperature_C);
    p["k_T_nT_per_C"] = json_rows(result.temperature_coefficient_nT_per_C);
  }
  if (result.has_bias_rate) {
    p["t_ref"] = history_time(result.window_end_utime);
    p["bias_rate_nT_per_h"] = json_rows(result.bias_rate_nT_per_h);
  }
  j["parameters"] = p;
  j["field_direction_error_deg"] = error_figures_json(result.field_error.direction_deg);
  j["field_magnitude_error_nT"] = error_figures_json(result.field_error.magnitude_nT);
  return j;
}

std::string export_table_csv(const CalibrationResult& result, const CalibrationOrigin& origin,
                             double rounding_field_nT) {
  const CalibrationTable exact = calibration_table(result);
  const CalibrationTable rounded = float32_rounded(exact);
  const TableRoundingError e = rounding_error(exact, rounded, rounding_field_nT);
  CsvRows rows;
  rows.text("format", "magcal-calibration-table");
  rows.text("format_version", std::to_string(kExportFormatVersion));
  rows.text("equation", kEquation);
  rows.text("frames", kFrames);
  rows.text("sat_id", origin.sat_id);
  rows.text("calibration_id", origin.id > 0 ? std::to_string(origin.id) : "");
  rows.text("source", origin.source);
  rows.text("method", result.method);
  rows.text("verdict", result.accepted ? "accepted" : "rejected");
  rows.text("epoch", history_time(result.utime));
  rows.text("epoch_utime", std::to_string(result.utime), "us");
  rows.text("has_alignment", result.has_alignment ? "1" : "0");
  // The table (float32): absent terms have empty values.
  rows.matrix("M", rounded.M, "1", true);
  rows.vector("o", rounded.offset_nT, "nT", true);
  const bool thermal = rounded.has_temperature_term;
  rows.float32("T0", thermal ? rounded.reference_temperature_C : kNaN, "degC");
  rows.vector("o_T", thermal ? rounded.offset_per_C_nT : kNoValues, "nT/degC", true);
  const bool drifting = rounded.has_rate_term;
  rows.text("t_ref", drifting ? history_time(rounded.rate_reference_utime) : "");
  rows.text("t_ref_utime", drifting ? std::to_string(rounded.rate_reference_utime) : "", "us");
  rows.vector("o_r", drifting ? rounded.offset_rate_nT_per_h : kNoValues, "nT/h", true);
  rows.float64("rounding_field", e.field_nT, "nT");
  rows.float64("rounding_error_at_field", e.at_field_nT, "nT");
  rows.float64("rounding_error_per_C", e.per_C_nT, "nT/degC");
  rows.float64("rounding_error_per_h", e.per_h_nT, "nT/h");
  // The calibration it came from (double precision).
  rows.vector("b", result.parameters.bias_nT, "nT", false);
  rows.matrix("D", result.parameters.D, "1", false);
  rows.matrix("R", rotation_of(result), "1", false);
  rows.vector("k_T", thermal ? result.temperature_coefficient_nT_per_C : kNoValues, "nT/degC",
              false);
  rows.vector("bias_rate", drifting ? result.bias_rate_nT_per_h : kNoValues, "nT/h", false);
  rows.float64("field_direction_error_rms", result.field_error.direction_deg.rms, "deg");
  rows.float64("field_direction_error_worst", result.field_error.direction_deg.worst, "deg");
  rows.float64("field_magnitude_error_rms", result.field_error.magnitude_nT.rms, "nT");
  rows.float64("field_magnitude_error_worst", result.field_error.magnitude_nT.worst, "nT");
  return rows.str();
}

std::optional<CalibrationResult> calibration_from_json(const nlohmann::json& in,
                                                       CalibrationOrigin* origin,
                                                       std::string* error) {
  const nlohmann::json& j = in.is_array() && in.size() == 1 ? in.front() : in;
  if (!j.is_object()) {
    *error = in.is_array() ? "a JSON array of " + std::to_string(in.size()) +
                                 " calibrations: give one (magcal history --limit 1)"
                           : "not a JSON object";
    return std::nullopt;
  }
  CalibrationResult r;
  const auto missing = [&](const char* key) {
    *error = std::string("no valid '") + key + "' (a calibration from magcal fit --json or " +
             "magcal history --format json is expected)";
    return std::nullopt;
  };
  if (!j.contains("method") || !j["method"].is_string()) return missing("method");
  r.method = j["method"].get<std::string>();
  for (auto [key, out] :
       {std::pair{"utime", &r.utime}, std::pair{"window_start_utime", &r.window_start_utime},
        std::pair{"window_end_utime", &r.window_end_utime}}) {
    if (!j.contains(key) || !j[key].is_number_integer()) return missing(key);
    *out = j[key].get<int64_t>();
  }
  if (j.contains("n_samples") && j["n_samples"].is_number_integer())
    r.n_samples = j["n_samples"].get<int>();
  Eigen::Vector3d b;
  if (!j.contains("bias_nT") || !read_matrix<3, 1>(j["bias_nT"], &b)) return missing("bias_nT");
  r.parameters.bias_nT = b;
  if (!j.contains("D") || !read_matrix<3, 3>(j["D"], &r.parameters.D)) return missing("D");
  if (!j.contains("covariance") || !read_matrix<9, 9>(j["covariance"], &r.covariance))
    return missing("covariance");
  if (j.contains("R_sensor_from_body")) {
    if (!read_matrix<3, 3>(j["R_sensor_from_body"], &r.alignment.R_sensor_from_body))
      return missing("R_sensor_from_body");
    r.has_alignment = true;
    Eigen::Matrix3d c_deg2;
    if (j.contains("alignment_covariance_deg2") &&
        read_matrix<3, 3>(j["alignment_covariance_deg2"], &c_deg2)) {
      r.alignment.angle_covariance_rad2 = c_deg2 * (kDegToRad * kDegToRad);
    } else {
      r.alignment.angle_covariance_rad2.setConstant(kNaN);  // unknown
    }
  }
  if (j.contains("reference_temperature_C") && j.contains("temperature_coefficient_nT_per_C")) {
    r.has_temperature_model = true;
    r.reference_temperature_C = number_or_nan(j["reference_temperature_C"]);
    Eigen::Vector3d k, sigma = kNoValues;
    if (!read_matrix<3, 1>(j["temperature_coefficient_nT_per_C"], &k))
      return missing("temperature_coefficient_nT_per_C");
    r.temperature_coefficient_nT_per_C = k;
    if (j.contains("temperature_coefficient_sigma_nT_per_C"))
      read_matrix<3, 1>(j["temperature_coefficient_sigma_nT_per_C"], &sigma);
    r.temperature_coefficient_covariance = sigma.cwiseAbs2().asDiagonal();  // the JSON has sigmas
  }
  if (j.contains("bias_rate_nT_per_h")) {
    r.has_bias_rate = true;
    Eigen::Vector3d rate;
    if (!read_matrix<3, 1>(j["bias_rate_nT_per_h"], &rate)) return missing("bias_rate_nT_per_h");
    r.bias_rate_nT_per_h = rate;
    if (j.contains("bias_rate_covariance"))
      read_matrix<3, 3>(j["bias_rate_covariance"], &r.bias_rate_covariance);
  }
  if (j.contains("verdict") && j["verdict"].is_string())
    r.accepted = j["verdict"].get<std::string>() == "accepted";
  r.status = r.accepted ? CalibrationStatus::kOk : CalibrationStatus::kRejected;
  if (j.contains("residual_rms_nT")) r.residual_rms_nT = number_or_nan(j["residual_rms_nT"]);
  for (auto [key, figures] : {std::pair{"field_direction_error_deg", &r.field_error.direction_deg},
                              std::pair{"field_magnitude_error_nT", &r.field_error.magnitude_nT}}) {
    if (j.contains(key) && j[key].is_object()) {
      figures->rms = number_or_nan(j[key].value("rms", nlohmann::json()));
      figures->worst = number_or_nan(j[key].value("worst", nlohmann::json()));
    }
  }
  if (j.contains("sat_id") && j["sat_id"].is_string())
    origin->sat_id = j["sat_id"].get<std::string>();
  if (j.contains("id") && j["id"].is_number_integer()) origin->id = j["id"].get<int64_t>();
  return r;
}

}  // namespace magcal
