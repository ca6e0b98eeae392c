// calibrations table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): exact
// round trip of every field (also the optional and absent ones), filters, limit-newest in either
// order, refit queries, rows of older schemas.
#include "storage/calibration_history.hpp"

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <string_view>

#include "storage/migrations.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::query_int;
using magcal::test::SqliteBackend;

namespace {

constexpr int64_t kHour = 3'600'000'000LL;
constexpr int64_t kT0 = 1'767'225'600'000'000LL;  // 2026-01-01T00:00:00Z

CalibrationRecord make_record(const std::string& sat, const std::string& method, int64_t utime,
                              int k) {
  CalibrationRecord r;
  r.sat_id = sat;
  r.method = method;
  r.utime = utime;
  r.window_start_utime = utime - 12 * kHour;
  r.window_end_utime = utime;
  r.n_samples = 4320 + k;
  r.bias_nT = {100.0 + k, -50.0 + 0.5 * k, 25.0 - k};
  r.D = {1e-3 * k, -2e-3, 3e-3, 1e-4, -1e-4, 2e-4};
  for (int i = 0; i < 45; ++i) r.cov[i] = 1e-6 * (i + 1) + 1e-9 * k;
  r.cov[cov_index(0, 0)] = 4.0 + k;  // bias variances, nT^2
  r.cov[cov_index(1, 1)] = 9.0;
  r.cov[cov_index(2, 2)] = 0.25;
  r.has_alignment = k % 2 == 1;
  r.R_sensor_from_body = {0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0};
  r.residual_rms_nT = 3.1 + 0.01 * k;
  r.status = k % 5 == 4 ? 4 : 0;
  r.verdict = r.status == 0 ? "accepted" : "rejected";
  if (r.status) r.rejection_reasons = {"residual_rms 12.0 nT > 9.0 nT", "quote \" and \\ kept"};
  r.iterations = 7;
  r.software_version = "test-1.0";
  r.created_utime = utime + 1000;
  return r;
}

// The same value bit for bit (-0.0 is not 0.0), or both NaN (unknown: NULL).
bool same(double a, double b) {
  if (std::isnan(a) || std::isnan(b)) return std::isnan(a) && std::isnan(b);
  return a == b && std::signbit(a) == std::signbit(b);
}
template <size_t N>
bool same(const std::array<double, N>& a, const std::array<double, N>& b) {
  for (size_t i = 0; i < N; ++i) {
    if (!same(a[i], b[i])) return false;
  }
  return true;
}

// `got` is `want` read back: every field (R only with an alignment: without one it is not
// stored), bias_sigma_nT derived from cov.
void check_round_trip(const CalibrationRecord& got, const CalibrationRecord& want) {
  CHECK(got.sat_id == want.sat_id);
  CHECK(got.method == want.method);
  CHECK(got.utime == want.utime);
  CHECK(got.window_start_utime == want.window_start_utime);
  CHECK(got.window_end_utime == want.window_end_utime);
  CHECK(got.n_samples == want.n_samples);
  CHECK(same(got.bias_nT, want.bias_nT));
  CHECK(same(got.D, want.D));
  CHECK(same(got.cov, want.cov));
  for (int i = 0; i < 3; ++i) {
    CHECK(got.bias_sigma_nT[i] == std::sqrt(want.cov[cov_index(i, i)]));
  }
  CHECK(got.has_alignment == want.has_alignment);
  if (want.has_alignment) CHECK(same(got.R_sensor_from_body, want.R_sensor_from_body));
  CHECK(got.alignment_covariance_rad2.has_value() == want.alignment_covariance_rad2.has_value());
  if (got.alignment_covariance_rad2 && want.alignment_covariance_rad2) {
    CHECK(same(*got.alignment_covariance_rad2, *want.alignment_covariance_rad2));
  }
  CHECK(same(got.residual_rms_nT, want.residual_rms_nT));
  CHECK(got.status == want.status);
  CHECK(got.verdict == want.verdict);
  CHECK(got.rejection_reasons == want.rejection_reasons);
  CHECK(got.iterations == want.iterations);
  CHECK(same(got.noise_scale, want.noise_scale));
  CHECK(same(got.residual_autocorrelation, want.residual_autocorrelation));
  CHECK(got.covariance_lag_window == want.covariance_lag_window);
  CHECK(same(got.residual_rms_all_nT, want.residual_rms_all_nT));
  CHECK(got.has_nonlinearity == want.has_nonlinearity);
  CHECK(same(got.k3, want.k3));
  CHECK(same(got.nis_mean, want.nis_mean));
  CHECK(same(got.measurement_noise_nT, want.measurement_noise_nT));
  CHECK(same(got.model_error, want.model_error));
  CHECK(got.has_temperature_model == want.has_temperature_model);
  CHECK(same(got.reference_temperature_C, want.reference_temperature_C));
  CHECK(same(got.temperature_coefficient_nT_per_C, want.temperature_coefficient_nT_per_C));
  CHECK(same(got.temperature_coefficient_cov, want.temperature_coefficient_cov));
  CHECK(got.temperature_model_refit_id == want.temperature_model_refit_id);
  CHECK(got.has_bias_rate == want.has_bias_rate);
  CHECK(same(got.bias_rate_nT_per_h, want.bias_rate_nT_per_h));
  CHECK(same(got.bias_rate_cov, want.bias_rate_cov));
  CHECK(same(got.bias_variability_nT2, want.bias_variability_nT2));
  CHECK(same(got.field_direction_error_rms_deg, want.field_direction_error_rms_deg));
  CHECK(same(got.field_direction_error_worst_deg, want.field_direction_error_worst_deg));
  CHECK(same(got.field_magnitude_error_rms_nT, want.field_magnitude_error_rms_nT));
  CHECK(same(got.field_magnitude_error_worst_nT, want.field_magnitude_error_worst_nT));
  CHECK(got.software_version == want.software_version);
  CHECK(got.created_utime == want.created_utime);
}

}  // namespace

TEST_CASE("cov_index addresses the row-major upper triangle") {
  CHECK(cov_index(0, 0) == 0);
  CHECK(cov_index(0, 8) == 8);
  CHECK(cov_index(1, 1) == 9);
  CHECK(cov_index(2, 2) == 17);
  CHECK(cov_index(8, 8) == 44);
  CHECK(cov_index(3, 1) == cov_index(1, 3));
  // Every (i <= j) pair maps to a distinct index 0..44 in row-major order.
  int expected = 0;
  for (int i = 0; i < 9; ++i) {
    for (int j = i; j < 9; ++j) CHECK(cov_index(i, j) == expected++);
  }
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a calibration record round-trips exactly, bias sigma comes from cov",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  for (int k : {3, 4}) {  // with alignment + accepted, without alignment + rejected
    const CalibrationRecord r = make_record("SAT1", "twostep", kT0 + k * kHour, k);
    const int64_t id = history.append(r);
    CHECK(id > 0);
    HistoryQuery q;
    q.sat_id = "SAT1";
    q.since_utime = r.utime;
    q.until_utime = r.utime;
    const auto rows = history.query(q);
    REQUIRE(rows.size() == 1);
    CHECK(rows[0].id == id);
    check_round_trip(rows[0], r);
  }
}

TEMPLATE_TEST_CASE_METHOD(BackendTest, "every field of a record round-trips bit for bit at once",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history = this->db->make_calibration_history();
  const int64_t refit_id = history->append(make_record("SAT1", "twostep", kT0, 1));
  CalibrationRecord r = make_record("SAT1", "ukf", kT0 + kHour, 4);  // rejected
  r.has_alignment = true;
  r.R_sensor_from_body = {0.1 + 0.2, 1.0, 0.5, -1.0, 1e-300, 0.0, 0.0, 2.0 / 3.0, 1.0};
  r.alignment_covariance_rad2 = std::array<double, 6>{1e-8 / 3.0, 2.5e-9, 7e-10, -1e-10, 0, 1};
  r.rejection_reasons = {"tab\there, newline\nthere", "control \x01 and UTF-8 \u00b0C", ""};
  r.noise_scale = 1.0 / 3.0;
  r.residual_autocorrelation = -0.031;
  r.covariance_lag_window = 0;
  r.residual_rms_all_nT = 3.62;
  r.has_nonlinearity = 1;
  r.k3 = {1e-9, -2e-9, 3e-10};
  r.nis_mean = 1.04;
  r.measurement_noise_nT = 3.3;
  r.model_error = {0.1 + 0.2, -3.5, 1e-300, 0, 2e-4, -1e-5, 0, 3e-6, -0.0};
  r.has_temperature_model = 1;
  r.reference_temperature_C = -12.5;
  r.temperature_coefficient_nT_per_C = {1.25, -0.5, 1e-3 / 3.0};
  r.temperature_coefficient_cov = {4e-4, 1e-5, -2e-6, 9e-4, 3e-6, 2.5e-5};
  r.temperature_model_refit_id = refit_id;
  r.has_bias_rate = 1;
  r.bias_rate_nT_per_h = {-2.75, 0.125, 1e-3 / 7.0};
  r.bias_rate_cov = {0.0289, 0.0025, 9e-4, -1e-4, 2e-5, 3e-6};
  r.bias_variability_nT2 = {26.01, 0.1 + 0.2, 1e-300};
  r.field_direction_error_rms_deg = 0.1 + 0.2;
  r.field_direction_error_worst_deg = 1.0 / 7.0;
  r.field_magnitude_error_rms_nT = 3.0e-300;
  r.field_magnitude_error_worst_nT = 12.5;
  const int64_t id = history->append(r);
  const auto got = history->get(id);
  REQUIRE(got);
  CHECK(got->id == id);
  check_round_trip(*got, r);

  // Absent fields: an empty software version and creation time take this build's and now.
  CalibrationRecord bare;
  bare.sat_id = "SAT2";
  bare.method = "ekf";
  const auto back = history->get(history->append(bare));
  REQUIRE(back);
  CHECK_FALSE(back->software_version.empty());
  CHECK(back->created_utime > kT0);
  bare.software_version = back->software_version;
  bare.created_utime = back->created_utime;
  check_round_trip(*back, bare);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "history query: sat, method, inclusive range, limit newest, either order",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  // 48 h of hourly ukf snapshots and daily twostep refits on two spacecraft.
  for (int k = 0; k < 48; ++k) {
    history.append(make_record("SAT1", "ukf", kT0 + k * kHour, k));
    history.append(make_record("SAT2", "ukf", kT0 + k * kHour, k));
    if (k % 24 == 2) history.append(make_record("SAT1", "twostep", kT0 + k * kHour, k));
  }
  HistoryQuery q;
  q.sat_id = "SAT1";
  CHECK(history.query(q).size() == 50);
  q.method = "ukf";
  auto rows = history.query(q);
  REQUIRE(rows.size() == 48);
  CHECK(rows.front().utime == kT0);  // ascending by default
  CHECK(rows.back().utime == kT0 + 47 * kHour);

  q.since_utime = kT0 + 10 * kHour;
  q.until_utime = kT0 + 20 * kHour;
  rows = history.query(q);
  REQUIRE(rows.size() == 11);  // both ends inclusive
  CHECK(rows.front().utime == kT0 + 10 * kHour);
  CHECK(rows.back().utime == kT0 + 20 * kHour);

  q.limit = 3;  // the 3 newest of the range, printed oldest first
  rows = history.query(q);
  REQUIRE(rows.size() == 3);
  CHECK(rows[0].utime == kT0 + 18 * kHour);
  CHECK(rows[2].utime == kT0 + 20 * kHour);
  q.descending = true;
  rows = history.query(q);
  REQUIRE(rows.size() == 3);
  CHECK(rows[0].utime == kT0 + 20 * kHour);
  CHECK(rows[2].utime == kT0 + 18 * kHour);

  q = HistoryQuery{};
  q.sat_id = "SAT1";
  q.method = "twostep";
  CHECK(history.query(q).size() == 2);
  q.sat_id = "UNKNOWN";
  CHECK(history.query(q).empty());
  CHECK(history.spacecraft() == std::vector<std::string>{"SAT1", "SAT2"});
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "latest, latest refit, previous refit, latest accepted refit",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  CHECK_FALSE(history.latest_refit("SAT1").has_value());
  CHECK_FALSE(history.previous_refit("SAT1").has_value());
  history.append(make_record("SAT1", "centered", kT0 + 1 * kHour, 1));  // accepted
  CHECK(history.latest_refit("SAT1")->utime == kT0 + 1 * kHour);
  CHECK_FALSE(history.previous_refit("SAT1").has_value());
  history.append(make_record("SAT1", "twostep", kT0 + 2 * kHour, 2));  // accepted
  history.append(make_record("SAT1", "ukf", kT0 + 5 * kHour, 5));
  history.append(make_record("SAT1", "twostep", kT0 + 4 * kHour, 4));  // rejected (k % 5 == 4)
  CHECK(history.latest("SAT1", "ukf")->utime == kT0 + 5 * kHour);
  CHECK_FALSE(history.latest("SAT1", "ekf").has_value());
  const auto latest = history.latest_refit("SAT1");
  REQUIRE(latest.has_value());
  CHECK(latest->utime == kT0 + 4 * kHour);
  CHECK(latest->verdict == "rejected");
  CHECK(history.previous_refit("SAT1")->utime == kT0 + 2 * kHour);
  CHECK(history.latest_accepted_refit("SAT1")->utime == kT0 + 2 * kHour);
  // The change-gate reference: only refits spanning a full window with enough samples.
  CalibrationRecord short_refit = make_record("SAT1", "twostep", kT0 + 6 * kHour, 6);
  short_refit.window_start_utime = short_refit.utime - 8 * kHour;  // an 8 h first window
  history.append(short_refit);
  CHECK(history.latest_accepted_refit("SAT1")->utime == kT0 + 6 * kHour);
  CHECK(history.latest_accepted_refit("SAT1", 11 * kHour, 1000)->utime == kT0 + 2 * kHour);
  CHECK_FALSE(history.latest_accepted_refit("SAT1", 11 * kHour, 5000).has_value());
  // A refit run again at the newest one's data time (two manual refits of one window): the
  // previous refit is still the one of the window before, not its twin (a zero "change").
  history.append(make_record("SAT1", "centered", kT0 + 6 * kHour, 7));
  CHECK(history.latest_refit("SAT1")->method == "centered");
  CHECK(history.latest_refit("SAT1")->utime == kT0 + 6 * kHour);
  CHECK(history.previous_refit("SAT1")->utime == kT0 + 4 * kHour);
  CHECK(is_refit_method("twostep"));
  CHECK(is_refit_method("centered"));
  CHECK_FALSE(is_refit_method("ukf"));
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "uncertainty evidence (schema 3) round-trips, unknown values stay NULL",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  CalibrationRecord known = make_record("SAT1", "twostep", kT0, 1);
  known.noise_scale = 1.21;
  known.residual_autocorrelation = 0.031;
  known.covariance_lag_window = 12;
  known.residual_rms_all_nT = 3.62;
  known.has_nonlinearity = 1;
  known.k3 = {1e-9, -2e-9, 3e-10};
  CalibrationRecord filter = make_record("SAT1", "ukf", kT0 + kHour, 2);
  filter.nis_mean = 1.04;
  filter.measurement_noise_nT = 3.3;
  history.append(known);
  history.append(filter);
  const auto a = history.latest("SAT1", "twostep");
  REQUIRE(a);
  CHECK(a->noise_scale == known.noise_scale);
  CHECK(a->residual_autocorrelation == known.residual_autocorrelation);
  CHECK(a->covariance_lag_window == 12);
  CHECK(a->residual_rms_all_nT == known.residual_rms_all_nT);
  CHECK(a->has_nonlinearity == 1);
  CHECK(a->k3 == known.k3);
  CHECK(std::isnan(a->nis_mean));
  const auto b = history.latest("SAT1", "ukf");
  REQUIRE(b);
  CHECK(b->nis_mean == 1.04);
  CHECK(b->measurement_noise_nT == 3.3);
  CHECK(std::isnan(b->noise_scale));
  CHECK(b->covariance_lag_window == -1);
  CHECK(b->has_nonlinearity == -1);
  CHECK(std::isnan(b->k3[0]));
}

TEMPLATE_TEST_CASE_METHOD(
    BackendTest, "a refit's model error (schema 4) round-trips, zero stays NULL, rows read by id",
    "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  CalibrationRecord extended = make_record("SAT1", "twostep", kT0, 1);
  extended.model_error = {0.1 + 0.2, -3.5, 1e-300, 0, 2e-4, -1e-5, 0, 3e-6, -0.0};
  const int64_t a = history.append(extended);
  const int64_t b = history.append(make_record("SAT1", "twostep", kT0 + kHour, 2));
  const auto back = history.get(a);
  REQUIRE(back);
  CHECK(back->id == a);
  CHECK(back->model_error == extended.model_error);
  CHECK(history.get(b)->model_error == std::array<double, 9>{});
  CHECK(query_int(*this->db, "SELECT count(*) FROM calibrations WHERE model_error IS NULL") == 1);
  CHECK_FALSE(history.get(b + 1).has_value());
  this->db->exec("UPDATE calibrations SET model_error = " + TestType::zero_blob_sql(8));
  CHECK_THROWS_AS(history.get(a), StorageError);
}

TEMPLATE_TEST_CASE_METHOD(
    BackendTest,
    "the alignment covariance round-trips exactly, NULL without an alignment or when unknown",
    "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  CalibrationRecord aligned = make_record("SAT1", "twostep", kT0, 1);
  REQUIRE(aligned.has_alignment);
  aligned.alignment_covariance_rad2 =
      std::array<double, 6>{1e-8 / 3.0, 2.5e-9, 7e-10, -1e-10, 3e-300, -0.0};
  CalibrationRecord unknown = make_record("SAT1", "twostep", kT0 + kHour, 3);
  REQUIRE(unknown.has_alignment);
  CalibrationRecord unaligned = make_record("SAT1", "twostep", kT0 + 2 * kHour, 2);
  REQUIRE_FALSE(unaligned.has_alignment);
  unaligned.alignment_covariance_rad2 = aligned.alignment_covariance_rad2;  // not stored
  const int64_t a = history.append(aligned);
  const int64_t u = history.append(unknown);
  const int64_t n = history.append(unaligned);
  REQUIRE(history.get(a)->alignment_covariance_rad2 == aligned.alignment_covariance_rad2);
  CHECK_FALSE(history.get(u)->alignment_covariance_rad2.has_value());
  CHECK_FALSE(history.get(n)->alignment_covariance_rad2.has_value());
  CHECK(query_int(*this->db,
                  "SELECT count(*) FROM calibrations WHERE alignment_covariance_rad2 IS NULL") ==
        2);
  this->db->exec("UPDATE calibrations SET alignment_covariance_rad2 = " +
                 TestType::zero_blob_sql(40) + " WHERE id = " + std::to_string(a));
  CHECK_THROWS_AS(history.get(a), StorageError);
}

TEMPLATE_TEST_CASE("rows stored before the alignment covariance was kept read it as unknown",
                   "[calibrations]", SqliteBackend, PostgresBackend) {
  TestType backend;
  {
    const auto db = backend.open(magcal::test::before_migration("_alignment_covariance"));
    if (!db) return;
    // A row as the previous schema stored it: an alignment without its covariance.
    db->exec(
        "INSERT INTO calibrations (sat_id, method, utime, window_start_utime, window_end_utime, "
        "n_samples, bias_x_nT, bias_y_nT, bias_z_nT, D11, D22, D33, D12, D13, D23, cov, "
        "has_alignment, R11, R12, R13, R21, R22, R23, R31, R32, R33, residual_rms_nT, status, "
        "verdict, software_version, created_utime) VALUES ('SAT1', 'twostep', 42, 0, 0, 0, 0, 0, "
        "0, 0, 0, 0, 0, 0, 0, " +
        TestType::zero_blob_sql(360) +
        ", 1, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 'accepted', 'old', 1)");
  }
  const auto db = backend.open_again();  // migrates to the newest schema
  const auto old_row = db->make_calibration_history()->latest("SAT1", "twostep");
  REQUIRE(old_row);
  CHECK(old_row->has_alignment);
  CHECK_FALSE(old_row->alignment_covariance_rad2.has_value());
  CHECK(old_row->cov == std::array<double, 45>{});
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "the bias temperature model round-trips, not modelled stays NULL",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  CalibrationRecord refit = make_record("SAT1", "twostep", kT0, 1);
  refit.has_temperature_model = 1;
  refit.reference_temperature_C = 0.1 + 0.2;  // not exact in binary: must come back bit-exact
  refit.temperature_coefficient_nT_per_C = {1.25, -0.5, 1e-3 / 3.0};
  refit.temperature_coefficient_cov = {4e-4, 1e-5, -2e-6, 9e-4, 3e-6, 2.5e-5};
  const int64_t refit_id = history.append(refit);
  CalibrationRecord snapshot = make_record("SAT1", "ukf", kT0 + kHour, 2);
  snapshot.has_temperature_model = 1;
  snapshot.reference_temperature_C = refit.reference_temperature_C;
  snapshot.temperature_coefficient_nT_per_C = refit.temperature_coefficient_nT_per_C;
  snapshot.temperature_coefficient_cov = refit.temperature_coefficient_cov;
  snapshot.temperature_model_refit_id = refit_id;
  const int64_t snapshot_id = history.append(snapshot);
  CalibrationRecord tested = make_record("SAT1", "twostep", kT0 + 2 * kHour, 3);
  tested.has_temperature_model = 0;
  tested.reference_temperature_C = 20.0;  // not modelled: not stored, whatever it holds
  const int64_t tested_id = history.append(tested);
  const int64_t plain_id = history.append(make_record("SAT1", "ukf", kT0 + 3 * kHour, 5));

  const auto a = history.get(refit_id);
  REQUIRE(a);
  CHECK(a->has_temperature_model == 1);
  CHECK(a->reference_temperature_C == refit.reference_temperature_C);
  CHECK(a->temperature_coefficient_nT_per_C == refit.temperature_coefficient_nT_per_C);
  CHECK(a->temperature_coefficient_cov == refit.temperature_coefficient_cov);
  CHECK(a->temperature_model_refit_id == 0);  // a refit's model is its own
  const auto b = history.get(snapshot_id);
  REQUIRE(b);
  CHECK(b->has_temperature_model == 1);
  CHECK(b->temperature_coefficient_nT_per_C == refit.temperature_coefficient_nT_per_C);
  CHECK(b->temperature_model_refit_id == refit_id);
  const auto c = history.get(tested_id);
  REQUIRE(c);
  CHECK(c->has_temperature_model == 0);
  CHECK(std::isnan(c->reference_temperature_C));
  CHECK(std::isnan(c->temperature_coefficient_nT_per_C[0]));
  CHECK(history.get(plain_id)->has_temperature_model == -1);
  CHECK(query_int(*this->db,
                  "SELECT count(*) FROM calibrations WHERE reference_temperature_C IS NULL AND "
                  "temperature_coefficient_x_nT_per_C IS NULL AND temperature_coefficient_cov IS "
                  "NULL AND temperature_model_refit_id IS NULL") == 2);
  this->db->exec("UPDATE calibrations SET temperature_coefficient_cov = " +
                 TestType::zero_blob_sql(8) + " WHERE id = " + std::to_string(refit_id));
  CHECK_THROWS_AS(history.get(refit_id), StorageError);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest, "invalid records are refused", "[calibrations]",
                          SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history_store = this->db->make_calibration_history();
  CalibrationHistory& history = *history_store;
  auto r = make_record("SAT1", "ukf", kT0, 0);
  r.verdict = "maybe";
  CHECK_THROWS_AS(history.append(r), StorageError);
  r = make_record("SAT1", "ukf", kT0, 0);
  r.status = 5;
  CHECK_THROWS_AS(history.append(r), StorageError);
  r = make_record("SAT1", "ukf", kT0, 0);
  r.bias_nT[1] = std::nan("");  // NOT NULL column
  CHECK_THROWS_AS(history.append(r), StorageError);
  HistoryQuery q;
  q.sat_id = "SAT1";
  CHECK(history.query(q).empty());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "append_all stores a batch as appends one by one would, or none of it",
                          "[calibrations]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto history = this->db->make_calibration_history();
  // 100 = 64 + 32 + 4 rows (PostgreSQL's statement sizes), rejected ones with reasons among them.
  std::vector<CalibrationRecord> batch;
  for (int k = 0; k < 100; ++k) batch.push_back(make_record("SAT1", "ukf", kT0 + k * kHour, k));
  history->append_all(batch);
  history->append_all({});
  HistoryQuery q;
  q.sat_id = "SAT1";
  const auto rows = history->query(q);
  REQUIRE(rows.size() == batch.size());
  for (size_t i = 0; i < rows.size(); ++i) {
    check_round_trip(rows[i], batch[i]);
    if (i > 0) CHECK(rows[i].id > rows[i - 1].id);  // stored in order
  }

  // An invalid record: refused, and in a transaction the valid ones before it are not stored.
  std::vector<CalibrationRecord> bad{make_record("SAT2", "ukf", kT0, 0),
                                     make_record("SAT2", "ukf", kT0 + kHour, 1)};
  bad[1].bias_nT[1] = std::nan("");  // NOT NULL column
  {
    Transaction tx(*this->db);
    CHECK_THROWS_AS(history->append_all(bad), StorageError);
  }
  q.sat_id = "SAT2";
  CHECK(history->query(q).empty());
}

TEST_CASE("status names") {
  CHECK(std::string(status_name(4)) == "rejected");
  CHECK(std::string(status_name(1)) == "not_converged");
  CHECK(std::string(status_name(9)) == "unknown");
}
