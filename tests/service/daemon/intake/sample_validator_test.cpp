// Bad input (design.md): each reason fires on its condition and only then; the reference field
// stored with a sample is h_body when given, else IGRF rotated with the attitude, else |h|.
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/daemon/intake/sample_validator.hpp"

using namespace magcal;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kFieldTol_nT = 1e-6;

mag_sample_t good_sample() {
  mag_sample_t s{};
  s.utime = *parse_iso8601_utc("2024-06-01T12:00:00Z");
  s.sat_id = "SAT-1";
  s.seq = 1;
  s.b_sensor_nT[0] = 20000.0;
  s.b_sensor_nT[1] = -15000.0;
  s.b_sensor_nT[2] = 30000.0;
  s.has_position = true;
  s.r_ecef_m[0] = 6921000.0;
  s.r_ecef_m[1] = 100000.0;
  s.r_ecef_m[2] = -50000.0;
  s.has_attitude = true;
  s.q_body_from_eci[0] = std::cos(0.3);
  s.q_body_from_eci[3] = std::sin(0.3);
  s.has_reference = false;
  s.temperature_C = std::nanf("");  // unknown temperature is fine
  return s;
}

std::optional<RejectReason> check(const mag_sample_t& s, const std::string& batch = "",
                                  ValidatorOptions o = {}) {
  return check_sample(s, batch, o);
}

}  // namespace

TEST_CASE("a good sample passes, NaN temperature included", "[sample_validator]") {
  CHECK_FALSE(check(good_sample()));
  auto s = good_sample();
  s.has_position = false;
  s.has_reference = true;
  s.h_body_nT[0] = 30000.0;
  CHECK_FALSE(check(s));
}

TEST_CASE("each rejection reason fires on its condition", "[sample_validator]") {
  SECTION("non_finite in b") {
    auto s = good_sample();
    s.b_sensor_nT[1] = kNaN;
    CHECK(check(s) == RejectReason::kNonFinite);
    s.b_sensor_nT[1] = std::numeric_limits<double>::infinity();
    CHECK(check(s) == RejectReason::kNonFinite);
  }
  SECTION("non_finite only counts in flagged fields") {
    auto s = good_sample();
    s.h_body_nT[0] = kNaN;  // has_reference false: ignored
    CHECK_FALSE(check(s));
    s.has_reference = true;
    CHECK(check(s) == RejectReason::kNonFinite);
    s = good_sample();
    s.r_ecef_m[2] = kNaN;
    CHECK(check(s) == RejectReason::kNonFinite);
    s.has_position = false;
    s.has_reference = true;
    s.h_body_nT[0] = 1.0;
    CHECK_FALSE(check(s));
    s = good_sample();
    s.q_body_from_eci[1] = kNaN;
    CHECK(check(s) == RejectReason::kNonFinite);
  }
  SECTION("bad attitude") {
    auto s = good_sample();
    s.q_body_from_eci[0] = 0.0;
    s.q_body_from_eci[3] = 0.0;
    CHECK(check(s) == RejectReason::kBadAttitude);
  }
  SECTION("zero vector: a sensor dropout") {
    auto s = good_sample();
    for (double& b : s.b_sensor_nT) b = 0.0;
    CHECK(check(s) == RejectReason::kZeroVector);
    CHECK(std::string(to_string(RejectReason::kZeroVector)) == "zero_vector");
    s.b_sensor_nT[2] = 1e-3;  // small, but a measurement
    CHECK_FALSE(check(s).has_value());
  }
  SECTION("out of range") {
    auto s = good_sample();
    s.b_sensor_nT[2] = -100000.5;
    CHECK(check(s) == RejectReason::kOutOfRange);
    s.b_sensor_nT[2] = 100000.0;  // at the range: accepted
    CHECK_FALSE(check(s));
    ValidatorOptions o;
    o.range_nT = 50000.0;
    s.b_sensor_nT[2] = 60000.0;
    CHECK(check(s, "", o) == RejectReason::kOutOfRange);
  }
  SECTION("absurd position") {
    auto s = good_sample();
    s.r_ecef_m[0] = 6.3e6;
    s.r_ecef_m[1] = s.r_ecef_m[2] = 0.0;
    CHECK(check(s) == RejectReason::kAbsurdPosition);
    s.r_ecef_m[0] = 8.1e6;
    CHECK(check(s) == RejectReason::kAbsurdPosition);
    s.r_ecef_m[0] = 7.9e6;
    CHECK_FALSE(check(s));
    s.r_ecef_m[0] = 0.0;  // "no fix" sent with the flag set
    CHECK(check(s) == RejectReason::kAbsurdPosition);
  }
  SECTION("no reference") {
    auto s = good_sample();
    s.has_position = false;
    CHECK(check(s) == RejectReason::kNoReference);
  }
  SECTION("batch membership and sat ids") {
    auto s = good_sample();
    CHECK(check(s, "SAT-2") == RejectReason::kBatchSatMismatch);
    CHECK_FALSE(check(s, "SAT-1"));
    s.sat_id.clear();
    CHECK_FALSE(check(s, "SAT-1"));  // inherits the batch's id
    CHECK(sample_sat_id(s, "SAT-1") == "SAT-1");
    CHECK(check(s) == RejectReason::kInvalidSatId);
  }
  SECTION("sat ids that are not UTF-8, or too long") {
    auto s = good_sample();
    for (const std::string bad : {"SAT-\xbc", "\xc3", "\xc0\xaf", "\xe0\x80\xaf", "\xed\xa0\x80",
                                  "\xf4\x90\x80\x80", "\xff", "SAT-\xe2\x82"}) {
      INFO(bad);
      s.sat_id = bad;
      CHECK(check(s) == RejectReason::kInvalidSatId);
      CHECK(check(good_sample(), bad) == RejectReason::kBatchSatMismatch);
    }
    s.sat_id = std::string(kMaxSatIdBytes + 1, 'S');
    CHECK(check(s) == RejectReason::kInvalidSatId);
    s.sat_id = std::string(kMaxSatIdBytes, 'S');
    CHECK_FALSE(check(s));
    for (const std::string good : {"SAT-\xc3\xa9", "\xe2\x82\xac-1", "\xf0\x9f\x9b\xb0", "\x7f"}) {
      INFO(good);
      s.sat_id = good;
      CHECK_FALSE(check(s));
    }
  }
  SECTION("whitelist") {
    ValidatorOptions o;
    o.whitelist = {"SAT-0", "SAT-1"};
    CHECK_FALSE(check(good_sample(), "", o));
    auto s = good_sample();
    s.sat_id = "INTRUDER";
    CHECK(check(s, "", o) == RejectReason::kUnknownSpacecraft);
  }
}

TEST_CASE("reference field: given, IGRF rotated with attitude, or magnitude only",
          "[sample_validator]") {
  ReferenceField field;
  // Independent composition from the pipeline parts (igrf, frames, rotation).
  auto s = good_sample();
  IgrfModel model;
  REQUIRE(model.set_date(decimal_year_from_utime(s.utime)));
  const Eigen::Vector3d r(s.r_ecef_m[0], s.r_ecef_m[1], s.r_ecef_m[2]);
  const Eigen::Vector3d b_ecef = model.field_ecef_nT(r);
  const Eigen::Vector3d b_eci = gcrs_from_itrf(s.utime) * b_ecef;
  const QuaternionWxyz q(s.q_body_from_eci[0], s.q_body_from_eci[1], s.q_body_from_eci[2],
                         s.q_body_from_eci[3]);
  const Eigen::Vector3d expect_body = dcm_from_quaternion(q) * b_eci;

  const auto with_attitude = to_reference_sample(s, field);
  REQUIRE(with_attitude);
  CHECK(with_attitude->has_reference_direction);
  // 1 nT covers the once-per-day coefficient refresh and the cached precession-nutation.
  CHECK((with_attitude->h_body_nT - expect_body).norm() < 1.0);
  CHECK(with_attitude->b_sensor_nT.x() == s.b_sensor_nT[0]);

  s.has_attitude = false;
  const auto magnitude_only = to_reference_sample(s, field);
  REQUIRE(magnitude_only);
  CHECK_FALSE(magnitude_only->has_reference_direction);
  CHECK(magnitude_only->h_body_nT.x() == Approx(b_ecef.norm()).epsilon(1e-6));
  CHECK(magnitude_only->h_body_nT.y() == 0.0);

  s.has_reference = true;
  s.h_body_nT[0] = 1.0;
  s.h_body_nT[1] = 2.0;
  s.h_body_nT[2] = 3.0;
  const auto given = to_reference_sample(s, field);
  REQUIRE(given);
  CHECK((given->h_body_nT - Eigen::Vector3d(1, 2, 3)).norm() < kFieldTol_nT);

  // The temperature goes with the sample (the refits' and the tracker's temperature model);
  // NaN, Inf or a value no sensor survives is unknown, and the sample stays valid.
  s.temperature_C = 21.5f;
  REQUIRE(to_reference_sample(s, field));
  CHECK(to_reference_sample(s, field)->temperature_C == 21.5);
  for (const float bad : {std::numeric_limits<float>::quiet_NaN(),
                          std::numeric_limits<float>::infinity(), 1e6f, -300.0f}) {
    s.temperature_C = bad;
    CHECK_FALSE(check_sample(s, "", ValidatorOptions{}));
    const auto unknown = to_reference_sample(s, field);
    REQUIRE(unknown);
    CHECK(std::isnan(unknown->temperature_C));
  }

  // Outside IGRF-14's validity (1900-2030): no reference, never NaN.
  auto old = good_sample();
  old.utime = *parse_iso8601_utc("1890-01-01T00:00:00Z");
  CHECK_FALSE(to_reference_sample(old, field));
}
