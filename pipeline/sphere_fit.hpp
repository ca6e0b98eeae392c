// Algebraic sphere fit (4 parameters) for constant-field data (a lab recording such as BROAD's,
// where the field does not change).
//
// Model: |B_k - c| = r for every sample (nT). Expanding,
//   |B_k|^2 = 2 c^T B_k + k,   k = r^2 - |c|^2,
// which is linear in (c, k): ordinary least squares on rows [2 B_k^T, 1] -> (c, k),
// then r = sqrt(k + |c|^2). The algebraic (not geometric) residual is minimised; for noise
// small against r the two agree to first order. Reported residual: rms_k (|B_k - c| - r).
//
// Why it exists: with an unknown constant reference magnitude the 9-parameter fit is
// scale-invariant (|h| cannot be estimated jointly with a full D), so the magnitude is fixed
// beforehand to this radius ("--reference-magnitude auto").
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

namespace magcal {

struct SphereFitOptions {
  int min_samples = 10;
  // Geometry gate: smallest eigenvalue of the centred sample scatter divided by r^2 (1/3 for
  // samples spread over the whole sphere, 0 for a plane/line where c is not determined).
  double min_spread = 1e-4;
  std::string validate() const;  // empty when valid
};

enum class SphereFitStatus {
  kOk = 0,
  kTooFewSamples = 1,
  kInvalidInput = 2,  // NaN/Inf in the samples or invalid options
  kDegenerate = 3,    // samples do not span 3-D (plane, line) or r^2 <= 0
};
const char* to_string(SphereFitStatus s);  // "ok", "too_few_samples", ...

struct SphereFitResult {
  SphereFitStatus status = SphereFitStatus::kInvalidInput;
  std::string message;
  Eigen::Vector3d center_nT = Eigen::Vector3d::Zero();
  double radius_nT = 0.0;
  double residual_rms_nT = 0.0;  // rms of |B_k - c| - r
  int n_samples = 0;
  bool ok() const { return status == SphereFitStatus::kOk; }
};

SphereFitResult fit_sphere(const std::vector<Eigen::Vector3d>& b_nT,
                           const SphereFitOptions& options = {});

}  // namespace magcal
