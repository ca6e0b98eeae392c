// Calibration of a real recording (service/io/field_recording.hpp): `magcal fit` on a
// foreign CSV (Astro Pi, BROAD, ...).
//
// Reference magnitude, one of:
//  - IGRF: |H_k| = |IGRF-14(t_k + tau, r_ecef(lat_k, lon_k, alt_k))| (nT). The time-tag offset
//    tau (s; tau > 0: the reference for a measurement at t is evaluated at t + tau) is applied
//    by evaluating |H| on the ORIGINAL position grid and interpolating |H|(t + tau) in time
//    (cubic Hermite, pipeline/time_offset.hpp apply_time_offset); samples whose t + tau falls
//    outside the position stream are dropped. tau is given, or estimated by profiling the
//    attitude-independent residual (pipeline/time_offset.hpp), or 0.
//  - constant: |h_k| = a given value, or ("auto") the radius of a 4-parameter algebraic sphere
//    fit to the raw data (pipeline/sphere_fit.hpp): with unknown constant magnitude the
//    9-parameter fit is scale-invariant, so the magnitude must be fixed first.
// Then the batch refit (pipeline/batch_calibration.hpp, twostep by default) and its gates.
//
// Noise sigma: a real low-cost sensor is quantised (Astro Pi: 100 nT), so a spacecraft default
// (3 nT) would make the reported covariance meaningless. Use the user's sigma when given;
// otherwise sigma = the residual rms of a first fit (the scalar residual |B_cal| - |h| is the
// noise projected on the field direction, so its rms estimates the per-axis sigma) and refit.
//
// Stage 2 with a constant reference field and known attitude (BROAD: q_file maps IMU -> ENU,
// Hamilton, so A_body_from_enu = A(conj(q_file))): rows without a quaternion are skipped
// (counted); R_sensor_from_body and the ENU field f are estimated jointly
// (pipeline/alignment.hpp align_with_unknown_reference). Reported: per-axis std of
// f_k = A_k^T R^T u_k, u_k = (I + D) B_k - b, with R_hat and with R = I.
#pragma once

#include <limits>
#include <memory>
#include <optional>
#include <string>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "pipeline/alignment.hpp"
#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_result.hpp"
#include "pipeline/sphere_fit.hpp"
#include "pipeline/time_offset.hpp"
#include "service/io/field_recording.hpp"

namespace magcal {

struct RecordingFitOptions {
  BatchCalibrationOptions batch;   // method, robust, gate options (sigma: see sigma_nT)
  std::optional<double> sigma_nT;  // nullopt: estimated from a first fit's residual rms
  // Constant reference magnitude: nullopt = IGRF at the recorded positions.
  bool reference_magnitude_auto = false;
  std::optional<double> reference_magnitude_nT;
  // Time-tag offset (IGRF reference only).
  std::optional<double> time_offset_s;  // applied as given
  bool estimate_time_offset = false;
  double offset_min_s = -1000.0;
  double offset_max_s = 1000.0;
  double offset_step_s = 40.0;   // coarse grid; refined by golden section (time_offset.hpp)
  bool split_halves = false;     // also fit the first and second halves in time separately
  bool alignment = true;         // stage 2 when the recording has quaternions
  std::string validate() const;  // empty when valid
};

struct RecordingAlignment {
  bool estimated = false;
  std::string message;  // why not, when not estimated
  JointAlignmentResult joint;
  RollPitchYaw rpy;                                               // of R_hat
  Eigen::Vector3d field_enu_nT = Eigen::Vector3d::Zero();         // mean f_k with R_hat
  Eigen::Vector3d enu_std_nT = Eigen::Vector3d::Zero();           // per-axis std, R_hat
  Eigen::Vector3d enu_std_identity_nT = Eigen::Vector3d::Zero();  // per-axis std, R = I
  int n_pairs = 0;
  // The check of itself: the residual rms per axis of u_k against R A_k f, and why the rotation
  // is refused ("" = within 5 x the noise; otherwise the result is rejected with
  // alignment_inconsistent), naming a quaternion convention that fits.
  double residual_per_axis_nT = 0.0;
  std::string inconsistency;
};

struct RecordingFitReport {
  CalibrationResult result;
  std::string reference;  // "igrf" or "constant"
  double sigma_used_nT = 0.0;
  bool sigma_estimated = false;
  int n_rows = 0;            // usable rows in the recording
  int n_dropped_offset = 0;  // samples whose t + tau fell outside the position stream
  // Constant reference.
  double reference_magnitude_nT = 0.0;
  std::optional<SphereFitResult> sphere;
  // Time offset.
  bool time_offset_applied = false;
  double time_offset_s = 0.0;
  std::optional<TimeOffsetResult> offset_estimate;  // when estimated
  // Residual rms of the fit with the offset ignored (tau = 0, all samples): the "before".
  double residual_rms_zero_offset_nT = std::numeric_limits<double>::quiet_NaN();
  // Halves (split_halves): each fitted like the whole, at the whole recording's offset.
  std::shared_ptr<RecordingFitReport> first_half, second_half;
  RecordingAlignment alignment;
};

// Runs everything above. Returns nullopt and sets *error (one line) on unusable input (no
// position and no constant magnitude, offset with a constant reference, IGRF out of range...).
// Fit failures are reported in report.result.status, not as errors.
std::optional<RecordingFitReport> fit_recording(const FieldRecording& recording,
                                                const RecordingFitOptions& options,
                                                std::string* error);

// calibration_result_to_json(result) plus the keys of the report: reference,
// reference_magnitude_nT, sigma_nT, sigma_estimated, sphere_fit {...}, time_offset_s,
// time_offset_sigma_s, time_offset_status, time_offset_range_s [min, max],
// residual_rms_zero_offset_nT, halves [{...}, {...}], R_sensor_from_body, alignment_deg,
// field_enu_nT, enu_std_nT, enu_std_identity_nT, n_missing_quaternion.
nlohmann::json recording_fit_to_json(const RecordingFitReport& report,
                                     const FieldRecording& recording);

}  // namespace magcal
