// What goes out on LCM (calibration_t) never carries NaN or Inf (issue 11): a failed refit's
// unknown residual and non-finite estimates are replaced by the documented conventions
// (service/io/calibration_record.hpp), and a finite result goes out unchanged.
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <vector>

#include "service/io/calibration_record.hpp"

using namespace magcal;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

CalibrationResult finite_result() {
  CalibrationResult r;
  r.method = "twostep";
  r.utime = 1704067200000000;
  r.n_samples = 4320;
  Vector9d p;
  p << 1000.0, -800.0, 900.0, 0.01, 0.02, -0.01, 0.002, -0.001, 0.003;
  r.parameters = CalibrationParameters::from_packed(p);
  r.covariance = Matrix9d::Identity() * 0.25;
  r.residual_rms_nT = 7.1;
  r.status = CalibrationStatus::kOk;
  r.accepted = true;
  return r;
}

// Every double of the message, decoded from its encoding (what a subscriber sees).
std::vector<double> doubles_on_the_wire(const calibration_t& msg) {
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  REQUIRE(msg.encode(bytes.data(), 0, static_cast<int>(bytes.size())) ==
          static_cast<int>(bytes.size()));
  calibration_t back;
  REQUIRE(back.decode(bytes.data(), 0, static_cast<int>(bytes.size())) ==
          static_cast<int>(bytes.size()));
  std::vector<double> v(back.bias_nT, back.bias_nT + 3);
  v.insert(v.end(), back.D, back.D + 6);
  v.insert(v.end(), back.cov, back.cov + 45);
  v.insert(v.end(), back.R_sensor_from_body, back.R_sensor_from_body + 9);
  v.push_back(back.residual_rms_nT);
  return v;
}

}  // namespace

TEST_CASE("a finite result goes out unchanged", "[calibration_record]") {
  const auto r = finite_result();
  const calibration_t msg = message_from_result("SAT-1", r);
  const calibration_t raw = storage::message_from_record(record_from_result("SAT-1", r));
  CHECK(msg.residual_rms_nT == raw.residual_rms_nT);
  CHECK(msg.status == raw.status);
  for (int i = 0; i < 45; ++i) CHECK(msg.cov[i] == raw.cov[i]);
  for (int i = 0; i < 3; ++i) CHECK(msg.bias_nT[i] == raw.bias_nT[i]);
}

TEST_CASE("a failed refit publishes no NaN", "[calibration_record]") {
  struct Case {
    const char* name;
    CalibrationStatus status;
    bool nan_estimate;
    int8_t expect_status;
  };
  const Case cases[] = {
      {"ok with an unknown residual", CalibrationStatus::kOk, false, 0},
      {"failed, NaN everywhere", CalibrationStatus::kFailed, true, 3},
      {"ok claimed, NaN estimate", CalibrationStatus::kOk, true, 3},
      {"rejected, NaN estimate", CalibrationStatus::kRejected, true, 3},
      {"unobservable, NaN estimate", CalibrationStatus::kUnobservable, true, 2},
  };
  for (const auto& c : cases) {
    DYNAMIC_SECTION(c.name) {
      auto r = finite_result();
      r.status = c.status;
      r.residual_rms_nT = kNaN;
      if (c.nan_estimate) {
        r.covariance(2, 5) = kNaN;
        r.covariance(0, 0) = kInf;
        r.parameters.bias_nT(1) = kNaN;
        r.has_alignment = true;
        r.alignment.R_sensor_from_body(1, 1) = -kInf;
      }
      const calibration_t msg = message_from_result("SAT-1", r);
      for (const double v : doubles_on_the_wire(msg)) CHECK(std::isfinite(v));
      CHECK(msg.residual_rms_nT == -1.0);  // unknown
      CHECK(msg.status == c.expect_status);
      if (c.nan_estimate) {
        CHECK(msg.bias_nT[1] == 0.0);
        CHECK(msg.bias_nT[0] == 1000.0);  // finite entries are kept
        CHECK(msg.cov[storage::cov_index(0, 0)] == 0.0);
        CHECK(msg.cov[storage::cov_index(2, 5)] == 0.0);
        CHECK(msg.cov[storage::cov_index(1, 1)] == 0.25);
      }
    }
  }
}

TEST_CASE("the bias temperature model goes through the history record and back",
          "[calibration_record]") {
  auto r = finite_result();
  r.has_temperature_model = true;
  r.reference_temperature_C = 17.25;
  r.temperature_coefficient_nT_per_C = Eigen::Vector3d(1.5, -0.75, 0.1);
  Eigen::Matrix3d cov;
  cov << 4e-4, 1e-5, -2e-6, 1e-5, 9e-4, 3e-6, -2e-6, 3e-6, 2.5e-5;
  r.temperature_coefficient_covariance = cov;
  const storage::CalibrationRecord rec = record_from_result("SAT-1", r);
  CHECK(rec.has_temperature_model == 1);
  const CalibrationResult back = result_from_record(rec);
  CHECK(back.has_temperature_model);
  CHECK(back.reference_temperature_C == r.reference_temperature_C);
  CHECK(back.temperature_coefficient_nT_per_C == r.temperature_coefficient_nT_per_C);
  CHECK(back.temperature_coefficient_covariance == cov);
  CHECK(back.parameters.bias_nT == r.parameters.bias_nT);

  // calibration_t has no temperature fields (a fixed contract): its bias is the bias at T0.
  const calibration_t msg = message_from_result("SAT-1", r);
  for (int i = 0; i < 3; ++i) CHECK(msg.bias_nT[i] == r.parameters.bias_nT(i));

  SECTION("a refit without the model says it has none; a filter says nothing") {
    auto plain = finite_result();
    CHECK(record_from_result("SAT-1", plain).has_temperature_model == 0);
    plain.method = "ukf";
    CHECK(record_from_result("SAT-1", plain).has_temperature_model == -1);
    CHECK_FALSE(result_from_record(record_from_result("SAT-1", plain)).has_temperature_model);
  }
}

TEST_CASE("a stored sample's temperature comes back with it (refit windows, UKF re-runs)",
          "[calibration_record]") {
  mag_sample_t msg{};
  msg.utime = 1704067200000000;
  msg.temperature_C = 99.0f;  // the message's: not the one stored (to_reference_sample judges)
  CalibrationSample sample;
  sample.utime = msg.utime;
  sample.h_body_nT = Eigen::Vector3d(20000.0, 0.0, 0.0);
  for (const double t : {-12.5, kNaN}) {
    sample.temperature_C = t;
    storage::StoredSample stored;
    fill_stored_sample(msg, "SAT-1", sample, 0, stored);
    const CalibrationSample back = calibration_sample_from_stored(stored);
    if (std::isnan(t))
      CHECK(std::isnan(back.temperature_C));
    else
      CHECK(back.temperature_C == t);
  }
}
