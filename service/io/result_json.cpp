#include "service/io/result_json.hpp"

#include <cmath>

#include "pipeline/roll_pitch_yaw_report.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"

namespace magcal {

nlohmann::json json_number(double value) {
  if (std::isfinite(value)) return value;
  return nullptr;
}

namespace {

template <typename Vec>
nlohmann::json json_vector(const Vec& v) {
  nlohmann::json a = nlohmann::json::array();
  for (Eigen::Index i = 0; i < v.size(); ++i) a.push_back(json_number(v(i)));
  return a;
}

template <typename Mat>
nlohmann::json json_matrix(const Mat& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (Eigen::Index r = 0; r < m.rows(); ++r) rows.push_back(json_vector(m.row(r)));
  return rows;
}

}  // namespace

nlohmann::json error_figures_json(const ErrorFigures& figures) {
  if (!std::isfinite(figures.rms)) return nullptr;
  return {{"rms", json_number(figures.rms)}, {"worst", json_number(figures.worst)}};
}

nlohmann::json calibration_result_to_json(const CalibrationResult& result,
                                          double gimbal_lock_margin_deg) {
  nlohmann::json j;
  j["method"] = result.method;
  j["utime"] = result.utime;
  j["window_start_utime"] = result.window_start_utime;
  j["window_end_utime"] = result.window_end_utime;
  j["n_samples"] = result.n_samples;
  j["bias_nT"] = json_vector(result.parameters.bias_nT);
  j["D"] = json_matrix(result.parameters.D);
  const Vector9d sigma = result.covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  j["bias_sigma_nT"] = json_vector(sigma.head<3>());
  j["D_sigma"] = json_vector(sigma.tail<6>());
  j["covariance"] = json_matrix(result.covariance);
  if (result.has_temperature_model) {  // bias_nT is the bias at reference_temperature_C
    j["reference_temperature_C"] = json_number(result.reference_temperature_C);
    j["temperature_coefficient_nT_per_C"] = json_vector(result.temperature_coefficient_nT_per_C);
    j["temperature_coefficient_sigma_nT_per_C"] =
        json_vector(result.temperature_coefficient_sigma_nT_per_C());
  }
  if (result.has_bias_rate) {  // bias_nT is the bias at window_end_utime
    j["bias_rate_nT_per_h"] = json_vector(result.bias_rate_nT_per_h);
    j["bias_rate_sigma_nT_per_h"] = json_vector(result.bias_rate_sigma_nT_per_h());
    j["bias_rate_covariance"] = json_matrix(result.bias_rate_covariance);
  }
  if (result.has_alignment) {
    const Eigen::Matrix3d& R = result.alignment.R_sensor_from_body;
    const Eigen::Matrix3d& covariance = result.alignment.angle_covariance_rad2;
    j["R_sensor_from_body"] = json_matrix(R);
    j["q_sensor_from_body"] = json_vector(quaternion_from_dcm(R));
    const RollPitchYawReport a =
        roll_pitch_yaw_report(R, covariance, gimbal_lock_margin_deg * kDegToRad);
    j["alignment_deg"] = {{"roll", json_number(a.rpy.roll_rad * kRadToDeg)},
                          {"pitch", json_number(a.rpy.pitch_rad * kRadToDeg)},
                          {"yaw", json_number(a.rpy.yaw_rad * kRadToDeg)}};
    // An unknown covariance (history rows stored before it was kept) leaves its keys out.
    const bool covariance_known = covariance.allFinite();
    if (covariance_known) {
      j["alignment_covariance_deg2"] = json_matrix(covariance * (kRadToDeg * kRadToDeg));
      const Eigen::Vector3d s = a.sigma_rad * kRadToDeg;
      j["alignment_sigma_deg"] = {
          {"roll", json_number(s(0))}, {"pitch", json_number(s(1))}, {"yaw", json_number(s(2))}};
    }
    j["alignment_singular"] = a.singular;
    // The stage's check of itself: the attitude lag it estimated, and why it refused the rotation.
    if (!std::isnan(result.alignment.attitude_lag_s)) {
      j["alignment_attitude_lag_s"] = json_number(result.alignment.attitude_lag_s);
      j["alignment_attitude_lag_sigma_s"] = json_number(result.alignment.attitude_lag_sigma_s);
      j["alignment_attitude_lag_applied"] = result.alignment.attitude_lag_applied;
    }
    if (!result.alignment.inconsistency.empty())
      j["alignment_inconsistency"] = result.alignment.inconsistency;
    if (a.singular) {
      j["alignment_determined_deg"] = {{a.combination_name, a.combination_rad * kRadToDeg}};
      j["alignment_canonical_error_deg"] = a.canonical_rotation_error_rad * kRadToDeg;
      if (covariance_known) {
        j["alignment_determined_sigma_deg"] = {
            {a.combination_name, json_number(a.combination_sigma_rad * kRadToDeg)}};
      }
    }
  }
  // The field error the calibration leaves on its window (pipeline/field_error.hpp); null when
  // not computed.
  j["field_direction_error_deg"] = error_figures_json(result.field_error.direction_deg);
  j["field_magnitude_error_nT"] = error_figures_json(result.field_error.magnitude_nT);
  j["residual_rms_nT"] = json_number(result.residual_rms_nT);
  j["iterations"] = result.iterations;
  j["converged"] = result.converged;
  j["status"] = to_string(result.status);
  j["verdict"] = result.accepted ? "accepted" : "rejected";
  j["rejection_reasons"] = result.rejection_reasons;
  j["fisher_condition_number"] = json_number(result.fisher_condition_number);
  j["n_downweighted"] = result.n_downweighted;
  // Uncertainty evidence (estimation.md section 7); null when unknown.
  j["noise_scale"] = json_number(result.noise_scale);
  j["residual_autocorrelation"] = json_number(result.residual_autocorrelation);
  if (std::isfinite(result.noise_scale))
    j["covariance_lag_window"] = result.covariance_lag_window;
  else
    j["covariance_lag_window"] = nullptr;
  j["residual_rms_all_nT"] = json_number(result.residual_rms_all_nT);
  // The bias's variance about its window average (in `covariance`), and what a refit without a
  // temperature channel estimated of a swing with the orbit.
  j["bias_variability_nT2"] = json_vector(result.bias_variability_nT2);
  if (result.orbit_swing.periods_tried > 0) {
    const UnresolvedBiasSwing& w = result.orbit_swing;
    j["orbit_swing"] = {{"period_min", json_number(w.period_s / 60.0)},
                        {"period_probability", json_number(w.period_probability)},
                        {"detected", w.detected()},
                        {"amplitude_nT", json_vector(w.amplitude_nT)},
                        {"amplitude_sigma_nT", json_vector(w.amplitude_sigma_nT)},
                        {"variance_nT2", json_vector(w.variance_nT2)}};
  }
  if (result.has_nonlinearity) {
    j["nonlinearity_k3"] = json_vector(result.nonlinearity_k3);  // of k_i y_i^2, 1/nT
    j["hysteresis_nT"] = json_vector(result.hysteresis_nT);
  }
  j["nis_mean"] = json_number(result.nis_mean);
  j["measurement_noise_nT"] = json_number(result.measurement_noise_nT);
  j["message"] = result.message;
  return j;
}

// Lossless ISO 8601: whole seconds print without a fraction, anything else with microseconds.
std::string history_time(int64_t utime) {
  return format_iso8601_utc(utime, utime % kMicrosPerSecond == 0 ? 0 : 6);
}

// One stored result as the JSON object of `history --format json` (also used by `status`).
nlohmann::json history_record_json(const storage::CalibrationRecord& rec) {
  nlohmann::json j = calibration_result_to_json(result_from_record(rec));
  // Not stored in the database: leave them out rather than print defaults as if measured.
  for (const char* key : {"fisher_condition_number", "n_downweighted", "message", "converged"}) {
    j.erase(key);
  }
  // An online result that applied its anchor refit's temperature model says whose it is.
  if (rec.temperature_model_refit_id > 0)
    j["temperature_model_refit_id"] = rec.temperature_model_refit_id;
  j["id"] = rec.id;
  j["sat_id"] = rec.sat_id;
  j["time"] = history_time(rec.utime);
  j["window_start"] = history_time(rec.window_start_utime);
  j["window_end"] = history_time(rec.window_end_utime);
  j["software_version"] = rec.software_version;
  j["created_time"] = history_time(rec.created_utime);
  return j;
}

}  // namespace magcal
