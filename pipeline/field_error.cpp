#include "pipeline/field_error.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>

#include "pipeline/rotation.hpp"

namespace magcal {
namespace {

// Running rms and worst |value|.
class Accumulator {
 public:
  void add(double value) {
    sum2_ += value * value;
    worst_ = std::max(worst_, std::abs(value));
    ++n_;
  }
  ErrorFigures figures() const {
    ErrorFigures f;
    if (n_ == 0) return f;
    f.n = n_;
    f.rms = std::sqrt(sum2_ / n_);
    f.worst = worst_;
    return f;
  }

 private:
  double sum2_ = 0.0, worst_ = 0.0;
  int n_ = 0;
};

// Both errors of `value` against `reference`; the direction only when `direction_known`.
void add_pair(const Eigen::Vector3d& value, const Eigen::Vector3d& reference, bool direction_known,
              Accumulator& direction_deg, Accumulator& magnitude_nT) {
  magnitude_nT.add(value.norm() - reference.norm());
  if (direction_known) direction_deg.add(angle_between_rad(value, reference) * kRadToDeg);
}

}  // namespace

double angle_between_rad(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b));
}

FieldError field_error(const std::vector<Eigen::Vector3d>& calibrated, const SampleSet& samples) {
  assert(calibrated.size() == samples.size());
  Accumulator direction, magnitude;
  for (std::size_t k = 0; k < samples.size(); ++k) {
    if (!calibrated[k].allFinite()) continue;
    const CalibrationSample& s = samples[k];
    // Without a direction h_body_nT holds |h| in x (CalibrationSample): its norm is still |h|.
    add_pair(calibrated[k], s.h_body_nT, s.has_reference_direction, direction, magnitude);
  }
  return {direction.figures(), magnitude.figures()};
}

FieldError field_difference(const std::vector<Eigen::Vector3d>& a,
                            const std::vector<Eigen::Vector3d>& b) {
  assert(a.size() == b.size());
  Accumulator direction, magnitude;
  for (std::size_t k = 0; k < a.size(); ++k) {
    if (a[k].allFinite() && b[k].allFinite()) add_pair(b[k], a[k], true, direction, magnitude);
  }
  return {direction.figures(), magnitude.figures()};
}

}  // namespace magcal
