// The result every calibration method reports (batch refit or filter snapshot), as the CLI
// prints it, the daemon publishes it (calibration_t) and the history stores it.
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "pipeline/field_error.hpp"

namespace magcal {

// Values and order match calibration_t.status (design.md): lowest non-zero wins when several
// apply.
enum class CalibrationStatus : int8_t {
  kOk = 0,            // estimate valid
  kNotConverged = 1,  // iteration limit reached / filter not yet converged
  kUnobservable = 2,  // geometry does not determine all parameters (Fisher ill-conditioned)
  kFailed = 3,        // no valid estimate (e.g. I + E not positive definite, too few samples)
  kRejected = 4,      // estimate computed but refused by the acceptance gates
};
const char* to_string(CalibrationStatus s);  // "ok", "not_converged", ...

struct AlignmentEstimate {
  Eigen::Matrix3d R_sensor_from_body = Eigen::Matrix3d::Identity();
  // Covariance (rad^2) of the rotation error as a rotation vector in the SENSOR frame: dtheta with
  // R_true = exp(-[dtheta x]) R_hat ≈ (I - [dtheta x]) R_hat, a small frame rotation of the sensor
  // axes in section 0's sense (at R_hat ≈ I, dtheta = the (roll, pitch, yaw) errors). The same
  // matrix is the covariance of the active rotation vector log(R_true R_hat^T) = -dtheta.
  // NaN: unknown (a result restored from a history row stored before schema 5).
  Eigen::Matrix3d angle_covariance_rad2 = Eigen::Matrix3d::Zero();
  int n_samples = 0;
  // rms |u_k - R h_k| / rms |h_k| after the fit: ~2e-4 on the paper scenario, sin(error) for
  // attitude errors, ~1 when no rotation maps one set on the other (a sign-flipped or swapped
  // sensor axis is a reflection). Not persisted.
  double residual_fraction = 0.0;
  // The stage's check of itself (pipeline/alignment_check.hpp), not persisted: why the rotation
  // is refused ("" = its residual is what the noise leaves), and the time lag between attitude
  // and magnetometer estimated from the same pairs (s, pipeline/attitude_lag.hpp's sign; NaN:
  // not estimated), applied to the rotation or only reported.
  std::string inconsistency;
  double attitude_lag_s = std::numeric_limits<double>::quiet_NaN();
  double attitude_lag_sigma_s = std::numeric_limits<double>::quiet_NaN();
  bool attitude_lag_applied = false;
};

// What a refit without a temperature channel estimated of a bias swing at the orbital period
// (pipeline/orbit_synchronous_bias.hpp).
struct UnresolvedBiasSwing {
  // The expected squared distance of the current bias from the published one that the swing
  // adds, averaged over the orbit phase and the periods, nT^2 per axis.
  Eigen::Vector3d variance_nT2 = Eigen::Vector3d::Zero();
  // The most probable period, its posterior probability, and the swing estimated there per axis
  // (sqrt(c^2 + s^2), nT) with its 1-sigma (the rms of c's and s's).
  double period_s = 0.0;
  double period_probability = 0.0;
  Eigen::Vector3d amplitude_nT = Eigen::Vector3d::Zero();
  Eigen::Vector3d amplitude_sigma_nT = Eigen::Vector3d::Zero();
  int periods_tried = 0;  // 0: not computed
  // Posterior probability that the bias swings with the orbit (variance_nT2 is weighted by it).
  double probability = 0.0;
  // A swing seen (probability above kDetectedProbability), not only one the data cannot exclude.
  bool detected() const { return periods_tried > 0 && probability > kDetectedProbability; }
  static constexpr double kDetectedProbability = 0.99;
};

struct CalibrationResult {
  std::string method;  // "centered", "twostep", "ekf", "ukf"
  int64_t utime = 0;   // time the estimate refers to
  int64_t window_start_utime = 0;
  int64_t window_end_utime = 0;
  int n_samples = 0;

  CalibrationParameters parameters;
  Matrix9d covariance = Matrix9d::Zero();  // of p = [b; D11 D22 D33 D12 D13 D23]

  bool has_alignment = false;
  AlignmentEstimate alignment;

  double residual_rms_nT = 0.0;  // rms of |B_cal| - |h|
  int iterations = 0;
  bool converged = false;
  CalibrationStatus status = CalibrationStatus::kFailed;
  std::string message;  // why, when status is not ok

  double fisher_condition_number = 0.0;  // of the scaled Fisher matrix (estimation.md 2d)
  int n_downweighted = 0;                // robust mode: samples given reduced weight

  // Evidence behind `covariance` (estimation.md section 7). NaN / 0 / false = not computed.
  // `covariance` is the one we stand behind (published in calibration_t.cov); the white-noise
  // inverse information (statistical part, nominal sigma) is kept beside it for comparison.
  Matrix9d covariance_white_noise = Matrix9d::Zero();
  double noise_scale = std::numeric_limits<double>::quiet_NaN();  // sqrt(chi2 / (n - n_params))
  // Lag-1 autocorrelation of the normalised scalar residuals, in sample order.
  double residual_autocorrelation = std::numeric_limits<double>::quiet_NaN();
  int covariance_lag_window = 0;  // HAC (Newey–West, Bartlett) lag window, samples; 0 = none
  // Robust fits: residual_rms_nT is over the kept samples, this one over all of them.
  double residual_rms_all_nT = std::numeric_limits<double>::quiet_NaN();
  // Extended model (odd per-axis nonlinearity k3_i B_i^3, 1/nT^2), when the data support it.
  bool has_nonlinearity = false;
  // In this implementation the coefficient is that of the per-axis term k_i y_i^2 (1/nT; the
  // form the paper sensor's truth model has, measured: bias MSE 1.15 vs 3.7 nT^2 with k3 y^3), see
  // pipeline/model_extension.hpp; fitted jointly with the hysteresis amplitude below.
  Eigen::Vector3d nonlinearity_k3 = Eigen::Vector3d::Zero();
  Eigen::Vector3d hysteresis_nT = Eigen::Vector3d::Zero();  // per-axis hysteresis amplitude
  // Covariance of [nonlinearity_k3; hysteresis_nT] ((1/nT)^2, nT^2; HAC, as `covariance`).
  Matrix6d extension_covariance = Matrix6d::Zero();

  // Bias temperature model, when the data support it (BIC) and enough samples carry
  // a temperature: b(T) = bias_nT + k_T (T - reference_temperature_C), k_T per axis in nT/degC;
  // `parameters.bias_nT` and `covariance` are then those of the bias at the reference temperature
  // (the mean temperature of the samples used). Covariance of k_T in (nT/degC)^2.
  bool has_temperature_model = false;
  double reference_temperature_C = std::numeric_limits<double>::quiet_NaN();
  Eigen::Vector3d temperature_coefficient_nT_per_C = Eigen::Vector3d::Zero();
  Eigen::Matrix3d temperature_coefficient_covariance = Eigen::Matrix3d::Zero();
  Eigen::Vector3d temperature_coefficient_sigma_nT_per_C() const {
    return temperature_coefficient_covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  }

  // Linear bias rate (a drifting sensor), when the data support it (BIC), also beside a
  // temperature model (of the samples moved to T0; the bias is then at T0 and at the window's end):
  // b(t) = bias_nT + r (t - window end), r per axis in nT/h; `parameters.bias_nT` and
  // `covariance` are then those of the bias at the window's end (the current bias: what a filter
  // re-anchored by this refit and an operator need). Covariance of r in (nT/h)^2.
  bool has_bias_rate = false;
  Eigen::Vector3d bias_rate_nT_per_h = Eigen::Vector3d::Zero();
  Eigen::Matrix3d bias_rate_covariance = Eigen::Matrix3d::Zero();
  Eigen::Vector3d bias_rate_sigma_nT_per_h() const {
    return bias_rate_covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  }

  // Batch refits that took the extension: p_9 - p, where the 9-parameter model's optimum lies on
  // this window relative to the published p (what an estimator without the extension, such as
  // the online filters, converges to instead). Zero otherwise.
  Vector9d model_error = Vector9d::Zero();
  // Batch refits: the bias's variance about its window average where the window's short-block
  // biases show it moving (pipeline/bias_variability.hpp), nT^2 per axis; zero otherwise. Already
  // in `covariance`; the filters re-anchored on the refit keep it as model error (stored since
  // schema 11, so also after a restart or a takeover).
  Eigen::Vector3d bias_variability_nT2 = Eigen::Vector3d::Zero();
  Matrix9d model_error_covariance() const {
    Matrix9d m = model_error * model_error.transpose();
    m.diagonal().head<3>() += bias_variability_nT2;
    return m;
  }
  // Twostep refits of a window with too few temperatures: the orbit-synchronous bias swing
  // estimated with it (pipeline/orbit_synchronous_bias.hpp); its variance_nT2 is in
  // bias_variability_nT2 where larger than the blocks'. periods_tried 0: not computed. Not
  // persisted.
  UnresolvedBiasSwing orbit_swing;
  // Batch refits whose estimator bias was measured (bootstrap, pipeline/batch_calibration.hpp)
  // and removed from `parameters`: that bias. Zero otherwise. Not persisted.
  Vector9d estimator_bias = Vector9d::Zero();

  // Online filters: mean normalised innovation squared over the snapshot period, and the
  // effective per-axis measurement noise the (adaptive) filter currently uses.
  double nis_mean = std::numeric_limits<double>::quiet_NaN();
  double measurement_noise_nT = std::numeric_limits<double>::quiet_NaN();

  // The field error this calibration leaves on its own window's samples (pipeline/field_error.hpp,
  // the table of pipeline/calibration_table.hpp applied): batch refits and `magcal fit`; not
  // computed (n = 0) for the daemon's filter snapshots.
  FieldError field_error;

  // Acceptance verdict (gates); rejected results keep their numbers for inspection.
  bool accepted = true;
  std::vector<std::string> rejection_reasons;

  Eigen::Vector3d bias_sigma_nT() const { return covariance.diagonal().head<3>().cwiseSqrt(); }
};

}  // namespace magcal
