#include "pipeline/calibration_difference.hpp"

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>

namespace magcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// x^T C^-1 x, NaN when C is not positive definite (or not finite).
template <int N>
double mahalanobis2(const Eigen::Matrix<double, N, 1>& x, const Eigen::Matrix<double, N, N>& C) {
  if (!C.allFinite()) return kNaN;
  const Eigen::LLT<Eigen::Matrix<double, N, N>> llt(0.5 * (C + C.transpose()));
  if (llt.info() != Eigen::Success) return kNaN;
  return x.dot(llt.solve(x));
}

}  // namespace

CalibrationDifference calibration_difference(const CalibrationResult& a,
                                             const CalibrationResult& b) {
  CalibrationDifference d;
  d.dp = b.parameters.packed() - a.parameters.packed();
  const Matrix9d C = a.covariance + b.covariance;
  d.sigma = C.diagonal().cwiseMax(0.0).cwiseSqrt();
  for (int i = 0; i < 9; ++i) d.z(i) = d.sigma(i) > 0.0 ? d.dp(i) / d.sigma(i) : kNaN;
  d.chi2 = mahalanobis2<9>(d.dp, C);
  d.has_alignment = a.has_alignment && b.has_alignment;
  d.same_model = a.has_alignment == b.has_alignment &&
                 a.has_temperature_model == b.has_temperature_model &&
                 a.has_bias_rate == b.has_bias_rate;
  d.alignment_chi2 = kNaN;
  if (d.has_alignment) {
    const Eigen::AngleAxisd rotation(Eigen::Matrix3d(b.alignment.R_sensor_from_body *
                                                     a.alignment.R_sensor_from_body.transpose()));
    d.dtheta_rad = rotation.angle() * rotation.axis();
    d.alignment_chi2 = mahalanobis2<3>(
        d.dtheta_rad,
        Eigen::Matrix3d(a.alignment.angle_covariance_rad2 + b.alignment.angle_covariance_rad2));
  }
  // A difference whose variance is unknown is not called significant: nothing supports it.
  d.significant = d.chi2 > CalibrationDifference::kChi2Quantile99_9dof ||
                  d.alignment_chi2 > CalibrationDifference::kChi2Quantile99_3dof;
  return d;
}

}  // namespace magcal
