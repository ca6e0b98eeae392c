// CalibrationResult -> JSON with the keys of design.md (`fit --json`, `history --format json`,
// `status --json`), shared by `magcal fit`, `magcal refit`, `magcal history` and `status`.
//
// Keys always present: method, utime, window_start_utime, window_end_utime, n_samples,
// bias_nT [3], D [[3],[3],[3]], bias_sigma_nT [3], D_sigma [6] (D11 D22 D33 D12 D13 D23),
// covariance [[9]x9] (p = [b; D11 D22 D33 D12 D13 D23], nT^2 / nT / 1), residual_rms_nT,
// iterations, converged, status ("ok", "not_converged", ...), verdict ("accepted" |
// "rejected"), rejection_reasons [strings], fisher_condition_number, n_downweighted, message.
// When result.has_alignment: R_sensor_from_body [[3],[3],[3]] (row-major rows),
// q_sensor_from_body [w, x, y, z] (the same rotation, estimation.md section 0: v_sensor =
// q v_body q*; sign: w > 0, rotation.hpp quaternion_from_dcm), alignment_deg {roll, pitch, yaw}
// (section 0), alignment_covariance_deg2 [[3],[3],[3]] (deg^2: the covariance of the rotation
// error as a rotation vector in the sensor frame, R_true = exp(-[dtheta x]) R_hat, equally of
// log(R_true R_hat^T) = -dtheta; pipeline/calibration_result.hpp AlignmentEstimate),
// alignment_sigma_deg {roll, pitch, yaw} and alignment_singular
// (pipeline/roll_pitch_yaw_report.hpp): within gimbal_lock_margin_deg of pitch +-90 deg the
// angles are the canonical split (roll 0, yaw = the determined combination), roll and yaw sigma
// null, and alignment_determined_deg / alignment_determined_sigma_deg {yaw_minus_roll |
// yaw_plus_roll} give the combination. An unknown covariance (NaN: history rows stored before
// schema 5) leaves alignment_covariance_deg2 and both sigma keys out.
// When result.has_temperature_model (bias_nT is then the bias at T0):
// reference_temperature_C (T0), temperature_coefficient_nT_per_C [3] and
// temperature_coefficient_sigma_nT_per_C [3].
// When result.has_bias_rate (bias_nT is then the bias at window_end_utime): bias_rate_nT_per_h
// [3], bias_rate_sigma_nT_per_h [3], bias_rate_covariance [[3]x3].
// field_direction_error_deg and field_magnitude_error_nT: {rms, worst} of the field error the
// calibration leaves on its window (pipeline/field_error.hpp), null when not computed.
// Non-finite numbers become null (JSON has no NaN).
// Callers add their own keys (compute_ms, time strings, ...) to the returned object.
#pragma once

#include <nlohmann/json.hpp>

#include "pipeline/calibration_result.hpp"
#include "pipeline/roll_pitch_yaw_report.hpp"
#include "storage/calibration_history.hpp"

namespace magcal {

nlohmann::json calibration_result_to_json(
    const CalibrationResult& result, double gimbal_lock_margin_deg = kDefaultGimbalLockMargin_deg);

// A finite double as a JSON number, anything else as null.
nlohmann::json json_number(double value);

// {"rms": ..., "worst": ...}, or null when not computed (rms NaN).
nlohmann::json error_figures_json(const ErrorFigures& figures);

// Lossless ISO 8601: whole seconds print without a fraction, anything else with microseconds.
std::string history_time(int64_t utime);

// One stored result as the JSON object of `history --format json` (also used by `status`):
// the fit keys plus id, sat_id, time strings and software version, and for an online result
// that applied a refit's temperature model temperature_model_refit_id (that refit's id).
nlohmann::json history_record_json(const storage::CalibrationRecord& rec);

}  // namespace magcal
