// The alignment stage's check of itself: is the vector residual after the best rotation what the
// noise leaves, and if not, what does it look like?
//
// Residual e_k = u_k - R h_k in time order, per axis. Its white part (noise, white attitude
// noise: the residual-structure covariance covers those) is estimated from the first
// differences, sigma_w^2 = sum |e_k - e_{k-1}|^2 / (6 (N - 1)); the rest, s_sys^2 = rms^2 -
// sigma_w^2 per axis, is a slowly varying misfit (a time lag between attitude and magnetometer, a
// convention mix-up, a wrong reference) that a constant rotation partly absorbs and no
// covariance from the residuals covers. The rotation is refused when
//  - s_sys > max_systematic_ratio x the noise the stage-1 fit leaves (max(stated sigma, stage-1
//    scalar residual rms)), or
//  - a time lag is detected (|tau| > lag_detection_significance x the noise's share of
//    sigma_tau, the lag model's bias bound being nil at no lag, and |tau| > that bound) and
//    fitting it moves the rotation by more than lag_significance of its sigma (Mahalanobis);
//    a lag fit that moves it so without a detected lag (a lag looks like a rotation about the
//    axis the attitude turns about) widens the rotation's covariance to the lag fit's instead;
// unless estimate_attitude_lag, which takes the lag-corrected rotation and its covariance
// (pipeline/attitude_lag.hpp) and checks that fit's residual instead. A refusal names what fits:
// the lag, or a signed permutation of the sensor axes (name_axis_mixup). Never applied silently.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/alignment.hpp"
#include "pipeline/attitude_lag.hpp"
#include "pipeline/calibration_result.hpp"

namespace magcal {

struct AlignmentCheckOptions {
  double sigma_nT = 3.0;                // stated noise per axis
  double stage1_residual_rms_nT = 0.0;  // scalar residual of the stage-1 fit
  bool estimate_attitude_lag = false;   // use the lag-corrected rotation
  // Of the stage-1 p = [b; D11 D22 D33 D12 D13 D23] the vectors were calibrated with: its error
  // leaves a residual the rotation cannot remove, expected, not a misfit (Zero: none stated).
  Matrix9d stage1_parameter_covariance = Matrix9d::Zero();
  double max_systematic_ratio = 5.0;
  double lag_significance = 3.0;
  double lag_detection_significance = 5.0;  // a lag against none, in noise sigmas
};

struct AlignmentCheck {
  std::string refusal;                  // empty: consistent
  double residual_per_axis_nT = 0.0;    // rms per axis about the rotation used
  double white_per_axis_nT = 0.0;       // from the first differences
  double systematic_per_axis_nT = 0.0;  // the rest
  // max(sigma, stage-1 residual), with the stage-1 parameters' error (and a fitted lag's) added
  double expected_per_axis_nT = 0.0;
  AttitudeLagResult lag;
  bool lag_applied = false;  // estimate_attitude_lag and the lag estimated: R, P below are its
  Eigen::Matrix3d R_sensor_from_body = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d angle_covariance_rad2 = Eigen::Matrix3d::Zero();
  bool consistent() const { return refusal.empty(); }
};

// timed: the pairs the rotation was fitted on with their time tags (timed_alignment_pairs);
// fitted: align_procrustes's result on them.
AlignmentCheck check_alignment(const TimedAlignmentPairs& timed, const AlignmentResult& fitted,
                               const AlignmentCheckOptions& options);

// White and systematic rms per axis of time-ordered vector residuals (see above).
void split_residual(const std::vector<Eigen::Vector3d>& residuals, double* white_per_axis_nT,
                    double* systematic_per_axis_nT);

// Sets r->has_alignment and r->alignment from align_procrustes's result on timed.pairs and its
// check: the rotation and covariance used (plus stage1_covariance_rad2, the stage-1 error's
// share), the residual fraction, the refusal and the lag.
void apply_alignment_check(const TimedAlignmentPairs& timed, const AlignmentResult& fitted,
                           const Eigen::Matrix3d& stage1_covariance_rad2,
                           const AlignmentCheckOptions& options, CalibrationResult* r);

// The signed permutation P of the sensor axes (48) under which (P u_k, h_k) fit a rotation best,
// among equal fits the one whose rotation is nearest the identity (a rotation absorbs the 24
// proper ones: the naming assumes a near-identity installation). "" when the reported axes fit
// as well as any; else e.g. "the sensor's y axis looks negated", "the sensor's x and y axes look
// swapped". *rms_nT: the best fit's vector residual rms.
std::string name_axis_mixup(const std::vector<AlignmentPair>& pairs, double* rms_nT = nullptr);

}  // namespace magcal
