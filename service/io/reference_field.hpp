// Reference magnetic field for the service: IGRF (pipeline/igrf.hpp) evaluated at an ECEF
// position and rotated into ECI (GCRS, pipeline/frames.hpp) or the body frame.
//
//   B_ecef  = IGRF(t, r_ecef)                              (nT, ITRF axes)
//   B_eci   = GCRS_from_ITRF(t) B_ecef                     (nT, GCRS axes)
//   h_body  = A(q_body_from_eci) B_eci                     (nT, body axes; estimation.md s. 0)
//
// Caches (why this is a class and lives in service/, not pipeline/):
//   - the IGRF coefficients are re-interpolated only when the date moves by more than
//     kCoefficientRefreshYears (~1 hour, as the simulator: the secular variation moves the field
//     by < 0.02 nT an hour; a day's ~0.3 nT drift, though below the model's accuracy, moved a
//     tumbling thermal day's temperature coefficient by 0.2 sigma against the simulator's field);
//   - the precession-nutation matrix is recomputed at most once per second of data time
//     (EarthOrientationCache); the Earth rotation angle is exact every call.
// Not thread-safe: one ReferenceField per worker thread.
//
// Errors are values: construction from a file reports a message; evaluation at a date outside
// the model's validity, at a non-finite position or the Earth's centre, or with a non-finite or
// zero quaternion returns nullopt, never NaN. (Quaternions are normalised before use.)
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include <Eigen/Core>

#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {

class ReferenceField {
 public:
  // Re-interpolate the coefficients when the date moves by more than this (1 hour).
  static constexpr double kCoefficientRefreshYears = 1.0 / 8784.0;

  // Built-in IGRF-14.
  explicit ReferenceField(double dut1_s = 0.0);
  // From a coefficient table already in memory.
  explicit ReferenceField(const IgrfCoefficientTable& table, double dut1_s = 0.0);

  // Loads an official IGRF coefficient file (.txt table or .shc); empty path = built-in
  // IGRF-14. On failure returns nullptr and sets *error to one clear line (file name, line).
  static std::unique_ptr<ReferenceField> from_file(const std::string& coefficients_path,
                                                   std::string* error, double dut1_s = 0.0);

  // Field at r_ecef_m (metres, ITRF) at utime, in ECEF axes (nT). nullopt outside validity.
  std::optional<Eigen::Vector3d> field_ecef_nT(int64_t utime, const Eigen::Vector3d& r_ecef_m);
  // Same field expressed in GCRS (ECI) axes.
  std::optional<Eigen::Vector3d> field_eci_nT(int64_t utime, const Eigen::Vector3d& r_ecef_m);
  // Same field in the body frame: h_body = A(q_body_from_eci) B_eci. q is (w, x, y, z).
  std::optional<Eigen::Vector3d> field_body_nT(int64_t utime, const Eigen::Vector3d& r_ecef_m,
                                               const QuaternionWxyz& q_body_from_eci);

  // True if the model covers this time.
  bool is_valid_time(int64_t utime) const;
  const std::string& model_name() const { return model_.table().name; }
  const IgrfModel& model() const { return model_; }

  // GCRS_from_ITRF at utime (cached precession-nutation).
  const Eigen::Matrix3d& gcrs_from_itrf(int64_t utime) { return earth_.gcrs_from_itrf(utime); }

 private:
  bool prepare_date(int64_t utime);

  IgrfModel model_;
  EarthOrientationCache earth_;
  bool have_date_ = false;
};

}  // namespace magcal
