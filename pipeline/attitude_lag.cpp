// Attitude-magnetometer time lag by joint Gauss-Newton on (rotation, lag). Math in the header.
#include "pipeline/attitude_lag.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

#include <Eigen/Cholesky>
#include <Eigen/Dense>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Beyond this turn of h between neighbours the finite differences stop approximating the rate.
constexpr double kMaxStepTurn_rad = 0.5;
constexpr double kEvenGridTolerance = 1e-6;
constexpr int kMaxIterations = 30;
constexpr double kLagTolerance_s = 1e-6;
// The coarse profile the fit starts from: the quadratic model holds to a few seconds at a few
// deg/s.
constexpr double kProfileHalfWidth_s = 3.0;
constexpr double kProfileStep_s = 0.25;
// The inertial field's direction turns up to about three times as fast as its magnitude changes
// (dipole field along an orbit), and only the magnitude's rate is seen in h: the bound of the
// h-only model's bias of tau relative to |tau| is this times rms(d|h|/dt) / rms |dh/dt|.
constexpr double kInertialRateOverMagnitudeRate = 3.0;

double angle_between(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

// Procrustes rotation of u on g (proper, det +1), once per candidate lag: one pass, no copy.
Eigen::Matrix3d best_rotation(const std::vector<AlignmentPair>& pairs,
                              const std::vector<Eigen::Vector3d>& g) {
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (std::size_t k = 0; k < pairs.size(); ++k)
    M.noalias() += pairs[k].u_sensor_nT * g[k].transpose();
  return wahba_rotation(M);
}

}  // namespace

TimedAlignmentPairs timed_alignment_pairs(const std::vector<AlignmentPair>& pairs,
                                          const std::vector<int64_t>& utime) {
  TimedAlignmentPairs out;
  const std::size_t n = std::min(pairs.size(), utime.size());
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), std::size_t{0});
  std::stable_sort(order.begin(), order.end(),
                   [&](std::size_t a, std::size_t b) { return utime[a] < utime[b]; });
  out.pairs.reserve(n);
  out.t_s.reserve(n);
  for (std::size_t i : order) {
    if (!out.t_s.empty() && utime[i] * 1e-6 <= out.t_s.back()) continue;  // duplicate time tag
    out.pairs.push_back(pairs[i]);
    out.t_s.push_back(static_cast<double>(utime[i]) * 1e-6);
  }
  const std::size_t m = out.pairs.size();
  const Eigen::Vector3d nan3 = Eigen::Vector3d::Constant(kNaN);
  out.h_rate_nT_per_s.assign(m, nan3);
  out.h_accel_nT_per_s2.assign(m, nan3);
  auto h = [&](std::size_t i) -> const Eigen::Vector3d& { return out.pairs[i].h_body_nT; };
  auto t = [&](std::size_t i) { return out.t_s[i]; };
  for (std::size_t j = 1; j + 1 < m; ++j) {
    if (angle_between(h(j - 1), h(j)) > kMaxStepTurn_rad ||
        angle_between(h(j), h(j + 1)) > kMaxStepTurn_rad)
      continue;
    const double h0 = t(j) - t(j - 1), h1 = t(j + 1) - t(j);
    const bool five_point = j >= 2 && j + 2 < m && std::abs(h1 - h0) <= kEvenGridTolerance * h0 &&
                            std::abs(t(j + 2) - t(j + 1) - h0) <= kEvenGridTolerance * h0 &&
                            std::abs(t(j - 1) - t(j - 2) - h0) <= kEvenGridTolerance * h0 &&
                            angle_between(h(j - 2), h(j - 1)) <= kMaxStepTurn_rad &&
                            angle_between(h(j + 1), h(j + 2)) <= kMaxStepTurn_rad;
    if (five_point) {
      out.h_rate_nT_per_s[j] =
          (h(j - 2) - 8.0 * h(j - 1) + 8.0 * h(j + 1) - h(j + 2)) / (12.0 * h0);
      out.h_accel_nT_per_s2[j] =
          (-h(j - 2) + 16.0 * h(j - 1) - 30.0 * h(j) + 16.0 * h(j + 1) - h(j + 2)) /
          (12.0 * h0 * h0);
    } else {
      const Eigen::Vector3d d0 = (h(j) - h(j - 1)) / h0, d1 = (h(j + 1) - h(j)) / h1;
      out.h_rate_nT_per_s[j] = (d0 * h1 + d1 * h0) / (h0 + h1);
      out.h_accel_nT_per_s2[j] = 2.0 * (d1 - d0) / (h0 + h1);
    }
  }
  return out;
}

AttitudeLagResult estimate_attitude_lag(const TimedAlignmentPairs& timed, int min_samples) {
  AttitudeLagResult out;
  std::vector<AlignmentPair> pairs;
  std::vector<Eigen::Vector3d> rate, accel;
  for (std::size_t k = 0; k < timed.pairs.size(); ++k) {
    if (!timed.h_rate_nT_per_s[k].allFinite()) continue;
    pairs.push_back(timed.pairs[k]);
    rate.push_back(timed.h_rate_nT_per_s[k]);
    accel.push_back(timed.h_accel_nT_per_s2[k]);
  }
  const std::size_t n = pairs.size();
  out.n_samples = static_cast<int>(n);
  if (static_cast<int>(n) < std::max(min_samples, 5)) {
    out.message = "attitude lag: " + std::to_string(n) +
                  " samples have neighbours close enough in time to differentiate the field";
    return out;
  }
  std::vector<Eigen::Vector3d> g(n);
  auto shift = [&](double tau) {
    for (std::size_t k = 0; k < n; ++k)
      g[k] = pairs[k].h_body_nT + tau * rate[k] + 0.5 * tau * tau * accel[k];
  };
  shift(0.0);
  out.R_zero_lag = best_rotation(pairs, g);
  // Gauss-Newton starts from the best point of a coarse profile (as time_offset.hpp's search).
  double tau = 0.0, best_ss = std::numeric_limits<double>::infinity();
  for (double t = -kProfileHalfWidth_s; t <= kProfileHalfWidth_s + 1e-9; t += kProfileStep_s) {
    shift(t);
    const Eigen::Matrix3d R_t = best_rotation(pairs, g);
    double ss = 0.0;
    for (std::size_t k = 0; k < n; ++k) ss += (pairs[k].u_sensor_nT - R_t * g[k]).squaredNorm();
    if (ss < best_ss) best_ss = ss, tau = t;
  }
  shift(tau);
  Eigen::Matrix3d R = best_rotation(pairs, g);
  // Jacobian of u - R g(tau) in (dtheta, tau): [(R g) x] and R g'(tau) (negated residual slope).
  auto normal_equations = [&](Eigen::Matrix4d* F, Eigen::Vector4d* rhs,
                              std::vector<Eigen::Vector4d>* scores,
                              std::vector<Eigen::Vector3d>* residuals) {
    F->setZero();
    rhs->setZero();
    for (std::size_t k = 0; k < n; ++k) {
      const Eigen::Vector3d Rg = R * g[k];
      Eigen::Matrix<double, 3, 4> J;
      J.leftCols<3>() = cross_matrix(Rg);
      J.col(3) = R * (rate[k] + tau * accel[k]);
      const Eigen::Vector3d e = pairs[k].u_sensor_nT - Rg;
      F->noalias() += J.transpose() * J;
      rhs->noalias() += J.transpose() * e;
      if (scores) (*scores)[k] = J.transpose() * e;
      if (residuals) (*residuals)[k] = e;
    }
  };
  Eigen::Matrix4d F;
  Eigen::Vector4d rhs;
  bool converged = false;
  for (int it = 0; it < kMaxIterations && !converged; ++it) {
    normal_equations(&F, &rhs, nullptr, nullptr);
    const Eigen::LDLT<Eigen::Matrix4d> ldlt(F);
    if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 0.0)) {
      out.message = "attitude lag: the lag is not separable from a rotation on these samples";
      return out;
    }
    const double step = ldlt.solve(rhs)(3);
    if (!std::isfinite(step)) break;
    tau += step;
    shift(tau);
    R = best_rotation(pairs, g);
    converged = std::abs(step) < kLagTolerance_s;
  }
  if (!converged) {
    out.message = "attitude lag: the fit did not converge";
    return out;
  }
  std::vector<Eigen::Vector4d> scores(n);
  std::vector<Eigen::Vector3d> residuals(n);
  normal_equations(&F, &rhs, &scores, &residuals);
  double ss = 0.0, ss0 = 0.0, magnitude_rate2 = 0.0;
  for (std::size_t k = 0; k < n; ++k) {
    ss += residuals[k].squaredNorm();
    ss0 += (pairs[k].u_sensor_nT - out.R_zero_lag * pairs[k].h_body_nT).squaredNorm();
    const double along = pairs[k].h_body_nT.normalized().dot(rate[k]);
    magnitude_rate2 += along * along;
  }
  const auto nd = static_cast<double>(n);
  const double s2 = ss / std::max(1.0, 3.0 * nd - 4.0);
  const Eigen::Matrix4d F_inv = F.inverse();
  const int window = bartlett_lag_window(lag1_autocorrelation(residuals), static_cast<int>(n));
  const Eigen::Matrix4d covariance =
      covariance_not_below<4>(s2 * F_inv, F_inv * newey_west_meat<4>(scores, window) * F_inv);
  out.lag_s = tau;
  out.field_inertial_rate_bound_nT_per_s =
      kInertialRateOverMagnitudeRate * std::sqrt(magnitude_rate2 / nd);
  // The h-only model's misfit m (|tau| times the inertial field's rate, per sample) biases the
  // fit by F^-1 J^T m; for any |m| <= M, (v' F^-1 J^T m)^2 <= M^2 v' F^-1 v in every direction v
  // (F = J'J). That bound holds where the lag is nearly a rotation about a body-fixed spin axis
  // too: there only the inertial field's motion, the very term the model gets wrong, tells the
  // lag from the rotation, and F^-1 is large along that direction.
  const double misfit_bound2_nT2 = tau * tau * out.field_inertial_rate_bound_nT_per_s *
                                   out.field_inertial_rate_bound_nT_per_s * nd;
  const Eigen::Matrix4d model_covariance = misfit_bound2_nT2 * F_inv;
  out.model_sigma_s = std::sqrt(model_covariance(3, 3));
  out.sigma_s = std::sqrt(covariance(3, 3) + model_covariance(3, 3));
  out.R_sensor_from_body = R;
  out.angle_covariance_rad2 =
      covariance.topLeftCorner<3, 3>() + model_covariance.topLeftCorner<3, 3>();
  out.residual_rms_nT = std::sqrt(ss / nd);
  out.residual_rms_zero_lag_nT = std::sqrt(ss0 / nd);
  out.estimated = std::isfinite(out.sigma_s);
  if (!out.estimated) out.message = "attitude lag: no uncertainty";
  return out;
}

}  // namespace magcal
