#include "pipeline/sphere_fit.hpp"

#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

namespace magcal {

std::string SphereFitOptions::validate() const {
  if (min_samples < 4) return "min_samples must be >= 4 (4 parameters)";
  if (!(min_spread >= 0.0) || !std::isfinite(min_spread)) return "min_spread must be >= 0";
  return {};
}

const char* to_string(SphereFitStatus s) {
  switch (s) {
    case SphereFitStatus::kOk:
      return "ok";
    case SphereFitStatus::kTooFewSamples:
      return "too_few_samples";
    case SphereFitStatus::kInvalidInput:
      return "invalid_input";
    case SphereFitStatus::kDegenerate:
      return "degenerate";
  }
  return "unknown";
}

SphereFitResult fit_sphere(const std::vector<Eigen::Vector3d>& b_nT,
                           const SphereFitOptions& options) {
  SphereFitResult out;
  out.n_samples = static_cast<int>(b_nT.size());
  if (const std::string e = options.validate(); !e.empty()) {
    out.message = e;
    return out;
  }
  if (out.n_samples < options.min_samples) {
    out.status = SphereFitStatus::kTooFewSamples;
    out.message = "too few samples: " + std::to_string(out.n_samples) + " < " +
                  std::to_string(options.min_samples);
    return out;
  }
  // Centre the data first (mean m) so the normal equations stay well conditioned at
  // |B| ~ 5e4 nT: fit |x|^2 = 2 c'^T x + k' with x = B - m, then c = m + c'.
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& b : b_nT) {
    if (!b.allFinite()) {
      out.message = "non-finite sample";
      return out;
    }
    mean += b;
  }
  mean /= static_cast<double>(b_nT.size());
  Eigen::Matrix4d normal = Eigen::Matrix4d::Zero();
  Eigen::Vector4d rhs = Eigen::Vector4d::Zero();
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const Eigen::Vector3d& b : b_nT) {
    const Eigen::Vector3d x = b - mean;
    Eigen::Vector4d row;
    row << 2.0 * x, 1.0;
    normal.selfadjointView<Eigen::Lower>().rankUpdate(row);
    rhs += row * x.squaredNorm();
    scatter += x * x.transpose();
  }
  normal = normal.selfadjointView<Eigen::Lower>();
  scatter /= static_cast<double>(b_nT.size());
  const double spread_scale = scatter.trace();
  const double min_eig = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter).eigenvalues()(0);
  const Eigen::LDLT<Eigen::Matrix4d> ldlt(normal);
  if (!(spread_scale > 0.0) || ldlt.info() != Eigen::Success) {
    out.status = SphereFitStatus::kDegenerate;
    out.message = "samples do not span three dimensions";
    return out;
  }
  const Eigen::Vector4d sol = ldlt.solve(rhs);
  const Eigen::Vector3d c = sol.head<3>();
  const double r2 = sol(3) + c.squaredNorm();
  if (!(r2 > 0.0) || !sol.allFinite()) {
    out.status = SphereFitStatus::kDegenerate;
    out.message = "no real sphere fits the samples (r^2 <= 0)";
    return out;
  }
  out.center_nT = mean + c;
  out.radius_nT = std::sqrt(r2);
  // A plane or line of samples makes the centre unobservable along the thin direction.
  if (min_eig / r2 < options.min_spread) {
    out.status = SphereFitStatus::kDegenerate;
    out.message = "samples (nearly) in a plane or line: centre not determined";
    return out;
  }
  double sum_sq = 0.0;
  for (const Eigen::Vector3d& b : b_nT) {
    const double e = (b - out.center_nT).norm() - out.radius_nT;
    sum_sq += e * e;
  }
  out.residual_rms_nT = std::sqrt(sum_sq / static_cast<double>(b_nT.size()));
  out.status = SphereFitStatus::kOk;
  return out;
}

}  // namespace magcal
