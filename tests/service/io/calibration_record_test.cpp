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
