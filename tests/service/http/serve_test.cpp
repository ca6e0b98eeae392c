// `magcal serve` over a replayed day (real `magcal sim` + `magcald` + `magcal serve` binaries):
// the API answers byte for byte what `magcal history` / `magcal status --json` print for the
// same arguments, points=N agrees with the raw rows, SIGTERM ends it with 0, and the database
// file is untouched.
#include <sys/stat.h>

#include <map>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/service/prometheus_text.hpp"

using magcal::test::http_get;
using magcal::test::run_magcal;
using magcal::test::ServeProcess;
using magcal::test::TempDir;

namespace {

const std::string kSat = "PAPER-1";

// CLI arguments -> the same request as URL query parameters.
struct Args {
  std::string cli, url;
};

}  // namespace

TEST_CASE("serve over a replayed day: history JSON and CSV and status are the CLI's bytes") {
  const std::string& db = magcal::test::replayed_day_db();
  TempDir dir("magcal_serve");
  struct stat before {};
  REQUIRE(::stat(db.c_str(), &before) == 0);
  const auto bytes_before = magcal::test::slurp(db);

  ServeProcess serve(db, dir);
  const std::vector<Args> requests = {
      {"", ""},
      {"--method ukf", "&method=ukf"},
      {"--method twostep", "&method=twostep"},
      {"--since 2020-01-01T06:00:00Z --until 2020-01-01T12:00:00Z",
       "&since=2020-01-01T06:00:00Z&until=2020-01-01T12:00:00Z"},
      {"--limit 10 --order desc", "&limit=10&order=desc"},
      {"--method ukf --limit 1", "&method=ukf&limit=1"},
  };
  for (const auto& a : requests) {
    for (const std::string format : {"json", "csv"}) {
      INFO(a.cli << " --format " << format);
      const auto cli = run_magcal("history --db " + db + " --sat " + kSat + " --format " + format +
                                      (a.cli.empty() ? "" : " " + a.cli),
                                  dir);
      REQUIRE(cli.exit_code == 0);
      REQUIRE(cli.out.size() > 100);
      const auto api =
          http_get(serve.port(), "/api/v1/history?sat=" + kSat + "&format=" + format + a.url);
      REQUIRE(api.status == 200);
      REQUIRE(api.body == cli.out);
    }
  }
  // The default format of the API is JSON.
  REQUIRE(http_get(serve.port(), "/api/v1/history?sat=" + kSat).body ==
          run_magcal("history --db " + db + " --sat " + kSat + " --format json", dir).out);
  const auto status = run_magcal("status --db " + db + " --json", dir);
  REQUIRE(status.exit_code == 0);
  const auto spacecraft = http_get(serve.port(), "/api/v1/spacecraft");
  REQUIRE(spacecraft.status == 200);
  REQUIRE(spacecraft.body == status.out);
  const auto j = nlohmann::json::parse(spacecraft.body);
  REQUIRE(j["spacecraft"].size() == 1);
  REQUIRE(j["spacecraft"][0]["last_refit"]["verdict"] == "accepted");

  // Unknown spacecraft: the CLI notes it on stderr (exit 0, nothing on stdout), the API 400s.
  REQUIRE(http_get(serve.port(), "/api/v1/history?sat=NOPE").status == 400);
  REQUIRE(serve.stop() == 0);

  struct stat after {};
  REQUIRE(::stat(db.c_str(), &after) == 0);
  REQUIRE(after.st_size == before.st_size);
  REQUIRE(after.st_mtim.tv_nsec == before.st_mtim.tv_nsec);
  REQUIRE(after.st_mtim.tv_sec == before.st_mtim.tv_sec);
  REQUIRE(magcal::test::slurp(db) == bytes_before);
}

TEST_CASE("serve over a replayed day: points=N buckets agree with the raw rows") {
  const std::string& db = magcal::test::replayed_day_db();
  TempDir dir("magcal_serve_points");
  ServeProcess serve(db, dir);
  const auto raw = nlohmann::json::parse(
      http_get(serve.port(), "/api/v1/history?sat=" + kSat + "&method=ukf").body);
  REQUIRE(raw.size() > 1000);
  for (const int points : {1, 24, 500, 5000}) {
    INFO("points=" << points);
    const auto r = http_get(serve.port(), "/api/v1/history?sat=" + kSat +
                                              "&method=ukf&points=" + std::to_string(points));
    REQUIRE(r.status == 200);
    const auto d = nlohmann::json::parse(r.body);
    REQUIRE(d["rows"] == raw.size());
    const auto& buckets = d["series"].at(0)["buckets"];
    REQUIRE(buckets.size() <= static_cast<size_t>(points));
    size_t total = 0;
    int64_t previous_end = std::numeric_limits<int64_t>::min();
    for (const auto& b : buckets) {
      const int64_t lo = b["start_utime"], hi = b["end_utime"];
      REQUIRE(lo > previous_end);
      previous_end = hi;
      // Recompute the bucket from the raw rows it covers.
      size_t count = 0, accepted = 0, n = 0;
      double sum = 0, mn = 1e300, mx = -1e300;
      for (const auto& row : raw) {
        const int64_t t = row["utime"];
        if (t < lo || t > hi) continue;
        ++count;
        accepted += row["verdict"] == "accepted";
        const double v = row["bias_nT"][1];
        sum += v;
        mn = std::min(mn, v);
        mx = std::max(mx, v);
        ++n;
      }
      REQUIRE(b["count"] == count);
      REQUIRE(b["accepted"] == accepted);
      const auto& f = b["bias_y_nT"];
      REQUIRE(f["n"] == n);
      REQUIRE(f["min"].get<double>() == mn);
      REQUIRE(f["max"].get<double>() == mx);
      REQUIRE(f["mean"].get<double>() == Approx(sum / static_cast<double>(n)).epsilon(1e-12));
      REQUIRE(f["min"].get<double>() <= f["mean"].get<double>());
      REQUIRE(f["mean"].get<double>() <= f["max"].get<double>());
      total += count;
    }
    REQUIRE(total == raw.size());
  }
}

TEST_CASE("serve: a missing database or a taken port is one line on stderr and exit 2") {
  TempDir dir("magcal_serve_err");
  auto r = run_magcal("serve --db " + dir.file("absent.db") + " --listen 127.0.0.1:0", dir);
  REQUIRE(r.exit_code == 2);
  REQUIRE(r.err.find("magcal serve: cannot open the database") == 0);
  REQUIRE_FALSE(std::filesystem::exists(dir.file("absent.db")));
  r = run_magcal("serve --db " + magcal::test::replayed_day_db() + " --listen nowhere", dir);
  REQUIRE(r.exit_code == 2);
  REQUIRE(r.err.find("not ADDR:PORT") != std::string::npos);
}

TEST_CASE("serve over a replayed day: /metrics is what the database holds") {
  const std::string& db = magcal::test::replayed_day_db();
  TempDir dir("magcal_serve_metrics");
  ServeProcess serve(db, dir);
  const auto reply = http_get(serve.port(), "/metrics");
  REQUIRE(reply.status == 200);
  const auto p = magcal::test::parse_prometheus_text(reply.body);
  INFO(reply.body);
  REQUIRE(p.error.empty());
  // Counted here through the storage API (independent of the server's queries).
  namespace st = magcal::storage;
  st::OpenOptions ro;
  ro.read_only = true;
  st::Database d(db, ro);
  st::SqliteSampleWindowStore samples(d);
  st::SqliteCalibrationHistory history(d);
  // The window `magcal status` counts: 12 h (the default window_hours) up to the newest sample;
  // the database holds a little more until retention runs.
  const int64_t newest = *samples.newest_utime(kSat);
  const int64_t in_window =
      samples.count_in_window(kSat, newest - int64_t{12} * 3600 * 1'000'000 + 1, newest + 1);
  CHECK(in_window < samples.count(kSat));
  CHECK(p.value("magcal_window_samples", {{"sat", kSat}}) == in_window);
  CHECK_FALSE(p.has("magcal_samples_stored_total"));  // retention deletes: not a counter here
  st::HistoryQuery q;
  q.sat_id = kSat;
  q.method = "twostep";
  std::map<std::string, int> verdicts;
  for (const auto& r : history.query(q)) ++verdicts[r.verdict];
  // deploy/demo.sh's day: the early refits (1000, 1415, 2000, 2829 and 4000 samples stored),
  // 08:00, 14:00, 20:00.
  REQUIRE(verdicts["accepted"] == 8);
  CHECK(p.value("magcal_refits_total", {{"sat", kSat}, {"verdict", "accepted"}}) ==
        verdicts["accepted"]);
  const auto last_refit = history.latest_accepted_refit(kSat);
  REQUIRE(last_refit);
  CHECK(p.value("magcal_last_refit_success_timestamp_seconds", {{"sat", kSat}}) ==
        static_cast<double>(last_refit->utime) * 1e-6);
  const auto ukf = history.latest(kSat, "ukf");
  REQUIRE(ukf);
  CHECK(p.value("magcal_ukf_bias_nT", {{"sat", kSat}, {"axis", "y"}}) == ukf->bias_nT[1]);
  // prometheus-cpp writes 15 significant digits: equal to the stored double to that precision.
  CHECK(p.value("magcal_ukf_bias_sigma_nT", {{"sat", kSat}, {"axis", "y"}}) ==
        Approx(ukf->bias_sigma_nT[1]).epsilon(1e-14));
  CHECK(p.value("magcal_build_info", {{"version", MAGCAL_VERSION}}) == 1);
  CHECK_FALSE(p.has("magcal_samples_received_total"));  // only a running magcald knows
  CHECK(serve.stop() == 0);
}
