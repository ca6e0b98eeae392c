#include "pipeline/calibration_table.hpp"

#include <algorithm>
#include <cmath>
#include <random>

#include <Eigen/Geometry>
#include <catch2/catch.hpp>

#include "pipeline/calibration_difference.hpp"
#include "pipeline/field_error.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {
namespace {

// A calibration with every term: alignment, temperature coefficient and bias rate.
CalibrationResult full_result() {
  CalibrationResult r;
  r.parameters.bias_nT = Eigen::Vector3d(1000.3, -800.7, 912.1);
  r.parameters.D << 0.011, 0.002, -0.003, 0.002, -0.02, 0.004, -0.003, 0.004, 0.013;
  r.has_alignment = true;
  r.alignment.R_sensor_from_body =
      Eigen::AngleAxisd(0.03, Eigen::Vector3d(1.0, -2.0, 0.5).normalized()).toRotationMatrix();
  r.has_temperature_model = true;
  r.reference_temperature_C = 21.37;
  r.temperature_coefficient_nT_per_C = Eigen::Vector3d(1.5, -0.7, 2.2);
  r.has_bias_rate = true;
  r.window_end_utime = 1'600'000'000'000'000;
  r.bias_rate_nT_per_h = Eigen::Vector3d(0.2, 0.05, -0.1);
  return r;
}

// estimation.md section 1, written out independently of the table.
Eigen::Vector3d calibrated_by_the_model(const CalibrationResult& r, const Eigen::Vector3d& B,
                                        double T, int64_t utime) {
  const double hours = static_cast<double>(utime - r.window_end_utime) / 3.6e9;
  const Eigen::Vector3d bias =
      r.parameters.bias_nT + r.temperature_coefficient_nT_per_C * (T - r.reference_temperature_C) +
      r.bias_rate_nT_per_h * hours;
  return r.alignment.R_sensor_from_body.transpose() *
         ((Eigen::Matrix3d::Identity() + r.parameters.D) * B - bias);
}

TEST_CASE("calibration table: M B - o - o_T dT - o_r dt is the model's calibrated field") {
  const CalibrationResult r = full_result();
  const CalibrationTable t = calibration_table(r);
  std::mt19937_64 rng(7);
  std::normal_distribution<double> n(0.0, 30000.0);
  for (int k = 0; k < 50; ++k) {
    const Eigen::Vector3d B(n(rng), n(rng), n(rng));
    const double T = 10.0 + 0.5 * k;
    const int64_t utime = r.window_end_utime - int64_t{k} * 600'000'000;
    const Eigen::Vector3d expected = calibrated_by_the_model(r, B, T, utime);
    REQUIRE((t.apply(B, T, utime) - expected).norm() < 1e-9 * expected.norm());
  }
  // Without a temperature the bias of a table with a temperature term is unknown.
  CHECK_FALSE(t.apply(Eigen::Vector3d(1e4, 0, 0), std::nan(""), r.window_end_utime).allFinite());
}

TEST_CASE("calibration table: without alignment or terms, R = I and T, t are not used") {
  CalibrationResult r;
  r.parameters.bias_nT = Eigen::Vector3d(1.0, 2.0, 3.0);
  r.parameters.D = Eigen::Matrix3d::Identity() * 0.01;
  const CalibrationTable t = calibration_table(r);
  CHECK(t.M.isApprox(Eigen::Matrix3d::Identity() * 1.01));
  CHECK(t.offset_nT.isApprox(r.parameters.bias_nT));
  const Eigen::Vector3d B(20000.0, -5000.0, 100.0);
  CHECK(t.apply(B, std::nan(""), 12345).isApprox(r.parameters.apply(B)));
}

TEST_CASE("float32 rounding: the stated bound holds on random fields and is not loose") {
  const CalibrationTable exact = calibration_table(full_result());
  const CalibrationTable rounded = float32_rounded(exact);
  constexpr double kField_nT = 70000.0;
  const TableRoundingError e = rounding_error(exact, rounded, kField_nT);
  REQUIRE(e.at_field_nT > 0.0);
  CHECK(e.at_field_nT < 0.05);  // float32: ~6e-8 relative of 7e4 nT, a few 1e-3 nT
  std::mt19937_64 rng(11);
  std::normal_distribution<double> n(0.0, 1.0);
  double worst = 0.0;
  for (int k = 0; k < 20000; ++k) {
    const Eigen::Vector3d B = Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized() * kField_nT;
    const double T = exact.reference_temperature_C;
    const double d = (rounded.apply(B, T, exact.rate_reference_utime) -
                      exact.apply(B, T, exact.rate_reference_utime))
                         .norm();
    worst = std::max(worst, d);
  }
  CHECK(worst <= e.at_field_nT);
  CHECK(worst > 0.3 * e.at_field_nT);
  // Per degC and per hour: the rounding of o_T and o_r.
  const Eigen::Vector3d B(kField_nT, 0.0, 0.0);
  const double at_ref =
      (rounded.apply(B, exact.reference_temperature_C, exact.rate_reference_utime) -
       exact.apply(B, exact.reference_temperature_C, exact.rate_reference_utime))
          .norm();
  const double ten_degrees =
      (rounded.apply(B, exact.reference_temperature_C + 10.0, exact.rate_reference_utime) -
       exact.apply(B, exact.reference_temperature_C + 10.0, exact.rate_reference_utime))
          .norm();
  CHECK(ten_degrees <= at_ref + 10.0 * e.per_C_nT + 1e-12);
}

TEST_CASE("field error: direction and magnitude against an independent computation") {
  SampleSet samples(3);
  samples[0].h_body_nT = Eigen::Vector3d(30000.0, 0.0, 0.0);
  samples[1].h_body_nT = Eigen::Vector3d(0.0, 40000.0, 0.0);
  samples[2].h_body_nT = Eigen::Vector3d(25000.0, 0.0, 0.0);  // |h| only
  samples[2].has_reference_direction = false;
  const double angle_rad = 1e-3;
  std::vector<Eigen::Vector3d> calibrated = {
      Eigen::Vector3d(30010.0 * std::cos(angle_rad), 30010.0 * std::sin(angle_rad), 0.0),
      Eigen::Vector3d(0.0, 39995.0, 0.0), Eigen::Vector3d(0.0, 0.0, 25003.0)};
  FieldError e = field_error(calibrated, samples);
  CHECK(e.direction_deg.n == 2);
  CHECK(e.direction_deg.rms == Approx(std::sqrt(0.5) * angle_rad * kRadToDeg).epsilon(1e-9));
  CHECK(e.direction_deg.worst == Approx(angle_rad * kRadToDeg).epsilon(1e-9));
  CHECK(e.magnitude_nT.n == 3);
  CHECK(e.magnitude_nT.rms == Approx(std::sqrt((100.0 + 25.0 + 9.0) / 3.0)).epsilon(1e-9));
  CHECK(e.magnitude_nT.worst == Approx(10.0).epsilon(1e-9));
  CHECK(e.computed());
  // A vector without a value (no temperature) is left out.
  calibrated[0] = Eigen::Vector3d::Constant(std::nan(""));
  e = field_error(calibrated, samples);
  CHECK(e.magnitude_nT.n == 2);
  CHECK(e.magnitude_nT.worst == Approx(5.0).epsilon(1e-9));
  // Nothing to measure: not computed.
  CHECK_FALSE(field_error({}, {}).computed());
}

TEST_CASE("field difference: two calibrated fields, one as the other's reference") {
  const std::vector<Eigen::Vector3d> a = {Eigen::Vector3d(1e4, 0.0, 0.0)};
  const std::vector<Eigen::Vector3d> b = {Eigen::AngleAxisd(2e-4, Eigen::Vector3d::UnitZ()) *
                                          Eigen::Vector3d(1e4 + 3.0, 0.0, 0.0)};
  const FieldError e = field_difference(a, b);
  CHECK(e.direction_deg.rms == Approx(2e-4 * kRadToDeg).epsilon(1e-9));
  CHECK(e.magnitude_nT.rms == Approx(3.0).epsilon(1e-9));
}

TEST_CASE("calibration difference: z, chi-square and the alignment's rotation") {
  CalibrationResult a = full_result(), b = full_result();
  a.covariance = Matrix9d::Identity() * 0.25;
  b.covariance = Matrix9d::Identity() * 0.25;
  a.alignment.angle_covariance_rad2 = Eigen::Matrix3d::Identity() * 1e-8;
  b.alignment.angle_covariance_rad2 = Eigen::Matrix3d::Identity() * 1e-8;
  CalibrationDifference d = calibration_difference(a, b);
  CHECK(d.chi2 == Approx(0.0).margin(1e-12));
  CHECK_FALSE(d.significant);
  b.parameters.bias_nT.x() += 2.0;  // sigma of the difference: sqrt(0.5)
  b.alignment.R_sensor_from_body =
      Eigen::AngleAxisd(3e-4, Eigen::Vector3d::UnitY()) * a.alignment.R_sensor_from_body;
  d = calibration_difference(a, b);
  CHECK(d.z(0) == Approx(2.0 / std::sqrt(0.5)));
  CHECK(d.chi2 == Approx(8.0));
  CHECK_FALSE(d.chi2 > CalibrationDifference::kChi2Quantile99_9dof);
  CHECK(d.dtheta_rad.isApprox(Eigen::Vector3d(0.0, 3e-4, 0.0), 1e-9));
  CHECK(d.alignment_chi2 == Approx(9e-8 / 2e-8));
  CHECK_FALSE(d.significant);
  b.parameters.bias_nT.x() += 2.0;
  CHECK(calibration_difference(a, b).significant);  // chi2 32
  // An unknown covariance is never called significant.
  a.covariance.setZero();
  b.covariance.setZero();
  d = calibration_difference(a, b);
  CHECK(std::isnan(d.chi2));
}

}  // namespace
}  // namespace magcal
