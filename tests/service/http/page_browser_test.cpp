// The page `/` in a real browser: headless Chromium (Debian `chromium`) loads it from `magcal
// serve` over a replayed day, with no network but the server. The page reports the number of
// points it drew and every console error in #magcal-test (data-plotted, data-errors); the test
// reads them from --dump-dom and checks a screenshot was written with content. Skips when
// chromium is absent (fails in CI, where deploy/setup-deps.sh --tests installs it).
// MAGCAL_SCREENSHOT_OUT=FILE.png keeps the screenshot (README's docs/screenshot-page.png).
// What each chart shows is checked from #magcal-drawn (the page reads it back from Chart.js)
// against the API's own buckets.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <regex>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "storage/calibration_history.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/test_skip.hpp"

using magcal::test::ServeProcess;
using magcal::test::TempDir;

namespace {

std::string find_chromium() {
  for (const char* path : {"/usr/bin/chromium", "/usr/bin/chromium-browser"}) {
    if (std::filesystem::exists(path)) return path;
  }
  return "";
}

// Each run gets its own profile: a second Chromium on the same one hands over to the first.
std::vector<std::string> chromium_args(const std::string& exe, const std::string& profile) {
  return {exe, "--headless",
          "--no-sandbox",  // CI runs as root
          "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
          "--disable-component-update", "--disable-sync", "--hide-scrollbars",
          "--user-data-dir=" + profile, "--window-size=1400,1000", "--virtual-time-budget=5000",
          // Without it Chromium 156 often hangs on --screenshot under a virtual-time budget.
          "--run-all-compositor-stages-before-draw"};
}

// The page at `url` after its scripts ran (--dump-dom), with a profile of its own.
std::string page_dom(const std::string& chromium, const TempDir& dir, const std::string& url,
                     const std::string& name) {
  auto args = chromium_args(chromium, dir.file("profile-" + name));
  args.push_back("--dump-dom");
  args.push_back(url);
  const std::string dom_file = dir.file(name + ".html");
  REQUIRE(magcal::test::run(args, dom_file, 120) == 0);
  return magcal::test::slurp(dom_file);
}

// What the page says each chart shows (#magcal-drawn: read back from Chart.js).
nlohmann::json drawn_charts(const std::string& dom) {
  const std::string open = "<script type=\"application/json\" id=\"magcal-drawn\">";
  const size_t begin = dom.find(open);
  INFO(dom.substr(0, 3000));
  REQUIRE(begin != std::string::npos);
  const size_t end = dom.find("</script>", begin);
  REQUIRE(end != std::string::npos);
  return nlohmann::json::parse(dom.substr(begin + open.size(), end - begin - open.size()));
}

bool near(double a, double b) {
  return std::abs(a - b) <= 1e-9 * std::max({1.0, std::abs(a), std::abs(b)});
}

// A point of `chart` at time x_ms standing for `value`, in a dataset whose label says it is not
// an accepted estimate ("rejected", "off scale"); the label, or "" when there is none.
std::string rejected_point_label(const nlohmann::json& chart, double x_ms, double value) {
  for (const auto& ds : chart["datasets"]) {
    const std::string label = ds["label"];
    if (label.find("rejected") == std::string::npos && label.find("off scale") == std::string::npos)
      continue;
    for (const auto& p : ds["points"]) {
      if (near(p[0].get<double>(), x_ms) && near(p[2].get<double>(), value)) return label;
    }
  }
  return "";
}

}  // namespace

TEST_CASE(
    "a day where nothing after the first refit is accepted: every estimate on the axis or "
    "an explicit, counted off-scale marker, rejected ones on every panel") {
  const std::string chromium = find_chromium();
  if (chromium.empty()) {
    magcal::test::skip_or_fail("chromium not installed (deploy/setup-deps.sh --tests)");
    return;
  }
  TempDir dir("magcal_page_wall");
  ServeProcess serve(magcal::test::wall_clock_day_db(), dir);
  const int port = serve.port();
  // The same UKF buckets as the page asks for, and the refits.
  const auto hist = nlohmann::json::parse(
      magcal::test::http_get(port, "/api/v1/history?sat=PAPER-1&method=ukf&points=600").body);
  const auto refits = nlohmann::json::parse(
      magcal::test::http_get(port, "/api/v1/history?sat=PAPER-1&method=twostep").body);
  REQUIRE(hist["series"].size() == 1);
  const auto& buckets = hist["series"][0]["buckets"];
  // The day is what this test is about: one accepted refit, and after it (almost) only
  // rejected UKF snapshots, on both sides of the accepted track.
  REQUIRE(refits.size() >= 1);
  REQUIRE(refits[0]["verdict"] == "accepted");
  const int64_t first_refit_utime = refits[0]["utime"];
  int accepted_after = 0, rejected_after = 0;
  for (const auto& b : buckets) {
    if (b["start_utime"].get<int64_t>() <= first_refit_utime) continue;
    (b["rejected"].get<int>() > 0 ? rejected_after : accepted_after) += 1;
  }
  std::printf(
      "wall-clock day: %zu UKF buckets, after the first refit %d with rejected snapshots, "
      "%d without\n",
      buckets.size(), rejected_after, accepted_after);
  REQUIRE(rejected_after > 100);

  const auto charts = drawn_charts(
      page_dom(chromium, dir, "http://127.0.0.1:" + std::to_string(port) + "/", "dom"));
  REQUIRE(charts.size() == 6);
  // Every drawn point: on the axis at its own value, or an off-scale marker on the edge it
  // passed, and the legend counts the markers.
  for (const auto& [id, chart] : charts.items()) {
    const double min = chart["min"], max = chart["max"];
    int pinned = 0, off_scale = 0;
    for (const auto& ds : chart["datasets"]) {
      const bool marker = ds["label"].get<std::string>().find("off scale") != std::string::npos;
      for (const auto& p : ds["points"]) {
        const double y = p[1], value = p[2];
        if (marker) {
          ++off_scale;
          CHECK((value > max || value < min));
          CHECK((y == (value > max ? max : min)));
        } else if (!(y == value && value >= min && value <= max)) {
          ++pinned;
        }
      }
      if (marker) {
        const std::string count = std::to_string(ds["points"].size()) + " off scale";
        CHECK(std::find(chart["legend"].begin(), chart["legend"].end(), count) !=
              chart["legend"].end());
      }
    }
    std::printf("%s: axis %.6g .. %.6g, %d off-scale markers\n", id.c_str(), min, max, off_scale);
    INFO(id << ": points drawn away from their value without an off-scale marker");
    CHECK(pinned == 0);
  }
  // Every bucket holding rejected or not-converged snapshots is drawn as such on every panel:
  // bias (3), each D entry, residual rms, samples.
  const std::vector<std::pair<std::string, std::string>> fields = {
      {"bias0", "bias_x_nT"}, {"bias1", "bias_y_nT"},    {"bias2", "bias_z_nT"}, {"dmat", "D11"},
      {"dmat", "D22"},        {"dmat", "D33"},           {"dmat", "D12"},        {"dmat", "D13"},
      {"dmat", "D23"},        {"rms", "residual_rms_nT"}};
  int missing = 0, checked = 0;
  for (const auto& b : buckets) {
    if (b["rejected"].get<int>() == 0) continue;
    const double x_ms =
        static_cast<double>(b["start_utime"].get<int64_t>() + b["end_utime"].get<int64_t>()) / 2 /
        1000;
    auto expect = [&](const std::string& chart, const std::string& field, double value) {
      ++checked;
      if (rejected_point_label(charts[chart], x_ms, value).empty()) {
        if (++missing <= 5) UNSCOPED_INFO(chart << " " << field << " at " << x_ms << ": " << value);
      }
    };
    for (const auto& [chart, field] : fields) {
      const double scale = chart == "dmat" ? 1e3 : 1.0;
      expect(chart, field, scale * b[field]["mean"].get<double>());
    }
    expect("count", "n_samples", b["n_samples"]["max"].get<double>());
  }
  std::printf("rejected UKF estimates drawn as rejected: %d of %d\n", checked - missing, checked);
  CHECK(missing == 0);
  REQUIRE(serve.stop() == 0);
}

TEST_CASE("the page draws the replayed day in headless Chromium without console errors") {
  const std::string chromium = find_chromium();
  if (chromium.empty()) {
    magcal::test::skip_or_fail("chromium not installed (deploy/setup-deps.sh --tests)");
    return;
  }
  TempDir dir("magcal_page");
  // The replayed day plus one rejected refit, newest of all (the summary shows it): every panel
  // must mark it as rejected.
  const std::string db = dir.file("day.db");
  std::filesystem::copy_file(magcal::test::replayed_day_db(), db);
  {
    magcal::storage::Database d(db);
    magcal::storage::SqliteCalibrationHistory history(d);
    auto rejected = history.latest_refit("PAPER-1");
    REQUIRE(rejected);
    rejected->utime += 3600LL * 1000000;
    rejected->window_end_utime = rejected->utime;
    rejected->bias_nT[1] += 40.0;
    rejected->status = 4;  // rejected by the gates
    rejected->verdict = "rejected";
    rejected->rejection_reasons = {"bias_change: y 40 nT, chi-square 800 > 16.3"};
    // With a bias temperature model: the summary says its bias is at T0 and gives k_T.
    rejected->has_temperature_model = 1;
    rejected->reference_temperature_C = 21.5;
    rejected->temperature_coefficient_nT_per_C = {1.25, -0.5, 2.0};
    rejected->temperature_coefficient_cov = {0.0004, 0.0, 0.0, 0.0009, 0.0, 0.0016};
    history.append(*rejected);
  }
  ServeProcess serve(db, dir);
  const std::string url = "http://127.0.0.1:" + std::to_string(serve.port()) + "/";

  auto args = chromium_args(chromium, dir.file("profile-dom"));
  args.push_back("--dump-dom");
  args.push_back(url);
  const std::string dom_file = dir.file("dom.html");
  REQUIRE(magcal::test::run(args, dom_file, 120) == 0);
  const std::string dom = magcal::test::slurp(dom_file);
  std::smatch m;
  const std::regex marker(
      "<div id=\"magcal-test\" data-plotted=\"([0-9]+)\" data-errors=\"([0-9]+)\" "
      "data-rejected=\"([^\"]*)\"[^>]*>([^<]*)<");
  INFO(dom.substr(0, 4000));
  REQUIRE(std::regex_search(dom, m, marker));
  const int plotted = std::stoi(m[1]);
  const int errors = std::stoi(m[2]);
  INFO("console errors: " << m[4]);
  REQUIRE(errors == 0);
  // A day of UKF snapshots (<= 600 buckets) on the bias, D, rms and count panels, plus refits.
  REQUIRE(plotted > 2000);
  // The page filled in the spacecraft picker and the summary from /api/v1/spacecraft.
  REQUIRE(dom.find("<option value=\"PAPER-1\">PAPER-1</option>") != std::string::npos);
  // The rejected refit is drawn as rejected on the three bias panels and for each of the six D
  // entries; the summary says "rejected" once.
  const std::string rejected_drawn = m[3];
  INFO("rejected refit points per chart: " << rejected_drawn);
  CHECK(rejected_drawn.find("bias0:1 bias1:1 bias2:1 dmat:6") != std::string::npos);
  CHECK(dom.find("rejected, rejected") == std::string::npos);
  CHECK(dom.find("bias at T0 = 21.5 \u00b0C, k_T [1.250 \u00b1 0.020, -0.500 \u00b1 0.030, "
                 "2.000 \u00b1 0.040] nT/\u00b0C), rejected</div>") != std::string::npos);
  // The newest refit's alignment, the paper's (1, 2, 1) deg mounting (with the sensor's internal
  // misalignment, 0.3 deg), each angle with its sigma; far from gimbal lock.
  for (const auto& [angle, truth_deg] : {std::pair{"roll", 1.0}, {"pitch", 2.0}, {"yaw", 1.0}}) {
    std::smatch cell;
    INFO(angle);
    REQUIRE(std::regex_search(dom, cell,
                              std::regex(std::string("<td id=\"alignment-") + angle +
                                         "\">(-?[0-9.]+) \u00b1 ([0-9.e+-]+)</td>")));
    CHECK(std::abs(std::stod(cell[1]) - truth_deg) < 0.5);
    CHECK(std::stod(cell[2]) > 0.0);
  }
  CHECK(dom.find("<td id=\"alignment-singular\">no</td>") != std::string::npos);

  args = chromium_args(chromium, dir.file("profile-screenshot"));
  const std::string png = dir.file("page.png");
  args.push_back("--screenshot=" + png);
  args.push_back(url);
  REQUIRE(magcal::test::run(args, dir.file("screenshot.log"), 120) == 0);
  REQUIRE(std::filesystem::exists(png));
  // A blank 1400x1000 page compresses to a few kB; six drawn charts are far larger.
  REQUIRE(std::filesystem::file_size(png) > 60'000);
  if (const char* keep = std::getenv("MAGCAL_SCREENSHOT_OUT")) {
    std::filesystem::copy_file(png, keep, std::filesystem::copy_options::overwrite_existing);
  }
  REQUIRE(serve.stop() == 0);
}
