// status_report (magcal status and /api/v1/spacecraft): the bias change between the last two
// refits, at one temperature when both model the bias temperature; the window's samples by
// station.
#include "service/io/status_report.hpp"

#include <unistd.h>

#include <catch2/catch.hpp>
#include <filesystem>
#include <string>
#include <vector>

#include "storage/database.hpp"
#include "storage/sample_window_store.hpp"

using magcal::SpacecraftStatus;

namespace {

constexpr int64_t kT0 = 1577836800LL * 1'000'000;

magcal::storage::CalibrationRecord refit(int64_t utime, std::array<double, 3> bias_nT) {
  magcal::storage::CalibrationRecord r;
  r.sat_id = "S";
  r.method = "twostep";
  r.utime = utime;
  r.bias_nT = bias_nT;
  r.verdict = "accepted";
  return r;
}

}  // namespace

TEST_CASE("status: the bias change compares the two refits at the last one's T0") {
  // A sensor that did not change, k_T = (1.5, -1.5, 1.5) nT/degC, b(20 degC) = (1000, 800, 900):
  // refitted on windows whose mean temperatures (T0) were 17 and 22 degC.
  const std::array<double, 3> k = {1.5, -1.5, 1.5};
  auto at = [&](double t0_C) {
    return std::array<double, 3>{1000.0 + k[0] * (t0_C - 20.0), 800.0 + k[1] * (t0_C - 20.0),
                                 900.0 + k[2] * (t0_C - 20.0)};
  };
  SpacecraftStatus s;
  s.sat_id = "S";
  s.previous_refit = refit(kT0, at(17.0));
  s.last_refit = refit(kT0 + 21'600'000'000, at(22.0));
  const int64_t window = 43'200'000'000;

  SECTION("both modelled: no change") {
    for (auto* r : {&*s.previous_refit, &*s.last_refit}) {
      r->has_temperature_model = 1;
      r->temperature_coefficient_nT_per_C = k;
    }
    s.previous_refit->reference_temperature_C = 17.0;
    s.last_refit->reference_temperature_C = 22.0;
    const auto j = magcal::status_json({s}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(0.0).margin(1e-9));
    CHECK(magcal::status_text({s}, window).find("both at 22.00 degC") != std::string::npos);
  }
  SECTION("not modelled: the plain difference, and no temperature line") {
    const auto j = magcal::status_json({s}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(k[i] * 5.0));
    CHECK(magcal::status_text({s}, window).find("degC") == std::string::npos);
  }
}

TEST_CASE("status: the samples in the window by the station that stored them") {
  const std::string path = (std::filesystem::temp_directory_path() /
                            ("magcal_status_report_" + std::to_string(::getpid()) + ".db"))
                               .string();
  const int64_t second = 1'000'000;
  const int64_t window = 3600 * second;
  auto batch = [&](int64_t first_s, int n) {
    std::vector<magcal::storage::StoredSample> out(static_cast<size_t>(n));
    for (int k = 0; k < n; ++k) {
      auto& s = out[static_cast<size_t>(k)];
      s.sat_id = "S";
      s.utime = kT0 + (first_s + 10 * k) * second;
      s.seq = k;
      s.h_norm_nT = 4.0e4;
    }
    return out;
  };
  std::vector<SpacecraftStatus> all;
  {
    magcal::storage::Database db(path);
    const auto samples = db.make_sample_window_store();
    samples->insert_batch(batch(0, 30), nullptr, "gs-b");  // 0..290 s: out of the window
    all = magcal::read_status(db, window);
    REQUIRE(all.size() == 1);
    CHECK(magcal::status_text(all, window).find("by station") != std::string::npos);
    samples->insert_batch(batch(300, 5));                           // no station, out too
    samples->insert_batch(batch(4000, 20), nullptr, "gs-b");        // 4000..4190 s
    samples->insert_batch(batch(4100, 30), nullptr, "gs-a");        // 4200..4390 s new: 20
    samples->insert_batch(batch(4195, 1), nullptr, "gs-a");         // new: 21
    samples->insert_batch(batch(4390 - 3600, 1), nullptr, "gs-c");  // newest - window: out
    all = magcal::read_status(db, window);
  }
  std::filesystem::remove(path);
  REQUIRE(all.size() == 1);
  // The window (4390 s - 1 h, 4390 s] holds gs-b's 20 and gs-a's 21.
  CHECK(all[0].samples_in_window == 41);
  REQUIRE(all[0].samples_by_station.size() == 2);
  CHECK(all[0].samples_by_station[0].station == "gs-a");
  CHECK(all[0].samples_by_station[0].samples == 21);
  CHECK(all[0].samples_by_station[1].station == "gs-b");
  CHECK(all[0].samples_by_station[1].samples == 20);
  CHECK(magcal::status_text(all, window).find("  by station       gs-a 21, gs-b 20\n") !=
        std::string::npos);
  const auto j = magcal::status_json(all, window)["spacecraft"][0]["samples_by_station"];
  CHECK(j == nlohmann::json::parse(
                 R"([{"station": "gs-a", "samples": 21}, {"station": "gs-b", "samples": 20}])"));

  // Samples without a station are shown as such; none named at all: no line.
  all[0].samples_by_station = {{"", 5}, {"gs-a", 3}};
  CHECK(magcal::status_text(all, window).find("by station       no station 5, gs-a 3\n") !=
        std::string::npos);
  CHECK(magcal::status_json(all, window)["spacecraft"][0]["samples_by_station"][0]["station"]
            .is_null());
  all[0].samples_by_station = {{"", 5}};
  CHECK(magcal::status_text(all, window).find("by station") == std::string::npos);
}
