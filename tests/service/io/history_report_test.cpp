// service/io/history_report: request validation and the points=N downsampling, checked against
// a direct computation written here (bucket edges from the stated width, per-field statistics).
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "service/io/history_report.hpp"
#include "service/io/status_report.hpp"

using namespace magcal;

namespace {

constexpr int64_t kT0 = 1'577'836'800'000'000LL;  // 2020-01-01T00:00:00Z
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Irregular times (gaps, a burst), two methods, some rejected, some unknown rms.
std::vector<storage::CalibrationRecord> rows() {
  std::vector<storage::CalibrationRecord> out;
  int64_t t = kT0;
  for (int k = 0; k < 200; ++k) {
    t += (k % 17 == 0) ? 3'600'000'000LL : 1'000'000LL * (1 + (k * 7919) % 97);
    storage::CalibrationRecord r;
    r.sat_id = "S";
    r.method = k % 10 == 3 ? "twostep" : "ukf";
    r.utime = t;
    r.n_samples = k;
    r.bias_nT = {std::sin(0.1 * k) * 50, 1000.0 - k, 0.25 * k * k};
    r.bias_sigma_nT = {1.0 + k % 3, 2.0, 3.0};
    for (int i = 3; i < 9; ++i) r.cov[storage::cov_index(i, i)] = 1e-6 * (i + k % 4);
    r.D = {0.01 * k, 0, 0, 0, 0, -0.01 * k};
    r.residual_rms_nT = k % 5 == 0 ? kNaN : 2.0 + 0.1 * k;
    if (k % 11 == 0) r.verdict = "rejected";
    out.push_back(r);
  }
  return out;
}

}  // namespace

TEST_CASE("downsample_history: buckets recomputed directly, counts sum to the rows") {
  const auto all = rows();
  storage::HistoryQuery q;
  q.sat_id = "S";
  for (const int points : {1, 3, 10, 64, 1000}) {
    INFO("points=" << points);
    const auto d = downsample_history(all, q, points);
    REQUIRE(d["rows"] == all.size());
    const int64_t start = d["start_utime"], end = d["end_utime"];
    REQUIRE(start == all.front().utime);
    REQUIRE(end == all.back().utime);
    const int64_t width = d["bucket_us"];
    REQUIRE(width * points >= end - start + 1);       // covers the range...
    REQUIRE(width * (points - 1) < end - start + 1);  // ...with no empty tail bucket
    size_t total = 0;
    for (const auto& series : d["series"]) {
      const std::string method = series["method"];
      for (const auto& b : series["buckets"]) {
        const int64_t lo = b["start_utime"], hi = b["end_utime"];
        REQUIRE((lo - start) % width == 0);
        REQUIRE(hi <= end);
        std::vector<const storage::CalibrationRecord*> in;
        for (const auto& r : all) {
          if (r.method == method && r.utime >= lo && r.utime <= hi) in.push_back(&r);
        }
        REQUIRE(b["count"] == in.size());
        REQUIRE(!in.empty());
        size_t accepted = 0;
        for (auto* r : in) accepted += r->verdict == "accepted";
        REQUIRE(b["accepted"] == accepted);
        REQUIRE(b["rejected"] == in.size() - accepted);
        // bias_z (exact values), residual rms (some unknown), D23 sigma (from the covariance).
        auto check = [&](const char* name, auto value_of) {
          double sum = 0, mn = INFINITY, mx = -INFINITY;
          size_t n = 0;
          for (auto* r : in) {
            const double v = value_of(*r);
            if (!std::isfinite(v)) continue;
            sum += v;
            mn = std::min(mn, v);
            mx = std::max(mx, v);
            ++n;
          }
          const auto& f = b[name];
          REQUIRE(f["n"] == n);
          if (n == 0) {
            REQUIRE(f["mean"].is_null());
            return;
          }
          REQUIRE(f["min"].get<double>() == mn);
          REQUIRE(f["max"].get<double>() == mx);
          REQUIRE(f["mean"].get<double>() == Approx(sum / static_cast<double>(n)).epsilon(1e-12));
          REQUIRE(mn <= f["mean"].get<double>());
          REQUIRE(f["mean"].get<double>() <= mx);
        };
        check("bias_z_nT", [](const auto& r) { return r.bias_nT[2]; });
        check("residual_rms_nT", [](const auto& r) { return r.residual_rms_nT; });
        check("D23_sigma",
              [](const auto& r) { return std::sqrt(r.cov[storage::cov_index(8, 8)]); });
        check("n_samples", [](const auto& r) { return static_cast<double>(r.n_samples); });
        total += in.size();
      }
    }
    REQUIRE(total == all.size());
  }
}

TEST_CASE("downsample_history: query range, descending order, no rows") {
  const auto all = rows();
  storage::HistoryQuery q;
  q.sat_id = "S";
  q.since_utime = kT0 - 86'400'000'000LL;
  q.until_utime = all.back().utime + 86'400'000'000LL;
  const auto d = downsample_history(all, q, 6);
  REQUIRE(d["start_utime"] == *q.since_utime);
  REQUIRE(d["end_utime"] == *q.until_utime);
  // The data sit in the middle of a 3-day span: the first bucket (day 1 minus...) is empty.
  for (const auto& s : d["series"]) {
    REQUIRE(s["buckets"].front()["start_utime"].get<int64_t>() > *q.since_utime);
  }
  q.descending = true;
  const auto desc = downsample_history(all, q, 50);
  for (const auto& s : desc["series"]) {
    int64_t previous = std::numeric_limits<int64_t>::max();
    for (const auto& b : s["buckets"]) {
      REQUIRE(b["start_utime"].get<int64_t>() < previous);
      previous = b["start_utime"];
    }
  }
  const auto none = downsample_history({}, q, 10);
  REQUIRE(none["rows"] == 0);
  REQUIRE(none["series"].empty());
}

TEST_CASE("parse_history_request names the bad parameter with the caller's prefix") {
  HistoryRequest r;
  r.sat = "S";
  std::string error;
  REQUIRE(parse_history_request(r, "--", &error));
  r.since = "2020-01-01";
  r.until = "2020-01-02T00:00:00.5Z";
  r.limit = 3;
  r.order = "desc";
  const auto q = parse_history_request(r, "--", &error);
  REQUIRE(q);
  REQUIRE(*q->since_utime == kT0);
  REQUIRE(*q->until_utime == kT0 + 86'400'000'000LL + 500'000);
  REQUIRE(q->descending);
  r.since = "soon";
  REQUIRE_FALSE(parse_history_request(r, "--", &error));
  REQUIRE(error == "--since 'soon' is not an ISO 8601 UTC time (e.g. 2026-01-01T12:00:00Z)");
  REQUIRE_FALSE(parse_history_request(r, "", &error));
  REQUIRE(error.rfind("since 'soon'", 0) == 0);
  r.since = "2020-01-03T00:00:00Z";  // after until: an empty range is a mistake
  REQUIRE_FALSE(parse_history_request(r, "--", &error));
  REQUIRE(error == "--since '2020-01-03T00:00:00Z' is after --until '2020-01-02T00:00:00.5Z'");
  r.since.clear();
  r.method = "lsq";
  REQUIRE_FALSE(parse_history_request(r, "", &error));
  REQUIRE(error == "unknown method 'lsq' (ukf, ekf, centered, twostep)");
}

namespace {

// The history CSV's lines split at every comma (its numeric and flag fields hold none); every
// line has the header's field count.
std::vector<std::vector<std::string>> csv_fields(const std::string& csv) {
  std::vector<std::vector<std::string>> table;
  for (size_t start = 0; start < csv.size();) {
    const size_t end = csv.find('\n', start);
    std::vector<std::string> fields;
    const std::string line = csv.substr(start, end - start);
    for (size_t f = 0;;) {
      const size_t comma = line.find(',', f);
      fields.push_back(line.substr(f, comma - f));
      if (comma == std::string::npos) break;
      f = comma + 1;
    }
    table.push_back(fields);
    start = end + 1;
  }
  for (const auto& row : table) REQUIRE(row.size() == table.at(0).size());
  return table;
}

size_t csv_column(const std::vector<std::vector<std::string>>& table, const std::string& name) {
  const auto it = std::find(table.at(0).begin(), table.at(0).end(), name);
  REQUIRE(it != table[0].end());
  return static_cast<size_t>(it - table[0].begin());
}

// The table's lines, without their newlines.
std::vector<std::string> text_lines(const std::string& text) {
  std::vector<std::string> lines;
  for (size_t from = 0, nl; (nl = text.find('\n', from)) != std::string::npos; from = nl + 1)
    lines.push_back(text.substr(from, nl - from));
  return lines;
}

}  // namespace

TEST_CASE("history JSON and CSV: the bias temperature model, and whose it is") {
  // A refit with the model, a UKF snapshot that applied it, a refit without it, an old row.
  storage::CalibrationRecord refit;
  refit.sat_id = "S";
  refit.method = "twostep";
  refit.utime = kT0;
  refit.id = 7;
  refit.has_temperature_model = 1;
  refit.reference_temperature_C = 12.5;
  refit.temperature_coefficient_nT_per_C = {1.5, -0.25, 0.0625};
  refit.temperature_coefficient_cov = {0.0625, 1e-3, 0.0, 0.25, 0.0, 1.0};  // exact roots
  storage::CalibrationRecord snapshot = refit;
  snapshot.method = "ukf";
  snapshot.utime = kT0 + 60'000'000;
  snapshot.id = 8;
  snapshot.temperature_model_refit_id = refit.id;
  storage::CalibrationRecord without;
  without.sat_id = "S";
  without.method = "twostep";
  without.utime = kT0 + 120'000'000;
  without.has_temperature_model = 0;
  storage::CalibrationRecord old_row = without;
  old_row.has_temperature_model = -1;
  const std::vector<storage::CalibrationRecord> all = {refit, snapshot, without, old_row};

  const auto json = nlohmann::json::parse(history_json_text(all));
  REQUIRE(json.size() == 4);
  for (const int k : {0, 1}) {
    const auto& o = json[static_cast<size_t>(k)];
    CHECK(o["reference_temperature_C"].get<double>() == 12.5);
    CHECK(o["temperature_coefficient_nT_per_C"] == nlohmann::json({1.5, -0.25, 0.0625}));
    // sqrt of the diagonal (xx, yy, zz of the stored upper triangle)
    CHECK(o["temperature_coefficient_sigma_nT_per_C"] == nlohmann::json({0.25, 0.5, 1.0}));
  }
  CHECK_FALSE(json[0].contains("temperature_model_refit_id"));  // its own estimate
  CHECK(json[1]["temperature_model_refit_id"] == 7);            // taken over from refit 7
  for (const int k : {2, 3}) {
    for (const char* key :
         {"reference_temperature_C", "temperature_coefficient_nT_per_C",
          "temperature_coefficient_sigma_nT_per_C", "temperature_model_refit_id"}) {
      CHECK_FALSE(json[static_cast<size_t>(k)].contains(key));
    }
  }

  const auto table = csv_fields(history_csv_text(all));
  REQUIRE(table.size() == 5);
  auto column = [&](const std::string& name) { return csv_column(table, name); };
  CHECK(table[1][column("has_temperature_model")] == "1");
  CHECK(table[1][column("reference_temperature_C")] == "12.5");
  CHECK(table[1][column("temperature_coefficient_x_nT_per_C")] == "1.5");
  CHECK(table[1][column("temperature_coefficient_z_nT_per_C")] == "0.0625");
  CHECK(table[1][column("temperature_coefficient_sigma_y_nT_per_C")] == "0.5");
  CHECK(table[1][column("temperature_model_refit_id")].empty());
  CHECK(table[2][column("temperature_model_refit_id")] == "7");
  CHECK(table[3][column("has_temperature_model")] == "0");
  CHECK(table[3][column("temperature_coefficient_x_nT_per_C")].empty());
  CHECK(table[4][column("has_temperature_model")].empty());

  // The table's bias of a modelled row says it is the bias at T0; the others say nothing.
  const auto lines = text_lines(history_table_text(all));
  REQUIRE(lines.size() == 5);
  CHECK(lines[1].ends_with("(bias at T0 = 12.50 degC)"));
  CHECK(lines[2].ends_with("(bias at T0 = 12.50 degC)"));
  CHECK(lines[3].find("bias at T0") == std::string::npos);
  CHECK(lines[4].find("bias at T0") == std::string::npos);
}

TEST_CASE("history JSON, CSV and table: a refit's bias rate") {
  // A refit with a rate, one whose data did not support it, an old row.
  storage::CalibrationRecord drifting;
  drifting.sat_id = "S";
  drifting.method = "twostep";
  drifting.utime = kT0;
  drifting.has_bias_rate = 1;
  drifting.bias_rate_nT_per_h = {1.5, -2.0, 0.25};
  drifting.bias_rate_cov = {0.0625, 0.25, 1.0, 1e-3, 0.0, 0.0};  // xx yy zz xy xz yz
  storage::CalibrationRecord steady = drifting;
  steady.utime = kT0 + 60'000'000;
  steady.has_bias_rate = 0;
  storage::CalibrationRecord old_row = steady;
  old_row.has_bias_rate = -1;
  const std::vector<storage::CalibrationRecord> all = {drifting, steady, old_row};

  const auto json = nlohmann::json::parse(history_json_text(all));
  REQUIRE(json.size() == 3);
  CHECK(json[0]["bias_rate_nT_per_h"] == nlohmann::json({1.5, -2.0, 0.25}));
  CHECK(json[0]["bias_rate_sigma_nT_per_h"] == nlohmann::json({0.25, 0.5, 1.0}));
  for (const size_t k : {1u, 2u}) CHECK_FALSE(json[k].contains("bias_rate_nT_per_h"));

  const auto table = csv_fields(history_csv_text(all));
  REQUIRE(table.size() == 4);
  auto column = [&](const std::string& name) { return csv_column(table, name); };
  CHECK(table[1][column("has_bias_rate")] == "1");
  CHECK(table[1][column("bias_rate_y_nT_per_h")] == "-2");
  CHECK(table[1][column("bias_rate_sigma_z_nT_per_h")] == "1");
  CHECK(table[2][column("has_bias_rate")] == "0");
  CHECK(table[2][column("bias_rate_x_nT_per_h")].empty());
  CHECK(table[3][column("has_bias_rate")].empty());

  // The table's bias of a drifting row says it is the bias at the window's end.
  const auto lines = text_lines(history_table_text(all));
  REQUIRE(lines.size() == 4);
  CHECK(lines[1].ends_with("(bias at the window's end, moving 1.50 -2.00 0.25 nT/h)"));
  CHECK(lines[2].find("window's end") == std::string::npos);
  CHECK(lines[3].find("window's end") == std::string::npos);
}

TEST_CASE("history CSV: the D sigmas, the covariance's upper triangle and the field error") {
  storage::CalibrationRecord r;
  r.sat_id = "S";
  r.method = "twostep";
  r.utime = kT0;
  for (int k = 0; k < 45; ++k) r.cov[static_cast<size_t>(k)] = 0.5 * (k + 1);
  r.cov[static_cast<size_t>(storage::cov_index(4, 4))] = 6.25;  // D22: sigma 2.5
  r.field_direction_error_rms_deg = 0.08;
  r.field_magnitude_error_worst_nT = 9.5;
  const auto table = csv_fields(history_csv_text({r}));
  REQUIRE(table.size() == 2);
  REQUIRE(table[0].size() == table[1].size());
  auto column = [&](const std::string& name) { return csv_column(table, name); };
  CHECK(table[1][column("D22_sigma")] == "2.5");
  // Every covariance entry once, named by its two parameters, in cov_index order.
  const char* names[9] = {"b1", "b2", "b3", "D11", "D22", "D33", "D12", "D13", "D23"};
  for (int i = 0; i < 9; ++i) {
    for (int j = i; j < 9; ++j) {
      const double v = r.cov[static_cast<size_t>(storage::cov_index(i, j))];
      CHECK(std::stod(table[1][column(std::string("cov_") + names[i] + "_" + names[j])]) == v);
    }
  }
  CHECK(table[1][column("field_direction_error_rms_deg")] == "0.08");
  CHECK(table[1][column("field_direction_error_worst_deg")].empty());
  CHECK(table[1][column("field_magnitude_error_worst_nT")] == "9.5");
  // The same figures in the JSON.
  const auto json = nlohmann::json::parse(history_json_text({r}));
  CHECK(json[0]["D_sigma"][1] == 2.5);
  CHECK(json[0]["field_direction_error_deg"]["rms"] == 0.08);
  CHECK(json[0]["field_magnitude_error_nT"].is_null());  // no rms: not computed
}
