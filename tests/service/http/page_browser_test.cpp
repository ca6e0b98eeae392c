// The page `/` in a real browser: headless Chromium (Debian `chromium`) loads it from `magcal
// serve` over a replayed day, with no network but the server. The page reports the number of
// points it drew and every console error in #magcal-test (data-plotted, data-errors); the test
// reads them from --dump-dom and checks a screenshot was written with content. Skips when
// chromium is absent (fails in CI, where deploy/setup-deps.sh --tests installs it).
// MAGCAL_SCREENSHOT_OUT=FILE.png keeps the screenshot (README's docs/screenshot-page.png).
#include <filesystem>
#include <regex>

#include <catch2/catch.hpp>

#include "storage/calibration_history.hpp"
#include "storage/database.hpp"
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

}  // namespace

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
    magcal::storage::CalibrationHistory history(d);
    auto rejected = history.latest_refit("PAPER-1");
    REQUIRE(rejected);
    rejected->utime += 3600LL * 1000000;
    rejected->window_end_utime = rejected->utime;
    rejected->bias_nT[1] += 40.0;
    rejected->status = 4;  // rejected by the gates
    rejected->verdict = "rejected";
    rejected->rejection_reasons = {"bias_change: y 40 nT, chi-square 800 > 16.3"};
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
  CHECK(dom.find("nT, rejected</div>") != std::string::npos);

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
