// Reference field with caches (see reference_field.hpp).
#include "service/io/reference_field.hpp"

#include <cmath>
#include <fstream>
#include <sstream>

#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {
// Precession-nutation refresh (data time): NPB moves by ~1e-6 arcsec per second.
constexpr double kEarthOrientationRefresh_s = 1.0;
}  // namespace

ReferenceField::ReferenceField(double dut1_s) : ReferenceField(builtin_igrf14(), dut1_s) {}

ReferenceField::ReferenceField(const IgrfCoefficientTable& table, double dut1_s)
    : model_(table), earth_(kEarthOrientationRefresh_s, dut1_s) {}

std::unique_ptr<ReferenceField> ReferenceField::from_file(const std::string& path,
                                                          std::string* error, double dut1_s) {
  if (path.empty()) return std::make_unique<ReferenceField>(dut1_s);
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    if (error) *error = "cannot open IGRF coefficient file '" + path + "'";
    return nullptr;
  }
  std::ostringstream text;
  text << in.rdbuf();
  std::string parse_error;
  const auto table = parse_igrf_coefficients(text.str(), &parse_error);
  if (!table) {
    if (error) *error = "IGRF coefficient file '" + path + "': " + parse_error;
    return nullptr;
  }
  return std::make_unique<ReferenceField>(*table, dut1_s);
}

bool ReferenceField::is_valid_time(int64_t utime) const {
  return model_.is_valid_date(decimal_year_from_utime(utime));
}

bool ReferenceField::prepare_date(int64_t utime) {
  const double year = decimal_year_from_utime(utime);
  if (!model_.is_valid_date(year)) return false;
  if (!have_date_ || std::abs(year - model_.date()) > kCoefficientRefreshYears) {
    model_.set_date(year);
    have_date_ = true;
  }
  return true;
}

std::optional<Eigen::Vector3d> ReferenceField::field_ecef_nT(int64_t utime,
                                                             const Eigen::Vector3d& r_ecef_m) {
  // A position at (or numerically near) the Earth's centre has no field value worth returning.
  if (!r_ecef_m.allFinite() || r_ecef_m.norm() < 1.0) return std::nullopt;
  if (!prepare_date(utime)) return std::nullopt;
  return model_.field_ecef_nT(r_ecef_m);
}

std::optional<Eigen::Vector3d> ReferenceField::field_eci_nT(int64_t utime,
                                                            const Eigen::Vector3d& r_ecef_m) {
  const auto b_ecef = field_ecef_nT(utime, r_ecef_m);
  if (!b_ecef) return std::nullopt;
  return Eigen::Vector3d(earth_.gcrs_from_itrf(utime) * *b_ecef);
}

std::optional<Eigen::Vector3d> ReferenceField::field_body_nT(
    int64_t utime, const Eigen::Vector3d& r_ecef_m, const QuaternionWxyz& q_body_from_eci) {
  if (!q_body_from_eci.allFinite() || q_body_from_eci.norm() < 0.5) return std::nullopt;
  const auto b_eci = field_eci_nT(utime, r_ecef_m);
  if (!b_eci) return std::nullopt;
  return rotate_vector(q_body_from_eci, *b_eci);
}

}  // namespace magcal
