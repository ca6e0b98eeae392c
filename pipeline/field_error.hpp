// The field error a calibration leaves, as attitude determination sees it: over a window's
// samples, the calibrated field B_cal,k (body frame) against the reference field h_k,
//   direction error  angle(B_cal,k, h_k)  (degrees; samples with a reference direction only),
//   magnitude error  |B_cal,k| - |h_k|    (nT; every sample),
// each as its rms and its worst (largest absolute value) over the window. Measurement noise and
// reference (IGRF, attitude) errors are in it as the on-board software meets them; for two
// calibrations applied to the same samples they are common, so the difference of their figures
// is the calibrations' own. field_difference() compares two calibrated fields directly (no
// reference: what uploading one instead of the other changes).
#pragma once

#include <limits>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"

namespace magcal {

// rms and worst |value| of one error over a window; n = 0 (and NaN figures): none computed.
struct ErrorFigures {
  int n = 0;
  double rms = std::numeric_limits<double>::quiet_NaN();
  double worst = std::numeric_limits<double>::quiet_NaN();
};

struct FieldError {
  ErrorFigures direction_deg;
  ErrorFigures magnitude_nT;
  bool computed() const { return magnitude_nT.rms == magnitude_nT.rms; }  // not NaN
};

// calibrated[k] is sample k's calibrated field in the body frame (a non-finite vector: none, e.g.
// no temperature for a table with a temperature term; left out). Direction errors only for
// samples with has_reference_direction. Sizes must match.
FieldError field_error(const std::vector<Eigen::Vector3d>& calibrated, const SampleSet& samples);

// The error of `b` taken against `a` as the reference, sample by sample (every pair of finite
// vectors has a direction).
FieldError field_difference(const std::vector<Eigen::Vector3d>& a,
                            const std::vector<Eigen::Vector3d>& b);

// Angle between two vectors, radians, accurate for small angles (atan2 of |a x b| and a . b).
double angle_between_rad(const Eigen::Vector3d& a, const Eigen::Vector3d& b);

}  // namespace magcal
