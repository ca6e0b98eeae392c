// Time lag between the attitude and the magnetometer, from the alignment pairs alone.
//
// Sign as pipeline/time_offset.hpp: tau > 0 means the reference for a measurement taken at t is
// the recorded one at t + tau; attitude time tags 1 s ahead of the magnetometer's (the reported
// attitude at t is the true one at t + 1 s) give tau = -1 s.
//
// Model: u_k = R h(t_k + tau) + eps_k, h(t_k + tau) ≈ h_k + tau hdot_k + tau^2 / 2 hddot_k, the
// derivatives by finite differences of the recorded h over the time-ordered samples (5-point
// central on an even grid, else 3-point on uneven spacing; samples without neighbours on both
// sides, or whose field turns by more than kMaxStepTurn_rad between neighbours, are left out).
// The cubic term is below 1 nT for |tau| <= 2 s at 1.5 deg/s. Joint Gauss-Newton on the small
// rotation dtheta (alignment.hpp's convention) and tau, R re-solved by Procrustes at each tau;
// the 4 x 4 covariance from the residuals' structure as align_procrustes's (sigma^2 F^-1 or the
// Newey-West sandwich, whichever is larger).
//
// Only h in the body frame is known here: shifting it in time also shifts the inertial field's
// own motion (about twice the orbital rate in LEO), which the true lag does not. That leaves a
// model error m of |tau| times the field's inertial rate (~90 nT/s in LEO). Its bias of (angles,
// tau), F^-1 J^T m, is bounded in every direction by the covariance M^2 F^-1 (M the bound of |m|
// over the samples): of the order of that rate over the body rate on a tumble, but up to the
// whole lag where the attitude turns about a nearly body-fixed axis, where a lag looks like a
// rotation about it and only the inertial field's motion tells them apart. sigma_s and the
// angles' covariance include it (model_sigma_s its share; nil at tau = 0, so a test of no lag
// uses the rest), Monte-Carlo in alignment_check_test.
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/alignment.hpp"

namespace magcal {

// Alignment pairs with their time tags, time-ordered, and the finite-difference derivatives of h.
struct TimedAlignmentPairs {
  std::vector<AlignmentPair> pairs;
  std::vector<double> t_s;
  std::vector<Eigen::Vector3d> h_rate_nT_per_s;    // dh/dt (NaN where not available)
  std::vector<Eigen::Vector3d> h_accel_nT_per_s2;  // d2h/dt2
};

// Sorts the pairs by time and differentiates h (see above).
TimedAlignmentPairs timed_alignment_pairs(const std::vector<AlignmentPair>& pairs,
                                          const std::vector<int64_t>& utime);

struct AttitudeLagResult {
  bool estimated = false;
  std::string message;  // why not, when not estimated
  double lag_s = 0.0;
  double sigma_s = std::numeric_limits<double>::quiet_NaN();        // all terms below
  double model_sigma_s = std::numeric_limits<double>::quiet_NaN();  // bound of the h-only bias
  // Bound of the inertial field's rate that the h-only model shifts with the lag: it leaves
  // about |lag_s| times this in the residual (vector rms, nT).
  double field_inertial_rate_bound_nT_per_s = 0.0;
  Eigen::Matrix3d R_sensor_from_body = Eigen::Matrix3d::Identity();  // at lag_s
  Eigen::Matrix3d angle_covariance_rad2 = Eigen::Matrix3d::Zero();   // marginal, tau free
  double residual_rms_nT = 0.0;                                      // at lag_s
  double residual_rms_zero_lag_nT = 0.0;                             // the same samples at 0
  Eigen::Matrix3d R_zero_lag = Eigen::Matrix3d::Identity();          // same samples, tau = 0
  int n_samples = 0;
};

// Joint (R, tau) fit on the pairs that have derivatives; needs min_samples of them and a
// two-dimensional spread of directions.
AttitudeLagResult estimate_attitude_lag(const TimedAlignmentPairs& timed, int min_samples = 10);

}  // namespace magcal
