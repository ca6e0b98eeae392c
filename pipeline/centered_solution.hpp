// Centered solution of the attitude-independent scalar problem (Alonso & Shuster; estimation.md
// 2a), the starting point of every batch refit.
//
//   z_k = |B_k|^2 - |h_k|^2 = L_k theta - |b|^2 + v_k,   L_k = [2 B_k^T, -S_k]
//   w_k = 1 / sigma_k^2,  sigma_k^2 = 4 sigma^2 |y_k|^2 + 6 sigma^4  (scalar_measurement.hpp)
//   y_k = B_k (no prior) or (I + D0) B_k - b0 (weights from a prior estimate)
//   bar(x) = sum w_k x_k / sum w_k,   x~_k = x_k - bar(x)  (removes the unknown |b|^2)
//   F~ = sum w_k L~_k^T L~_k,   theta* = F~^-1 sum w_k L~_k^T (z~_k - mu~_k),  Cov = F~^-1
//
// Two passes over the samples (means, then centered sums) with fixed-size 9x9 accumulators:
// no allocation, no cancellation from subtracting large raw moments. F~ is solved in the
// diagonally scaled form (c in nT and E dimensionless differ by ~1e5).
// Samples must be finite with |h| > 0 (batch_calibration validates; a bad sample here gives
// kInvalidInput).
#pragma once

#include <limits>
#include <string>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "pipeline/temperature_model.hpp"

namespace magcal {

struct CenteredOptions {
  double sigma_nT = 3.0;  // magnetometer white noise per axis
  int min_samples = 10;   // 9 unknowns + the eliminated mean
  // F~ is treated as singular when its scaled condition number exceeds this.
  double max_condition = 1e14;
  // Also derive theta_covariance from the residuals' structure (a third pass): the HAC sandwich
  // F~^-1 Omega F~^-1 (hac_covariance.hpp, scores w_k L~_k^T e~_k, lag window from the
  // residuals' lag-1 autocorrelation), not below F~^-1. For `magcal fit --method centered`, whose
  // white F~^-1 leaves out the error the unmodelled sensor effects cause (paper scenario, 12 h:
  // z bias up to 6 sigma off). Off for the LM start, whose covariance nobody reads.
  bool residual_covariance = false;
  // Also estimate the bias temperature model's terms a jointly, as 4 more centered columns
  // (pipeline/temperature_model.hpp) about this reference temperature (degC).
  bool temperature_model = false;
  double reference_temperature_C = 0.0;
  std::string validate() const;  // empty when valid
};

enum class CenteredStatus {
  kOk = 0,                   // theta valid and I + E positive definite
  kNotPositiveDefinite = 1,  // theta computed, but I + E is not PD (b, D not recoverable;
                             // the LM refinement may still start from theta)
  kSingular = 2,             // F~ singular: geometry does not determine theta
  kTooFewSamples = 3,
  kInvalidInput = 4,  // NaN/Inf, |h| <= 0, or invalid options
};
const char* to_string(CenteredStatus s);

struct CenteredResult {
  CenteredStatus status = CenteredStatus::kInvalidInput;
  std::string message;
  Vector9d theta = Vector9d::Zero();             // [c (nT); E11 E22 E33 E12 E13 E23]
  Matrix9d theta_covariance = Matrix9d::Zero();  // F~^-1, or the HAC one (residual_covariance)
  Matrix9d theta_covariance_white = Matrix9d::Zero();  // F~^-1
  // residual_covariance only: sqrt(sum w e~^2 / (n - 10)), lag-1 autocorrelation of sqrt(w) e~,
  // and the Bartlett lag window used.
  double noise_scale = std::numeric_limits<double>::quiet_NaN();
  double residual_autocorrelation = std::numeric_limits<double>::quiet_NaN();
  int lag_window = 0;
  double chi2 = std::numeric_limits<double>::quiet_NaN();  // sum w e~^2 (residual_covariance)
  // temperature_model: a = [kappa; beta] and its covariance (HAC with residual_covariance).
  Vector4d temperature_terms = Vector4d::Zero();
  Matrix4d temperature_covariance = Matrix4d::Zero();
  double condition_number = 0.0;  // of the scaled F~
  int n_samples = 0;
};

// weight_parameters: estimate used for the weights' y_k (null: y_k = B_k).
CenteredResult centered_solution(const SampleSet& samples, const CenteredOptions& options = {},
                                 const CalibrationParameters* weight_parameters = nullptr);

}  // namespace magcal
