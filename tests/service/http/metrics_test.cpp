// Metrics (service/http/metrics.hpp): the exposition text parses (an independent reader,
// tests/service/prometheus_text.hpp), carries exactly the contract's names with the values that
// were counted, and the database-only metrics of `magcal serve` equal counts made here from
// the rows the test wrote.
#include "service/http/metrics.hpp"

#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <map>
#include <set>

#include <catch2/catch.hpp>

#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/prometheus_text.hpp"

namespace {

namespace fs = std::filesystem;
using magcal::http::DaemonMetrics;
using magcal::test::parse_prometheus_text;

struct TempDb {
  fs::path dir;
  TempDb() {
    dir = fs::temp_directory_path() / ("magcal_metrics_" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir);
  }
  ~TempDb() { fs::remove_all(dir); }
  std::string path() const { return (dir / "m.db").string(); }
};

}  // namespace

TEST_CASE("daemon metrics: the contract's names, the counted values, valid text", "[metrics]") {
  const std::vector<double> bounds_s{0.001, 0.01, 1.0};
  DaemonMetrics m("9.9.9-test", "gs-north", bounds_s);
  DaemonMetrics::SpacecraftTotals a;
  a.sat_label = "SAT-A";
  a.received = 300;
  a.stored = 290;
  a.refits_accepted = 1;
  a.refits_rejected = 1;
  a.last_refit_success_utime = 1'577'923'200'000'000;
  a.has_ukf_snapshot = true;
  a.ukf_bias_nT = {1000.5, 800.25, -900.0};
  a.ukf_bias_sigma_nT = {0.3, 1.2, 0.2};
  a.ukf_accepted = true;
  a.owned = true;
  DaemonMetrics::SpacecraftTotals b;
  b.sat_label = "SAT-B";
  b.received = 7;
  b.missing = 2;
  b.refits_error = 1;
  b.refits_claimed_elsewhere = 3;
  // Commit latencies, put in buckets here (le semantics) from the observations.
  const std::vector<double> commits_s{0.0002, 0.003, 0.003, 7.0};
  std::vector<int64_t> buckets(bounds_s.size() + 1, 0);
  for (const double c : commits_s) {
    ++buckets[static_cast<size_t>(std::lower_bound(bounds_s.begin(), bounds_s.end(), c) -
                                  bounds_s.begin())];
  }
  int64_t duplicates = 4;
  m.set_totals_source([&] {
    DaemonMetrics::Totals t;
    t.rejected_by_reason = {{"duplicate", duplicates}, {"out_of_range", 1}};
    t.queue_depth = 12;
    t.queue_overflow = 5;
    t.storage_healthy = false;
    t.storage_failing_s = 42.5;
    t.storage_pending = 4000;
    t.spilled = 12000;
    t.spill_held = 8000;
    t.spill_bytes = 1'300'000;
    t.spill_recovered = 17;
    t.spill_dropped = 1;
    t.leases_lost = 2;
    t.fleet_settings_mismatch = 1;
    t.spacecraft = {a, b};
    t.commit_bucket_counts = buckets;
    t.commit_sum_s = 7.0062;
    return t;
  });

  const auto p = parse_prometheus_text(m.text());
  REQUIRE(p.error.empty());
  const std::map<std::string, std::string> expected_types{
      {"magcal_samples_received_total", "counter"},
      {"magcal_samples_stored_total", "counter"},
      {"magcal_samples_rejected_total", "counter"},
      {"magcal_samples_missing_total", "counter"},
      {"magcal_queue_depth", "gauge"},
      {"magcal_queue_overflow_total", "counter"},
      {"magcal_storage_commit_seconds", "histogram"},
      {"magcal_sqlite_commit_seconds", "histogram"},
      {"magcal_ukf_bias_nT", "gauge"},
      {"magcal_ukf_bias_sigma_nT", "gauge"},
      {"magcal_ukf_snapshot_accepted", "gauge"},
      {"magcal_refits_total", "counter"},
      {"magcal_refits_claimed_elsewhere_total", "counter"},
      {"magcal_last_refit_success_timestamp_seconds", "gauge"},
      {"magcal_storage_healthy", "gauge"},
      {"magcal_storage_failing_seconds", "gauge"},
      {"magcal_storage_pending_samples", "gauge"},
      {"magcal_samples_spilled_total", "counter"},
      {"magcal_spill_samples", "gauge"},
      {"magcal_spill_bytes", "gauge"},
      {"magcal_spill_recovered_samples_total", "counter"},
      {"magcal_spill_dropped_records_total", "counter"},
      {"magcal_spacecraft_owned", "gauge"},
      {"magcal_leases_lost_total", "counter"},
      {"magcal_fleet_settings_mismatch", "gauge"},
      {"magcal_build_info", "gauge"},
      {"magcal_station_info", "gauge"}};
  CHECK(p.types == expected_types);
  CHECK(p.value("magcal_spacecraft_owned", {{"sat", "SAT-A"}}) == 1.0);
  CHECK(p.value("magcal_spacecraft_owned", {{"sat", "SAT-B"}}) == 0.0);  // another daemon's
  CHECK(p.value("magcal_leases_lost_total") == 2.0);
  CHECK(p.value("magcal_fleet_settings_mismatch") == 1.0);

  CHECK(p.value("magcal_samples_received_total", {{"sat", "SAT-A"}}) == 300.0);
  CHECK(p.sum("magcal_samples_received_total") == 307.0);
  CHECK(p.value("magcal_samples_stored_total", {{"sat", "SAT-A"}}) == 290.0);
  CHECK(p.value("magcal_samples_missing_total", {{"sat", "SAT-B"}}) == 2.0);
  CHECK(p.value("magcal_samples_rejected_total", {{"reason", "duplicate"}}) == 4.0);
  CHECK(p.value("magcal_samples_rejected_total", {{"reason", "out_of_range"}}) == 1.0);
  CHECK(p.value("magcal_queue_depth") == 12.0);
  CHECK(p.value("magcal_queue_overflow_total") == 5.0);
  CHECK(p.value("magcal_storage_healthy") == 0.0);
  CHECK(p.value("magcal_storage_failing_seconds") == 42.5);
  CHECK(p.value("magcal_storage_pending_samples") == 4000.0);
  CHECK(p.value("magcal_samples_spilled_total") == 12000.0);
  CHECK(p.value("magcal_spill_samples") == 8000.0);
  CHECK(p.value("magcal_spill_bytes") == 1'300'000.0);
  CHECK(p.value("magcal_spill_recovered_samples_total") == 17.0);
  CHECK(p.value("magcal_spill_dropped_records_total") == 1.0);
  CHECK(p.value("magcal_build_info", {{"version", "9.9.9-test"}}) == 1.0);
  CHECK(p.value("magcal_station_info", {{"station", "gs-north"}}) == 1.0);
  CHECK(p.sum("magcal_station_info") == 1.0);  // one station: this daemon's
  CHECK(p.value("magcal_ukf_bias_nT", {{"sat", "SAT-A"}, {"axis", "y"}}) == 800.25);
  CHECK(p.value("magcal_ukf_bias_sigma_nT", {{"sat", "SAT-A"}, {"axis", "x"}}) == 0.3);
  CHECK(p.value("magcal_ukf_snapshot_accepted", {{"sat", "SAT-A"}}) == 1.0);
  // No snapshot of SAT-B yet: no bias series (never a made-up 0 nT).
  CHECK(p.sum("magcal_ukf_bias_nT", {{"sat", "SAT-B"}}) == 0.0);
  CHECK(!p.value("magcal_ukf_bias_nT", {{"sat", "SAT-B"}, {"axis", "x"}}));
  CHECK(p.value("magcal_refits_total", {{"sat", "SAT-A"}, {"verdict", "accepted"}}) == 1.0);
  CHECK(p.value("magcal_refits_total", {{"sat", "SAT-A"}, {"verdict", "rejected"}}) == 1.0);
  CHECK(p.value("magcal_refits_total", {{"sat", "SAT-B"}, {"verdict", "error"}}) == 1.0);
  CHECK(p.value("magcal_refits_claimed_elsewhere_total", {{"sat", "SAT-B"}}) == 3.0);
  CHECK(p.value("magcal_refits_claimed_elsewhere_total", {{"sat", "SAT-A"}}) == 0.0);
  CHECK(p.value("magcal_last_refit_success_timestamp_seconds", {{"sat", "SAT-A"}}) ==
        1'577'923'200.0);
  CHECK(!p.value("magcal_last_refit_success_timestamp_seconds", {{"sat", "SAT-B"}}));

  // Histogram: cumulative buckets counted here from the observations, +Inf = count; the same
  // under the backend-neutral name and the deprecated one.
  for (const std::string histogram :
       {"magcal_storage_commit_seconds", "magcal_sqlite_commit_seconds"}) {
    INFO(histogram);
    CHECK(p.value(histogram + "_count") == 4.0);
    CHECK(p.value(histogram + "_sum") == Approx(7.0062));
    for (const double le : bounds_s) {
      double n = 0;
      for (const double c : commits_s) n += c <= le ? 1 : 0;
      const auto it = std::find_if(p.samples.begin(), p.samples.end(), [&](const auto& x) {
        return x.name == histogram + "_bucket" && std::stod(x.labels.at("le")) == le;
      });
      REQUIRE(it != p.samples.end());
      CHECK(it->value == n);
    }
    CHECK(p.value(histogram + "_bucket", {{"le", "+Inf"}}) == 4.0);
  }

  // Totals kept by the daemon only move the counters forward; a scrape with nothing new adds
  // nothing to the histogram.
  duplicates = 9;
  a.received = 310;
  ++buckets[1];
  const auto p2 = parse_prometheus_text(m.text());
  CHECK(p2.value("magcal_samples_rejected_total", {{"reason", "duplicate"}}) == 9.0);
  CHECK(p2.value("magcal_samples_received_total", {{"sat", "SAT-A"}}) == 310.0);
  const auto p3 = parse_prometheus_text(m.text());
  for (const std::string histogram :
       {"magcal_storage_commit_seconds", "magcal_sqlite_commit_seconds"}) {
    INFO(histogram);
    CHECK(p2.value(histogram + "_count") == 5.0);
    CHECK(p3.value(histogram + "_count") == 5.0);
    CHECK(p3.value(histogram + "_sum") == Approx(7.0062));
  }
}

TEST_CASE("daemon metrics: label values are escaped", "[metrics]") {
  const std::string odd = "SAT \"quoted\" \\ back\nslash";
  DaemonMetrics m("1", odd, {0.1});
  m.set_totals_source([&] {
    DaemonMetrics::Totals t;
    DaemonMetrics::SpacecraftTotals s;
    s.sat_label = odd;
    s.received = 3;
    t.spacecraft.push_back(s);
    s.sat_label = "";  // undecodable frames
    s.received = 1;
    t.spacecraft.push_back(s);
    return t;
  });
  const auto p = parse_prometheus_text(m.text());
  REQUIRE(p.error.empty());
  CHECK(p.value("magcal_samples_received_total", {{"sat", odd}}) == 3.0);
  CHECK(p.sum("magcal_samples_received_total") == 4.0);
  CHECK(p.value("magcal_station_info", {{"station", odd}}) == 1.0);
}

TEST_CASE("database metrics (magcal serve): what the database holds", "[metrics]") {
  namespace st = magcal::storage;
  TempDb tmp;
  std::map<std::string, int> stored;
  std::map<std::pair<std::string, std::string>, int> stored_by_station;  // (sat, station)
  std::map<std::string, std::vector<std::pair<int64_t, std::string>>>
      stored_rows;  // (utime, station)
  {
    st::Database db(tmp.path());
    st::SqliteSampleWindowStore samples(db);
    // Three batches: stations gs-a and gs-b, and one without a station (before schema 7); the
    // second repeats half of the first's samples, which stay gs-a's.
    std::set<int64_t> held;
    for (const auto& [station, first] : {std::pair{"gs-a", 0}, {"gs-b", 50}, {"", 150}}) {
      std::vector<st::StoredSample> rows;
      int new_rows = 0;
      for (int i = first; i < first + 100; ++i) {
        st::StoredSample s;
        s.sat_id = i % 5 == 0 ? "SAT-B" : "SAT-A";
        s.utime = 1'577'836'800'000'000 + int64_t{i} * 10'000'000;
        s.h_norm_nT = 40000.0;
        rows.push_back(s);
        if (!held.insert(s.utime).second) continue;  // an earlier station's
        ++stored[s.sat_id];
        ++stored_by_station[{s.sat_id, station}];
        stored_rows[s.sat_id].emplace_back(s.utime, station);
        ++new_rows;
      }
      REQUIRE(samples.insert_batch(rows, nullptr, station).inserted == new_rows);
    }
    st::SqliteCalibrationHistory history(db);
    auto record = [](const std::string& method, int64_t utime, bool accepted, double bx) {
      st::CalibrationRecord r;
      r.sat_id = "SAT-A";
      r.method = method;
      r.utime = utime;
      r.bias_nT = {bx, 2.0, 3.0};
      r.cov[st::cov_index(0, 0)] = 0.25;  // sigma x = 0.5 nT
      r.cov[st::cov_index(1, 1)] = 4.0;
      r.cov[st::cov_index(2, 2)] = 9.0;
      r.verdict = accepted ? "accepted" : "rejected";
      r.status = accepted ? 0 : 4;
      return r;
    };
    history.append(record("twostep", 1'577'858'400'000'000, true, 10.0));
    history.append(record("twostep", 1'577'880'000'000'000, false, 11.0));
    history.append(record("centered", 1'577'880'000'000'000, true, 12.0));
    history.append(record("ukf", 1'577'880'000'000'000, true, 13.0));
    history.append(record("ukf", 1'577'880'060'000'000, false, 14.0));  // the newest one
  }
  st::Database db(tmp.path(), st::OpenOptions{.read_only = true});
  const int64_t day_utime = 86'400'000'000;
  const auto p = parse_prometheus_text(magcal::http::database_metrics_text(db, "2.0", day_utime));
  REQUIRE(p.error.empty());
  // A shorter window counts what `magcal status` counts: (newest - W, newest] per spacecraft.
  {
    const int64_t window_utime = 1'000'000'000;  // 1000 s of the 2490 s stored
    const auto q =
        parse_prometheus_text(magcal::http::database_metrics_text(db, "2.0", window_utime));
    REQUIRE(q.error.empty());
    REQUIRE(stored_rows.size() == 2);  // SAT-A and SAT-B: the loop below checks both
    for (const auto& [sat, rows] : stored_rows) {
      int64_t newest = rows.front().first;
      for (const auto& r : rows) newest = std::max(newest, r.first);
      std::map<std::string, int> in_window;
      int total = 0;
      for (const auto& [utime, station] : rows) {
        if (utime > newest - window_utime) ++in_window[station], ++total;
      }
      INFO(sat);
      CHECK(total > 0);
      CHECK(total < stored[sat]);
      CHECK(q.value("magcal_window_samples", {{"sat", sat}}) == total);
      for (const auto& [station, n] : in_window) {
        CHECK(q.value("magcal_window_samples_by_station", {{"sat", sat}, {"station", station}}) ==
              n);
      }
    }
  }
  CHECK(p.value("magcal_window_samples", {{"sat", "SAT-A"}}) == stored["SAT-A"]);
  CHECK(p.value("magcal_window_samples", {{"sat", "SAT-B"}}) == stored["SAT-B"]);
  REQUIRE(stored_by_station.size() == 6);  // both spacecraft from each of the three batches
  for (const auto& [key, n] : stored_by_station) {
    INFO(key.first << " by '" << key.second << "'");
    CHECK(p.value("magcal_window_samples_by_station",
                  {{"sat", key.first}, {"station", key.second}}) == n);
  }
  CHECK(p.sum("magcal_window_samples_by_station") == p.sum("magcal_window_samples"));
  CHECK(!p.has("magcal_samples_stored_total"));  // retention makes the held count fall
  CHECK(p.value("magcal_refits_total", {{"sat", "SAT-A"}, {"verdict", "accepted"}}) == 2.0);
  CHECK(p.value("magcal_refits_total", {{"sat", "SAT-A"}, {"verdict", "rejected"}}) == 1.0);
  CHECK(p.value("magcal_last_refit_success_timestamp_seconds", {{"sat", "SAT-A"}}) ==
        1'577'880'000.0);
  CHECK(p.value("magcal_ukf_bias_nT", {{"sat", "SAT-A"}, {"axis", "x"}}) == 14.0);
  CHECK(p.value("magcal_ukf_bias_sigma_nT", {{"sat", "SAT-A"}, {"axis", "x"}}) == 0.5);
  CHECK(p.value("magcal_ukf_bias_sigma_nT", {{"sat", "SAT-A"}, {"axis", "z"}}) == 3.0);
  CHECK(p.value("magcal_ukf_snapshot_accepted", {{"sat", "SAT-A"}}) == 0.0);
  CHECK(p.value("magcal_build_info", {{"version", "2.0"}}) == 1.0);
  CHECK(!p.has("magcal_samples_received_total"));  // only a running daemon knows
  CHECK(!p.has("magcal_sqlite_commit_seconds_count"));
  CHECK(!p.has("magcal_storage_commit_seconds_count"));
  CHECK(!p.has("magcal_station_info"));  // a database has many stations: by_station above
}
