// status_report (magcal status and /api/v1/spacecraft): the bias change between the last two
// refits, at one temperature when both model the bias temperature; the window's samples by
// station; the stations sharing the database, live or gone, and what each owns.
#include "service/io/status_report.hpp"

#include <unistd.h>

#include <catch2/catch.hpp>
#include <chrono>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "storage/lease_store.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"

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
    const auto j = magcal::status_json({.spacecraft = {s}, .stations = {}}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(0.0).margin(1e-9));
    CHECK(magcal::status_text({.spacecraft = {s}, .stations = {}}, window)
              .find("both at 22.00 degC") != std::string::npos);
  }
  SECTION("not modelled: the plain difference, and no temperature line") {
    const auto j = magcal::status_json({.spacecraft = {s}, .stations = {}}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(k[i] * 5.0));
    CHECK(magcal::status_text({.spacecraft = {s}, .stations = {}}, window).find("degC") ==
          std::string::npos);
  }
}

TEST_CASE("status: a previous refit with a bias rate is moved by it to the last one's window end") {
  // A sensor drifting (1, -2, 0.5) nT/h, refitted 6 h apart, each bias at its window's end.
  const int64_t six_hours = 21'600'000'000;
  SpacecraftStatus s;
  s.sat_id = "S";
  s.previous_refit = refit(kT0, {1000.0, 800.0, 900.0});
  s.previous_refit->window_end_utime = kT0;
  s.previous_refit->window_start_utime = kT0 - 2 * six_hours;
  s.last_refit = refit(kT0 + six_hours, {1006.0, 788.0, 905.0});  // 2 nT on z beyond the drift
  s.last_refit->window_end_utime = kT0 + six_hours;
  SECTION("the previous refit has the rate: the change is what it did not predict") {
    s.previous_refit->has_bias_rate = 1;
    s.previous_refit->bias_rate_nT_per_h = {1.0, -2.0, 0.5};
    const auto j = magcal::status_json({.spacecraft = {s}, .stations = {}}, 2 * six_hours);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    CHECK(d[0].get<double>() == Approx(0.0).margin(1e-9));
    CHECK(d[1].get<double>() == Approx(0.0).margin(1e-9));
    CHECK(d[2].get<double>() == Approx(2.0));
    CHECK(magcal::status_text({.spacecraft = {s}, .stations = {}}, 2 * six_hours)
              .find("the previous refit moved by its bias rate to 2020-01-01T06:00:00") !=
          std::string::npos);
  }
  SECTION("without a rate: the plain difference") {
    const auto j = magcal::status_json({.spacecraft = {s}, .stations = {}}, 2 * six_hours);
    CHECK(j["spacecraft"][0]["bias_change_since_previous_refit_nT"][1].get<double>() ==
          Approx(-12.0));
  }
}

TEST_CASE(
    "status: a refit run again at the same data time shows the change since the window "
    "before, not a zero change against its twin") {
  const std::string path = (std::filesystem::temp_directory_path() /
                            ("magcal_status_twin_" + std::to_string(::getpid()) + ".db"))
                               .string();
  const int64_t six_hours = 21'600'000'000;
  magcal::FleetStatus fleet;
  {
    magcal::storage::Database db(path);
    const auto history = db.make_calibration_history();
    history->append(refit(kT0, {1000.0, 800.0, 900.0}));
    history->append(refit(kT0 + six_hours, {1003.0, 804.0, 900.0}));
    auto robust = refit(kT0 + six_hours, {1003.5, 804.0, 900.0});  // e.g. `magcal refit --robust`
    robust.method = "centered";
    history->append(robust);
    fleet = magcal::read_status(db, 2 * six_hours);
  }
  std::filesystem::remove(path);
  REQUIRE(fleet.spacecraft.size() == 1);
  const std::string text = magcal::status_text(fleet, 2 * six_hours);
  INFO(text);
  CHECK(text.find("[    +3.50     +4.00     +0.00] nT  (|change| 5.32 nT) since the refit of "
                  "2020-01-01T00:00:00") != std::string::npos);
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
  magcal::FleetStatus all;
  {
    magcal::storage::Database db(path);
    const auto samples = db.make_sample_window_store();
    samples->insert_batch(batch(0, 30), nullptr, "gs-b");  // 0..290 s: out of the window
    all = magcal::read_status(db, window);
    REQUIRE(all.spacecraft.size() == 1);
    CHECK(magcal::status_text(all, window).find("by station") != std::string::npos);
    samples->insert_batch(batch(300, 5));                           // no station, out too
    samples->insert_batch(batch(4000, 20), nullptr, "gs-b");        // 4000..4190 s
    samples->insert_batch(batch(4100, 30), nullptr, "gs-a");        // 4200..4390 s new: 20
    samples->insert_batch(batch(4195, 1), nullptr, "gs-a");         // new: 21
    samples->insert_batch(batch(4390 - 3600, 1), nullptr, "gs-c");  // newest - window: out
    all = magcal::read_status(db, window);
  }
  std::filesystem::remove(path);
  REQUIRE(all.spacecraft.size() == 1);
  // The window (4390 s - 1 h, 4390 s] holds gs-b's 20 and gs-a's 21.
  CHECK(all.spacecraft[0].samples_in_window == 41);
  REQUIRE(all.spacecraft[0].samples_by_station.size() == 2);
  CHECK(all.spacecraft[0].samples_by_station[0].station == "gs-a");
  CHECK(all.spacecraft[0].samples_by_station[0].samples == 21);
  CHECK(all.spacecraft[0].samples_by_station[1].station == "gs-b");
  CHECK(all.spacecraft[0].samples_by_station[1].samples == 20);
  CHECK(magcal::status_text(all, window).find("  by station       gs-a 21, gs-b 20\n") !=
        std::string::npos);
  const auto j = magcal::status_json(all, window)["spacecraft"][0]["samples_by_station"];
  CHECK(j == nlohmann::json::parse(
                 R"([{"station": "gs-a", "samples": 21}, {"station": "gs-b", "samples": 20}])"));

  // Samples without a station are shown as such; none named at all: no line.
  all.spacecraft[0].samples_by_station = {{"", 5}, {"gs-a", 3}};
  CHECK(magcal::status_text(all, window).find("by station       no station 5, gs-a 3\n") !=
        std::string::npos);
  CHECK(magcal::status_json(all, window)["spacecraft"][0]["samples_by_station"][0]["station"]
            .is_null());
  all.spacecraft[0].samples_by_station = {{"", 5}};
  CHECK(magcal::status_text(all, window).find("by station") == std::string::npos);
}

TEST_CASE("status: the stations sharing the database, live or gone, with what each owns") {
  const std::string path = (std::filesystem::temp_directory_path() /
                            ("magcal_status_stations_" + std::to_string(::getpid()) + ".db"))
                               .string();
  const int64_t second = 1'000'000;
  // Liveness is judged on the wall clock at the read, as the daemons beat on it.
  const int64_t now = std::chrono::duration_cast<std::chrono::microseconds>(
                          std::chrono::system_clock::now().time_since_epoch())
                          .count();
  magcal::FleetStatus fleet;
  {
    magcal::storage::Database db(path);
    const auto leases = db.make_lease_store();
    leases->heartbeat("gs-b", "b1", {}, now - 600 * second, 30 * second);  // died 10 min ago
    leases->heartbeat("gs-a", "a1", {}, now, 3600 * second);
    leases->heartbeat("gs-c", "c1", {}, now, 3600 * second);
    leases->leave("gs-c", now);  // a clean stop: gone at once
    REQUIRE(leases->try_acquire("S1", "gs-a", now, 3600 * second));
    REQUIRE(leases->try_acquire("S2", "gs-a", now, 3600 * second));
    REQUIRE(leases->try_acquire("S3", "gs-b", now - 600 * second, 30 * second));  // expired
    // Status lists spacecraft with samples or results: give each a result-free sample.
    const auto samples = db.make_sample_window_store();
    std::vector<magcal::storage::StoredSample> rows(3);
    for (int k = 0; k < 3; ++k) {
      rows[static_cast<size_t>(k)].sat_id = "S" + std::to_string(k + 1);
      rows[static_cast<size_t>(k)].utime = kT0;
      rows[static_cast<size_t>(k)].h_norm_nT = 4.0e4;
    }
    samples->insert_batch(rows);
    fleet = magcal::read_status(db, 3600 * second);
  }
  std::filesystem::remove(path);
  REQUIRE(fleet.spacecraft.size() == 3);
  REQUIRE(fleet.stations.size() == 3);
  CHECK(fleet.stations[0].row.station == "gs-a");
  CHECK(fleet.stations[0].live);
  CHECK(fleet.stations[0].spacecraft_owned == 2);
  CHECK(fleet.stations[1].row.station == "gs-b");
  CHECK_FALSE(fleet.stations[1].live);
  CHECK(fleet.stations[1].spacecraft_owned == 0);  // its expired lease is owned by nobody
  CHECK(fleet.stations[2].row.station == "gs-c");
  CHECK_FALSE(fleet.stations[2].live);

  const std::string text = magcal::status_text(fleet, 3600 * second);
  CHECK(text.find("stations (wall clock)\n  gs-a             live, last beat ") !=
        std::string::npos);
  CHECK(text.find(", owns 2 spacecraft\n") != std::string::npos);
  CHECK(text.find("  gs-b             gone since ") != std::string::npos);
  const auto j = magcal::status_json(fleet, 3600 * second)["stations"];
  REQUIRE(j.size() == 3);
  CHECK(j[0]["station"] == "gs-a");
  CHECK(j[0]["live"] == true);
  CHECK(j[0]["spacecraft_owned"] == 2);
  CHECK(j[1]["live"] == false);
  CHECK(j[1]["expires_utime"] == now - 570 * second);
  CHECK(j[2]["expires_utime"] == now);
}

TEST_CASE("status: live stations whose settings differ from the majority's are marked") {
  const std::string path = (std::filesystem::temp_directory_path() /
                            ("magcal_status_settings_" + std::to_string(::getpid()) + ".db"))
                               .string();
  const int64_t second = 1'000'000;
  const int64_t now = std::chrono::duration_cast<std::chrono::microseconds>(
                          std::chrono::system_clock::now().time_since_epoch())
                          .count();
  const auto common = magcal::station_settings({{"refit.every_hours", "0"}, {"ukf.alpha", "1"}});
  const auto other = magcal::station_settings({{"refit.every_hours", "6"}, {"ukf.alpha", "1"}});
  const auto read = [&](const std::function<void(magcal::storage::LeaseStore&)>& beat) {
    magcal::FleetStatus fleet;
    {
      magcal::storage::Database db(path);
      beat(*db.make_lease_store());
      fleet = magcal::read_status(db, 3600 * second);
    }
    std::filesystem::remove(path);
    return fleet;
  };

  SECTION("two agree, one differs: the one is marked, against the two") {
    const auto fleet = read([&](magcal::storage::LeaseStore& leases) {
      leases.heartbeat("gs-a", "a1", common, now, 3600 * second);
      leases.heartbeat("gs-b", "b1", other, now, 3600 * second);
      leases.heartbeat("gs-c", "c1", common, now, 3600 * second);
      // Gone, with yet other settings: not compared (a stopped station owns nothing).
      leases.heartbeat("gs-d", "d1", magcal::station_settings({{"refit.every_hours", "9"}}),
                       now - 600 * second, 30 * second);
    });
    REQUIRE(fleet.stations.size() == 4);
    CHECK(fleet.stations[0].settings_differ_from.empty());
    CHECK(fleet.stations[2].settings_differ_from.empty());
    CHECK(fleet.stations[3].settings_differ_from.empty());
    const auto& b = fleet.stations[1];
    CHECK(b.settings_differ_from == std::vector<std::string>{"gs-a", "gs-c"});
    REQUIRE(b.settings_differences.size() == 1);
    CHECK(b.settings_differences[0].key == "refit.every_hours");

    const std::string text = magcal::status_text(fleet, 3600 * second);
    CHECK(text.find(", owns 0 spacecraft\n                   SETTINGS DIFFER from gs-a, gs-c: "
                    "refit.every_hours 6 here, 0 there\n  gs-c ") != std::string::npos);
    CHECK(text.find("SETTINGS DIFFER") == text.rfind("SETTINGS DIFFER"));  // only gs-b
    const auto j = magcal::status_json(fleet, 3600 * second)["stations"];
    CHECK(j[0]["settings_differ"].is_null());
    CHECK(j[0]["settings_hash"] == common.hash);
    CHECK(j[1]["settings_hash"] == other.hash);
    CHECK(j[1]["settings_differ"]["from"] == nlohmann::json{"gs-a", "gs-c"});
    CHECK(j[1]["settings_differ"]["keys"] ==
          nlohmann::json::parse(R"([{"key": "refit.every_hours", "here": "6", "there": "0"}])"));
  }
  SECTION("one against one: no majority, both are marked, each against the other") {
    const auto fleet = read([&](magcal::storage::LeaseStore& leases) {
      leases.heartbeat("gs-a", "a1", common, now, 3600 * second);
      leases.heartbeat("gs-b", "b1", other, now, 3600 * second);
    });
    REQUIRE(fleet.stations.size() == 2);
    CHECK(fleet.stations[0].settings_differ_from == std::vector<std::string>{"gs-b"});
    CHECK(fleet.stations[1].settings_differ_from == std::vector<std::string>{"gs-a"});
    CHECK(magcal::status_text(fleet, 3600 * second)
              .find("SETTINGS DIFFER from gs-b: refit.every_hours 0 here, 6 there\n") !=
          std::string::npos);
  }
  SECTION("equal settings, or a station that declares none: nothing is marked") {
    const auto fleet = read([&](magcal::storage::LeaseStore& leases) {
      leases.heartbeat("gs-a", "a1", common, now, 3600 * second);
      leases.heartbeat("gs-b", "b1", common, now, 3600 * second);
      leases.heartbeat("gs-c", "c1", {}, now, 3600 * second);
    });
    for (const auto& st : fleet.stations) CHECK(st.settings_differ_from.empty());
    const std::string text = magcal::status_text(fleet, 3600 * second);
    CHECK(text.find("SETTINGS DIFFER") == std::string::npos);
    CHECK(magcal::status_json(fleet, 3600 * second)["stations"][2]["settings_hash"].is_null());
  }
}
