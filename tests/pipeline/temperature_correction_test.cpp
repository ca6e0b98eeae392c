// The online filters' temperature correction: a refit's bias temperature model moves each sample
// to the model's reference temperature, a missing temperature takes a recent one, else the sample
// is not for the filter. Checked on hand-made models (the end-to-end accuracy of a filter using
// it: tests/service/daemon/ownership/spacecraft_tracker_test.cpp).
#include <cmath>
#include <limits>

#include <catch2/catch.hpp>

#include "pipeline/temperature_correction.hpp"

using namespace magcal;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr int64_t kEpoch_utime = 1'767'225'600'000'000;  // 2026-01-01T00:00:00Z

CalibrationResult refit_with_model() {
  CalibrationResult r;
  r.parameters.D << 0.02, 0.001, 0.0, 0.001, -0.01, 0.002, 0.0, 0.002, 0.03;
  r.has_temperature_model = true;
  r.reference_temperature_C = 20.0;
  r.temperature_coefficient_nT_per_C = Eigen::Vector3d(1.5, -0.5, 2.0);
  r.temperature_coefficient_covariance = Eigen::Matrix3d::Identity() * 0.01;
  return r;
}

CalibrationSample sample_at(int64_t utime, double temperature_C) {
  CalibrationSample s;
  s.utime = utime;
  s.b_sensor_nT = Eigen::Vector3d(20000.0, -3000.0, 5000.0);
  s.temperature_C = temperature_C;
  return s;
}

}  // namespace

TEST_CASE("a refit's temperature model moves a sample to its reference temperature") {
  const CalibrationResult refit = refit_with_model();
  TemperatureCorrection c;
  c.take_from(refit, 7);
  REQUIRE(c.active);
  CHECK(c.refit_id == 7);
  Eigen::Vector3d b;
  // B' = B - (I + D)^-1 k_T (T - T0), i.e. (I + D) (B - B') = k_T (T - T0).
  const CalibrationSample warm = sample_at(kEpoch_utime, 30.0);
  REQUIRE(c.correct(warm, b));
  const Eigen::Matrix3d I_plus_D = Eigen::Matrix3d::Identity() + refit.parameters.D;
  CHECK((I_plus_D * (warm.b_sensor_nT - b) - refit.temperature_coefficient_nT_per_C * 10.0).norm() <
        1e-9);
  REQUIRE(c.correct(sample_at(kEpoch_utime, 20.0), b));
  CHECK(b == warm.b_sensor_nT);

  CalibrationResult online;
  c.describe(online);
  CHECK(online.has_temperature_model);
  CHECK(online.reference_temperature_C == 20.0);
  CHECK(online.temperature_coefficient_nT_per_C == refit.temperature_coefficient_nT_per_C);
  CHECK(online.temperature_coefficient_covariance == refit.temperature_coefficient_covariance);
}

TEST_CASE("a sample without a temperature takes one at most a minute away, else is unused") {
  TemperatureCorrection c;
  c.take_from(refit_with_model(), 1);
  Eigen::Vector3d at_30;
  REQUIRE(c.correct(sample_at(kEpoch_utime, 30.0), at_30));
  Eigen::Vector3d b;
  const int64_t hold = TemperatureCorrection::kTemperatureHoldMax_utime;
  REQUIRE(c.correct(sample_at(kEpoch_utime + hold, kNaN), b));
  CHECK(b == at_30);
  REQUIRE(c.correct(sample_at(kEpoch_utime - hold, kNaN), b));  // a recorder dump: older
  CHECK(b == at_30);
  CHECK_FALSE(c.correct(sample_at(kEpoch_utime + hold + 1, kNaN), b));
  CHECK(c.n_unused_no_temperature == 1);
}

TEST_CASE("without a usable model the correction changes nothing and uses every sample") {
  CalibrationResult no_model = refit_with_model();
  no_model.has_temperature_model = false;
  CalibrationResult non_finite = refit_with_model();
  non_finite.temperature_coefficient_nT_per_C(1) = kNaN;
  for (const CalibrationResult& refit : {no_model, non_finite}) {
    TemperatureCorrection c;
    c.take_from(refit, 3);
    CHECK_FALSE(c.active);
    CHECK(c.refit_id == 0);
    Eigen::Vector3d b;
    const CalibrationSample s = sample_at(kEpoch_utime, kNaN);
    REQUIRE(c.correct(s, b));
    CHECK(b == s.b_sensor_nT);
    CalibrationResult online;
    c.describe(online);
    CHECK_FALSE(online.has_temperature_model);
  }
}
