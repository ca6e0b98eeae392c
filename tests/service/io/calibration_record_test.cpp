// What goes out on LCM (calibration_t) never carries NaN or Inf (a receiver cannot tell it from
// data): a failed refit's unknown residual and non-finite estimates are replaced by the documented
// conventions (service/io/calibration_record.hpp), and a finite result goes out unchanged.
// calibration_t <-> history record. The filter-state blob: one versioned format, round trip on
// SQLite and PostgreSQL, unknown versions refused.
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <random>
#include <variant>
#include <vector>

#include "pipeline/magnetometer_ukf.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/filter_state_store.hpp"
#include "tests/storage/storage_backends.hpp"

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
  const calibration_t raw = message_from_record(record_from_result("SAT-1", r));
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

TEST_CASE("a refit's bias variability goes through the history record: the same model error",
          "[calibration_record]") {
  // A filter re-anchored on a refit read back from the database (a restart, a takeover) keeps
  // the same model error as one re-anchored on the fresh refit.
  auto r = finite_result();
  r.method = "twostep";
  r.bias_variability_nT2 = Eigen::Vector3d(26.01, 4.5, 0.0);
  r.model_error(1) = -2.5;
  const storage::CalibrationRecord rec = record_from_result("SAT-1", r);
  const CalibrationResult back = result_from_record(rec);
  CHECK(back.bias_variability_nT2 == r.bias_variability_nT2);
  CHECK(back.model_error_covariance() == r.model_error_covariance());
  CHECK(back.model_error_covariance()(0, 0) == 26.01);
}

TEST_CASE("the field error goes through the history record and back", "[calibration_record]") {
  auto r = finite_result();
  r.method = "twostep";
  r.field_error.direction_deg = {100, 0.075, 0.31};
  r.field_error.magnitude_nT = {120, 4.25, 17.5};
  const CalibrationResult back = result_from_record(record_from_result("SAT-1", r));
  CHECK(back.field_error.direction_deg.rms == 0.075);
  CHECK(back.field_error.direction_deg.worst == 0.31);
  CHECK(back.field_error.magnitude_nT.rms == 4.25);
  CHECK(back.field_error.magnitude_nT.worst == 17.5);
  CHECK(back.field_error.computed());
  // Not computed (a filter snapshot): stays so.
  CHECK_FALSE(
      result_from_record(record_from_result("SAT-1", finite_result())).field_error.computed());
}

TEST_CASE("the bias temperature model and the bias rate go through the history record and back",
          "[calibration_record]") {
  auto r = finite_result();
  r.has_temperature_model = true;
  r.reference_temperature_C = 17.25;
  r.temperature_coefficient_nT_per_C = Eigen::Vector3d(1.5, -0.75, 0.1);
  Eigen::Matrix3d cov;
  cov << 4e-4, 1e-5, -2e-6, 1e-5, 9e-4, 3e-6, -2e-6, 3e-6, 2.5e-5;
  r.temperature_coefficient_covariance = cov;
  // (A refit has one or the other; the record keeps each on its own.)
  r.has_bias_rate = true;
  r.bias_rate_nT_per_h = Eigen::Vector3d(-2.75, 0.5, 1.25);
  r.bias_rate_covariance = 100.0 * cov;
  const storage::CalibrationRecord rec = record_from_result("SAT-1", r);
  CHECK(rec.has_temperature_model == 1);
  CHECK(rec.has_bias_rate == 1);
  const CalibrationResult back = result_from_record(rec);
  CHECK(back.has_temperature_model);
  CHECK(back.reference_temperature_C == r.reference_temperature_C);
  CHECK(back.temperature_coefficient_nT_per_C == r.temperature_coefficient_nT_per_C);
  CHECK(back.temperature_coefficient_covariance == cov);
  CHECK(back.has_bias_rate);
  CHECK(back.bias_rate_nT_per_h == r.bias_rate_nT_per_h);
  CHECK(back.bias_rate_covariance == r.bias_rate_covariance);
  CHECK(back.parameters.bias_nT == r.parameters.bias_nT);

  // calibration_t has no temperature fields (a fixed contract): its bias is the bias at T0.
  const calibration_t msg = message_from_result("SAT-1", r);
  for (int i = 0; i < 3; ++i) CHECK(msg.bias_nT[i] == r.parameters.bias_nT(i));

  SECTION("a refit without the model says it has none; a filter says nothing") {
    auto plain = finite_result();
    CHECK(record_from_result("SAT-1", plain).has_temperature_model == 0);
    CHECK(record_from_result("SAT-1", plain).has_bias_rate == 0);
    plain.method = "ukf";
    CHECK(record_from_result("SAT-1", plain).has_temperature_model == -1);
    CHECK(record_from_result("SAT-1", plain).has_bias_rate == -1);
    CHECK_FALSE(result_from_record(record_from_result("SAT-1", plain)).has_temperature_model);
    CHECK_FALSE(result_from_record(record_from_result("SAT-1", plain)).has_bias_rate);
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

TEST_CASE("calibration_t converts to and from a history record without loss") {
  storage::CalibrationRecord r;
  r.sat_id = "SAT9";
  r.method = "twostep";
  r.utime = 1704067200000000;
  r.window_start_utime = r.utime - 43200000000;
  r.window_end_utime = r.utime;
  r.n_samples = 4321;
  r.bias_nT = {101.0, -49.5, 24.0};
  r.D = {1e-3, -2e-3, 3e-3, 1e-4, -1e-4, 2e-4};
  for (int i = 0; i < 45; ++i) r.cov[static_cast<size_t>(i)] = 1e-6 * (i + 1);
  r.cov[storage::cov_index(0, 0)] = 5.0;  // bias variances, nT^2
  r.has_alignment = true;
  r.R_sensor_from_body = {0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0};
  r.residual_rms_nT = 3.11;
  r.status = 0;
  r.verdict = "accepted";
  const calibration_t msg = message_from_record(r);
  CHECK(msg.sat_id == "SAT9");
  CHECK(msg.status == 0);
  const storage::CalibrationRecord back = record_from_message(msg);
  CHECK(back.bias_nT == r.bias_nT);
  CHECK(back.D == r.D);
  CHECK(back.cov == r.cov);
  CHECK(back.R_sensor_from_body == r.R_sensor_from_body);
  CHECK(back.has_alignment == r.has_alignment);
  CHECK(back.window_start_utime == r.window_start_utime);
  CHECK(back.n_samples == r.n_samples);
  CHECK(back.verdict == "accepted");
  CHECK(back.bias_sigma_nT[0] == std::sqrt(r.cov[0]));
  auto rejected = msg;
  rejected.status = 4;
  CHECK(record_from_message(rejected).verdict == "rejected");
}

namespace {

// A filter state with every field set: a UKF run over noisy samples for 5 h (two bias-motion
// blocks closed), re-anchored early (the model error), its state as the daemon saves it.
FilterState run_filter_state() {
  std::mt19937_64 rng(17);
  std::normal_distribution<double> n(0.0, 1.0);
  MagnetometerUkf ukf;
  const Eigen::Vector3d b(1000.0, 800.0, 900.0);
  Vector9d model_error;
  model_error << 1.2, -4.2, 0.1, 1e-5, 2e-5, -3e-5, 4e-6, -5e-5, 6e-6;
  for (int k = 0; k < 1800; ++k) {
    const Eigen::Vector3d h = 40000.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    ukf.update(h + b + 3.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)), 40000.0,
               1704067200000000 + k * 10'000'000LL);
    if (k == 150) {
      ukf.reanchor(ukf.x(), ukf.P(), model_error * model_error.transpose());
      ukf.seed_bias_rate(Eigen::Vector3d(0.5, -1.5, 0.25),
                         Eigen::Vector3d(0.01, 0.04, 0.0025).asDiagonal().toDenseMatrix());
    }
  }
  REQUIRE(ukf.initialized());
  REQUIRE(ukf.state().bias_motion_n == 2);
  REQUIRE(ukf.state().bias_motion_sum_J_nT.norm() > 0.0);
  return ukf.state();
}

template <typename Backend>
void check_filter_state_round_trip() {
  Backend backend;
  const auto db = backend.open();
  if (!db) return;
  const FilterState state = run_filter_state();
  db->make_filter_state_store()->save(stored_filter_state("SAT-1", "ukf", state));
  // Read back on another connection: what a restarted daemon (or another one) finds.
  const auto stored = backend.open_again()->make_filter_state_store()->load("SAT-1", "ukf");
  REQUIRE(stored.has_value());
  FilterState back;
  REQUIRE(filter_state_from_stored(*stored, back) == "");
  CHECK(back == state);  // bit for bit
}

}  // namespace

TEST_CASE("the filter state round-trips bit for bit through SQLite", "[filter_state]") {
  check_filter_state_round_trip<test::SqliteBackend>();
}

TEST_CASE("the filter state round-trips bit for bit through PostgreSQL", "[filter_state]") {
  check_filter_state_round_trip<test::PostgresBackend>();
}

TEST_CASE("a filter state blob of an unknown version or format is refused, naming it",
          "[filter_state]") {
  storage::FilterState stored = stored_filter_state("SAT-1", "ukf", run_filter_state());
  FilterState back;
  REQUIRE(stored.counters.size() > 4);
  CHECK(stored.counters[0] == '5');  // "MCF" + version, little-endian: the version comes first
  auto newer = stored;
  newer.counters[0] = '7';
  CHECK(filter_state_from_stored(newer, back) ==
        "filter state blob version 7: this magcal reads 1 to 5");
  auto foreign = stored;
  foreign.counters[3] = 'X';
  CHECK(filter_state_from_stored(foreign, back).starts_with("not a magcal filter state"));
  auto truncated = stored;
  truncated.counters.resize(truncated.counters.size() - 1);
  CHECK(filter_state_from_stored(truncated, back).find("inside its fields") != std::string::npos);
  auto longer = stored;
  longer.counters.push_back(0);
  CHECK(filter_state_from_stored(longer, back).find("1 bytes after its fields") !=
        std::string::npos);
  // Version 4 is version 5 without the anchor refit's bias rate (2 x 3 doubles at the end): it
  // restores with those zero, everything else as written.
  FilterState from_v5;
  REQUIRE(filter_state_from_stored(stored, from_v5) == "");
  auto v4 = stored;
  v4.counters[0] = '4';
  v4.counters.resize(v4.counters.size() - 6 * sizeof(double));
  FilterState from_v4;
  REQUIRE(filter_state_from_stored(v4, from_v4) == "");
  FilterState expected_v4 = from_v5;
  expected_v4.refit_bias_rate_nT_per_h.setZero();
  expected_v4.refit_bias_random_walk_nT2_per_hour.setZero();
  CHECK(from_v4 == expected_v4);
  // Version 3 is version 4 without the blocks' sensitivity to D (3 x 6 x 2 + 3 x 2 doubles at
  // the end): it restores with those sums zero, everything else as written.
  auto v3 = v4;
  v3.counters[0] = '3';
  v3.counters.resize(v3.counters.size() - (36 + 6) * sizeof(double));
  FilterState from_v3;
  REQUIRE(filter_state_from_stored(v3, from_v3) == "");
  FilterState expected = from_v4;
  expected.bias_motion_sum_J_nT.setZero();
  expected.bias_motion_sum_tJ_nT_h.setZero();
  expected.bias_motion_sum_Jd_nT.setZero();
  expected.bias_motion_sum_tJd_nT_h.setZero();
  CHECK(from_v3 == expected);
  auto v3_longer = v3;
  v3_longer.counters.push_back(0);
  CHECK(filter_state_from_stored(v3_longer, back).find("1 bytes after its fields") !=
        std::string::npos);
  // Version 2 had the same fields as 3 (the later ones optional): a version 2 blob still restores.
  auto v2 = v3;
  v2.counters[0] = '2';
  REQUIRE(filter_state_from_stored(v2, back) == "");
  CHECK(back == from_v3);
}

TEST_CASE("a filter state saved while collecting for the start keeps the start's lag-1 products",
          "[filter_state]") {
  std::mt19937_64 rng(5);
  std::normal_distribution<double> n(0.0, 1.0);
  MagnetometerUkf ukf;
  for (int k = 0; k < 40; ++k) {  // below the start's min_samples
    const Eigen::Vector3d h = 40000.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    ukf.update(h + Eigen::Vector3d(1000.0, 800.0, 900.0), 40000.0,
               1704067200000000 + k * 10'000'000LL);
  }
  REQUIRE_FALSE(ukf.initialized());
  const auto* lag1 = std::get_if<ScalarLag1Moments>(&ukf.state().lag1_or_block);
  REQUIRE(lag1 != nullptr);
  REQUIRE(lag1->m.norm() > 0.0);
  FilterState back;
  REQUIRE(filter_state_from_stored(stored_filter_state("SAT-1", "ukf", ukf.state()), back) == "");
  CHECK(back == ukf.state());
}

TEST_CASE("a started filter's blob from before the packed state (lag-1 products kept) restores",
          "[filter_state]") {
  const FilterState state = run_filter_state();
  const storage::FilterState stored = stored_filter_state("SAT-1", "ukf", state);
  // The lag-1 section (66 + 11 doubles after the magic, the 70 bytes of version 1's fields, the
  // 34 of the noise estimate and the 66 moments) is zero in a started filter's blob now; older
  // releases wrote the products the start had used.
  constexpr size_t kLag1Offset = 4 + 70 + 34 + 66 * sizeof(double);
  constexpr size_t kLag1Bytes = (66 + 11) * sizeof(double);
  REQUIRE(stored.counters.size() > kLag1Offset + kLag1Bytes);
  for (size_t i = kLag1Offset; i < kLag1Offset + kLag1Bytes; ++i) CHECK(stored.counters[i] == 0);
  auto older = stored;
  for (size_t i = 0; i < kLag1Bytes; ++i)
    older.counters[kLag1Offset + i] = stored.counters[kLag1Offset - kLag1Bytes + i];
  FilterState back;
  REQUIRE(filter_state_from_stored(older, back) == "");
  CHECK(back == state);
}

TEST_CASE("a stored factor S with entries above the diagonal is refused", "[filter_state]") {
  storage::FilterState stored = stored_filter_state("SAT-1", "ukf", run_filter_state());
  stored.P[1] = 1.0;  // row 0, column 1
  FilterState back;
  CHECK(filter_state_from_stored(stored, back) == "filter state S is not lower triangular");
}
