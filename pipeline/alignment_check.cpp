// The alignment stage's consistency check and the naming of axis mix-ups. Math in the header.
#include "pipeline/alignment_check.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {
namespace {

// Fits count as equal within this relative rms (the 24 proper permutations fit identically).
constexpr double kEqualFitTolerance = 1e-6;

template <typename... Args>
std::string format(const char* fmt, Args... args) {
  char buf[512];
  std::snprintf(buf, sizeof(buf), fmt, args...);
  return buf;
}

std::vector<Eigen::Vector3d> residuals_about(const std::vector<AlignmentPair>& pairs,
                                             const Eigen::Matrix3d& R) {
  std::vector<Eigen::Vector3d> e(pairs.size());
  for (std::size_t k = 0; k < pairs.size(); ++k)
    e[k] = pairs[k].u_sensor_nT - R * pairs[k].h_body_nT;
  return e;
}

double rms_per_axis(const std::vector<Eigen::Vector3d>& e) {
  double ss = 0.0;
  for (const Eigen::Vector3d& x : e) ss += x.squaredNorm();
  return std::sqrt(ss / std::max<double>(1.0, 3.0 * static_cast<double>(e.size())));
}

// Squared Mahalanobis distance of the small rotation taking R_from to R_to, under P.
double rotation_shift_chi2(const Eigen::Matrix3d& R_from, const Eigen::Matrix3d& R_to,
                           const Eigen::Matrix3d& P) {
  const Eigen::AngleAxisd aa(Eigen::Matrix3d(R_to * R_from.transpose()));
  const Eigen::Vector3d dtheta = -aa.angle() * aa.axis();  // R_to = (I - [dtheta x]) R_from
  const Eigen::LDLT<Eigen::Matrix3d> ldlt(P);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 0.0))
    return std::numeric_limits<double>::infinity();
  return dtheta.dot(ldlt.solve(dtheta));
}

std::string describe_lag(const AttitudeLagResult& lag) {
  return format("the attitude looks %.3f +- %.3f s %s the magnetometer", std::abs(lag.lag_s),
                lag.sigma_s, lag.lag_s < 0.0 ? "ahead of" : "behind");
}

const char* const kAxis[3] = {"x", "y", "z"};

}  // namespace

void split_residual(const std::vector<Eigen::Vector3d>& e, double* white_per_axis_nT,
                    double* systematic_per_axis_nT) {
  const double total = rms_per_axis(e);
  double ss_diff = 0.0;
  for (std::size_t k = 1; k < e.size(); ++k) ss_diff += (e[k] - e[k - 1]).squaredNorm();
  const double white =
      e.size() > 1 ? std::sqrt(ss_diff / (6.0 * static_cast<double>(e.size() - 1))) : total;
  *white_per_axis_nT = std::min(white, total);
  *systematic_per_axis_nT = std::sqrt(std::max(0.0, total * total - white * white));
}

std::string name_axis_mixup(const std::vector<AlignmentPair>& pairs, double* rms_nT) {
  std::array<int, 3> perm = {0, 1, 2};
  double best_rms = std::numeric_limits<double>::infinity(), best_angle = 0.0;
  Eigen::Matrix3d best_P = Eigen::Matrix3d::Identity();
  std::vector<AlignmentPair> mapped(pairs.size());
  AlignmentOptions o;
  o.sigma_nT = 1.0;  // only the rotation and the residual are used
  do {
    for (int signs = 0; signs < 8; ++signs) {
      Eigen::Matrix3d P = Eigen::Matrix3d::Zero();  // corrected u = P u_reported
      for (int i = 0; i < 3; ++i) P(i, perm[i]) = (signs >> i) & 1 ? -1.0 : 1.0;
      for (std::size_t k = 0; k < pairs.size(); ++k)
        mapped[k] = {P * pairs[k].u_sensor_nT, pairs[k].h_body_nT};
      const AlignmentResult r = align_procrustes(mapped, o);
      if (!r.ok()) return {};
      const double angle = rotation_angle(r.estimate.R_sensor_from_body);
      const double tolerance = kEqualFitTolerance * r.residual_rms_nT;
      const bool better = !std::isfinite(best_rms) || r.residual_rms_nT < best_rms - tolerance ||
                          (r.residual_rms_nT <= best_rms + tolerance && angle < best_angle);
      if (better) best_rms = r.residual_rms_nT, best_angle = angle, best_P = P;
    }
  } while (std::next_permutation(perm.begin(), perm.end()));
  if (rms_nT) *rms_nT = best_rms;
  if (best_P.isIdentity()) return {};
  std::string negated, swapped;
  int n_negated = 0;
  bool permuted = false;
  for (int i = 0; i < 3; ++i) permuted = permuted || best_P(i, i) == 0.0;
  if (!permuted) {
    for (int i = 0; i < 3; ++i) {
      if (best_P(i, i) > 0.0) continue;
      negated += std::string(n_negated++ ? " and " : "") + kAxis[i];
    }
    return "the sensor's " + negated + (n_negated > 1 ? " axes look" : " axis looks") + " negated";
  }
  // Corrected axis i reads the reported axis j = perm(i), with a sign.
  std::string reads;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      if (best_P(i, j) == 0.0) continue;
      reads += std::string(i ? ", " : "") + (best_P(i, j) < 0.0 ? "-" : "") + kAxis[j];
    }
  }
  return "the sensor's axes look swapped: x, y, z are the reported " + reads;
}

namespace {

// The stage-1 parameters' own error, constant over the window, moves each calibrated vector
// u = (I + D) B - b by du = dD u - db (u ~ B to first order): per-axis rms of it under their
// covariance P. On a few hours of the paper sensor (b sigma up to ~20 nT) it is most of what
// the best rotation leaves; on a day of tumbling data, well under a nanotesla.
double parameter_error_per_axis_nT(const std::vector<AlignmentPair>& pairs, const Matrix9d& P) {
  if (pairs.empty() || P.isZero()) return 0.0;
  Eigen::Matrix<double, 3, 9> J = Eigen::Matrix<double, 3, 9>::Zero();
  J.leftCols<3>() = -Eigen::Matrix3d::Identity();
  double sum = 0.0;
  for (const AlignmentPair& pair : pairs) {
    const Eigen::Vector3d& u = pair.u_sensor_nT;
    J(0, 3) = u(0), J(1, 4) = u(1), J(2, 5) = u(2);  // D11 D22 D33
    J(0, 6) = u(1), J(1, 6) = u(0);                  // D12
    J(0, 7) = u(2), J(2, 7) = u(0);                  // D13
    J(1, 8) = u(2), J(2, 8) = u(1);                  // D23
    sum += (J * P * J.transpose()).trace();
  }
  return std::sqrt(sum / (3.0 * static_cast<double>(pairs.size())));
}

}  // namespace

AlignmentCheck check_alignment(const TimedAlignmentPairs& timed, const AlignmentResult& fitted,
                               const AlignmentCheckOptions& options) {
  AlignmentCheck out;
  out.R_sensor_from_body = fitted.estimate.R_sensor_from_body;
  out.angle_covariance_rad2 = fitted.estimate.angle_covariance_rad2;
  out.expected_per_axis_nT =
      std::hypot(std::max(options.sigma_nT, options.stage1_residual_rms_nT),
                 parameter_error_per_axis_nT(timed.pairs, options.stage1_parameter_covariance));
  out.lag = estimate_attitude_lag(timed);
  const double ratio = options.max_systematic_ratio;

  std::vector<Eigen::Vector3d> e = residuals_about(timed.pairs, out.R_sensor_from_body);
  out.residual_per_axis_nT = rms_per_axis(e);
  split_residual(e, &out.white_per_axis_nT, &out.systematic_per_axis_nT);
  // Tested against no lag, where the h-only model's bias (its bound grows with |tau|) is nil:
  // the noise's share of the lag's sigma, at a detection level that every refit passes (a
  // false refusal per refit at 3 sigma would be 0.3 %). And the lag must exceed that bias's
  // bound: beyond it the lag is not told from a rotation (and misfits of other kinds, which
  // the same geometry amplifies alike, could make it).
  const double lag_noise_sigma_s = std::sqrt(std::max(
      0.0, out.lag.sigma_s * out.lag.sigma_s - out.lag.model_sigma_s * out.lag.model_sigma_s));
  const bool lag_significant =
      out.lag.estimated &&
      std::abs(out.lag.lag_s) > options.lag_detection_significance * lag_noise_sigma_s &&
      std::abs(out.lag.lag_s) > out.lag.model_sigma_s;
  const bool lag_fit_moves_rotation =
      out.lag.estimated && rotation_shift_chi2(out.R_sensor_from_body, out.lag.R_sensor_from_body,
                                               out.angle_covariance_rad2) >
                               options.lag_significance * options.lag_significance;
  const bool lag_moves_rotation = lag_significant && lag_fit_moves_rotation;
  if (options.estimate_attitude_lag && out.lag.estimated) {
    out.lag_applied = true;
    out.R_sensor_from_body = out.lag.R_sensor_from_body;
    out.angle_covariance_rad2 = out.lag.angle_covariance_rad2;
    // The residual's structure at the lag (the samples the lag was fitted on).
    std::vector<Eigen::Vector3d> e_lag;
    const double tau = out.lag.lag_s;
    for (std::size_t k = 0; k < timed.pairs.size(); ++k) {
      if (!timed.h_rate_nT_per_s[k].allFinite()) continue;
      const Eigen::Vector3d h = timed.pairs[k].h_body_nT + tau * timed.h_rate_nT_per_s[k] +
                                0.5 * tau * tau * timed.h_accel_nT_per_s2[k];
      e_lag.push_back(timed.pairs[k].u_sensor_nT - out.R_sensor_from_body * h);
    }
    out.residual_per_axis_nT = rms_per_axis(e_lag);
    split_residual(e_lag, &out.white_per_axis_nT, &out.systematic_per_axis_nT);
    // What the h-only lag model leaves (the inertial field's motion shifted with the lag).
    out.expected_per_axis_nT =
        std::hypot(out.expected_per_axis_nT,
                   std::abs(tau) * out.lag.field_inertial_rate_bound_nT_per_s / std::sqrt(3.0));
  } else if (lag_moves_rotation) {
    out.refusal = format(
        "%s (a constant rotation leaves %.1f nT per axis, %.1f nT with the lag, against %.1f nT "
        "of noise): the rotation moves by more than %.0f sigma with the lag; estimate it "
        "(--estimate-attitude-lag) or correct the attitude time tags",
        describe_lag(out.lag).c_str(), out.lag.residual_rms_zero_lag_nT / std::sqrt(3.0),
        out.lag.residual_rms_nT / std::sqrt(3.0), out.expected_per_axis_nT,
        options.lag_significance);
    return out;
  } else if (lag_fit_moves_rotation) {
    // A lag the data cannot tell from a rotation (about the axis the attitude turns about) moves
    // the rotation beyond its sigma: the rotation's sigma is the lag fit's, where that is larger.
    out.angle_covariance_rad2 =
        covariance_not_below<3>(out.angle_covariance_rad2, out.lag.angle_covariance_rad2);
  }
  if (out.systematic_per_axis_nT <= ratio * out.expected_per_axis_nT) return out;

  out.refusal = format(
      "after the best rotation the residual is %.1f nT per axis, %.1f nT of it slowly varying, "
      "more than %g x the %.1f nT the noise leaves",
      out.residual_per_axis_nT, out.systematic_per_axis_nT, ratio, out.expected_per_axis_nT);
  double mixup_rms_nT = 0.0;
  const std::string mixup = name_axis_mixup(timed.pairs, &mixup_rms_nT);
  if (!mixup.empty() && mixup_rms_nT / std::sqrt(3.0) <= ratio * out.expected_per_axis_nT) {
    out.refusal += format(": %s (%.1f nT per axis so; a diagnosis, not applied)", mixup.c_str(),
                          mixup_rms_nT / std::sqrt(3.0));
  } else if (!out.lag_applied && out.lag.estimated &&
             out.lag.residual_rms_nT / std::sqrt(3.0) <= ratio * out.expected_per_axis_nT) {
    out.refusal += ": " + describe_lag(out.lag) + " (--estimate-attitude-lag)";
  } else {
    out.refusal +=
        ": check the attitude's time tags and convention, the sensor axes and the reference";
  }
  return out;
}

void apply_alignment_check(const TimedAlignmentPairs& timed, const AlignmentResult& fitted,
                           const Eigen::Matrix3d& stage1_covariance_rad2,
                           const AlignmentCheckOptions& options, CalibrationResult* r) {
  AlignmentResult with_stage1 = fitted;
  with_stage1.estimate.angle_covariance_rad2 += stage1_covariance_rad2;
  const AlignmentCheck check = check_alignment(timed, with_stage1, options);
  r->has_alignment = true;
  r->alignment = with_stage1.estimate;
  double sum_h2 = 0.0;
  for (const AlignmentPair& p : timed.pairs) sum_h2 += p.h_body_nT.squaredNorm();
  const double rms_h = std::sqrt(sum_h2 / static_cast<double>(timed.pairs.size()));
  r->alignment.residual_fraction = fitted.residual_rms_nT / rms_h;
  r->alignment.angle_covariance_rad2 = check.angle_covariance_rad2;
  if (check.lag_applied) {
    r->alignment.R_sensor_from_body = check.R_sensor_from_body;
    r->alignment.angle_covariance_rad2 = check.angle_covariance_rad2 + stage1_covariance_rad2;
    r->alignment.n_samples = check.lag.n_samples;
    r->alignment.residual_fraction = check.lag.residual_rms_nT / rms_h;
  }
  r->alignment.inconsistency = check.refusal;
  r->alignment.attitude_lag_applied = check.lag_applied;
  if (check.lag.estimated) {
    r->alignment.attitude_lag_s = check.lag.lag_s;
    r->alignment.attitude_lag_sigma_s = check.lag.sigma_s;
  }
}

}  // namespace magcal
