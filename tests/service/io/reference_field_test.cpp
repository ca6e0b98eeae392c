// ReferenceField: the service's cached IGRF + Earth orientation, checked against the uncached
// pipeline functions it composes (igrf, frames, rotation) and for errors as values.
#include "service/io/reference_field.hpp"

#include <cmath>
#include <filesystem>
#include <fstream>

#include <unistd.h>

#include <catch2/catch.hpp>

#include "pipeline/time_utc.hpp"

using namespace magcal;

namespace {
// Caching the coefficients for up to an hour moves the field by < ~0.02 nT (secular variation
// is at most ~150 nT/yr at the surface, ~0.4 nT/day).
constexpr double kHourCacheTolerance_nT = 0.02;
constexpr double kExact_nT = 1e-9;
const Eigen::Vector3d kLeo_m(4000e3, -3000e3, 4500e3);
}  // namespace

TEST_CASE("ReferenceField ECEF/ECI/body agree with the uncached pipeline", "[reference_field]") {
  ReferenceField field;
  const int64_t t = utime_from_calendar({2026, 11, 22, 6, 30, 0.0});
  IgrfModel model;
  REQUIRE(model.set_date(decimal_year_from_utime(t)));
  const Eigen::Vector3d b_ecef_ref = model.field_ecef_nT(kLeo_m);

  const auto b_ecef = field.field_ecef_nT(t, kLeo_m);
  REQUIRE(b_ecef);
  CHECK((*b_ecef - b_ecef_ref).norm() < kExact_nT);

  const auto b_eci = field.field_eci_nT(t, kLeo_m);
  REQUIRE(b_eci);
  CHECK((*b_eci - gcrs_from_itrf(t) * b_ecef_ref).norm() < 1e-6);

  const QuaternionWxyz q = QuaternionWxyz(0.7, -0.2, 0.4, 0.1).normalized();
  const auto h_body = field.field_body_nT(t, kLeo_m, q);
  REQUIRE(h_body);
  CHECK((*h_body - dcm_from_quaternion(q) * gcrs_from_itrf(t) * b_ecef_ref).norm() < 1e-6);
  CHECK(std::abs(h_body->norm() - b_ecef_ref.norm()) < 1e-6);
}

TEST_CASE("ReferenceField re-interpolates only after ~1 hour", "[reference_field]") {
  ReferenceField field;
  const int64_t t0 = utime_from_calendar({2024, 3, 1, 0, 0, 0.0});
  REQUIRE(field.field_ecef_nT(t0, kLeo_m));
  const double date0 = field.model().date();
  // Half an hour later: same coefficients, field within the hour-cache tolerance of exact.
  const int64_t t1 = t0 + 1800LL * kMicrosPerSecond;
  const auto b1 = field.field_ecef_nT(t1, kLeo_m);
  REQUIRE(b1);
  CHECK(field.model().date() == date0);
  IgrfModel exact;
  REQUIRE(exact.set_date(decimal_year_from_utime(t1)));
  CHECK((*b1 - exact.field_ecef_nT(kLeo_m)).norm() < kHourCacheTolerance_nT);
  // Two hours later: re-interpolated.
  const int64_t t2 = t0 + 2LL * 3600 * kMicrosPerSecond;
  REQUIRE(field.field_ecef_nT(t2, kLeo_m));
  CHECK(field.model().date() == decimal_year_from_utime(t2));
}

TEST_CASE("ReferenceField returns nullopt, not NaN, for bad inputs", "[reference_field]") {
  ReferenceField field;
  const int64_t too_late = utime_from_calendar({2031, 1, 1, 0, 0, 0.0});
  const int64_t too_early = utime_from_calendar({1899, 6, 1, 0, 0, 0.0});
  const int64_t ok = utime_from_calendar({2025, 1, 1, 0, 0, 0.0});
  CHECK_FALSE(field.field_ecef_nT(too_late, kLeo_m));
  CHECK_FALSE(field.field_eci_nT(too_early, kLeo_m));
  CHECK_FALSE(field.field_body_nT(too_late, kLeo_m, QuaternionWxyz(1, 0, 0, 0)));
  CHECK_FALSE(field.is_valid_time(too_late));
  CHECK(field.is_valid_time(ok));
  const double nan = std::nan("");
  CHECK_FALSE(field.field_ecef_nT(ok, Eigen::Vector3d(nan, 0, 7e6)));
  CHECK_FALSE(field.field_ecef_nT(ok, Eigen::Vector3d::Zero()));
  CHECK_FALSE(field.field_body_nT(ok, kLeo_m, QuaternionWxyz(nan, 0, 0, 0)));
  CHECK_FALSE(field.field_body_nT(ok, kLeo_m, QuaternionWxyz::Zero()));
  // A refused date leaves the model usable.
  CHECK(field.field_ecef_nT(ok, kLeo_m));
}

TEST_CASE("ReferenceField::from_file reports errors as values", "[reference_field]") {
  std::string err;
  CHECK(ReferenceField::from_file("", &err) != nullptr);  // built-in
  CHECK(ReferenceField::from_file("/nonexistent/igrf.txt", &err) == nullptr);
  CHECK(err.find("cannot open") != std::string::npos);

  const auto path = std::filesystem::temp_directory_path() /
                    ("magcal_reference_field_test_" + std::to_string(::getpid()) + ".shc");
  {
    std::ofstream f(path);
    f << "1 1 2 2 1 2000.0 2005.0\n2000.0 2005.0\n1 0 -29000 -29010\n1 1 -1700 x\n";
  }
  CHECK(ReferenceField::from_file(path.string(), &err) == nullptr);
  CHECK(err.find("line 4") != std::string::npos);
  CHECK(err.find(path.filename().string()) != std::string::npos);
  {
    std::ofstream f(path);
    f << "1 1 2 2 1 2000.0 2005.0\n2000.0 2005.0\n1 0 -29000 -29010\n1 1 -1700 -1690\n"
         "1 -1 5000 4990\n";
  }
  const auto custom = ReferenceField::from_file(path.string(), &err);
  REQUIRE(custom != nullptr);
  CHECK(custom->field_ecef_nT(utime_from_calendar({2003, 1, 1, 0, 0, 0.0}), kLeo_m));
  CHECK_FALSE(custom->field_ecef_nT(utime_from_calendar({2006, 1, 1, 0, 0, 0.0}), kLeo_m));
  std::filesystem::remove(path);
}
