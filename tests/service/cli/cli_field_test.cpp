// `magcal field`, run as the real binary (popen): official IGRF-14 test values, geodetic
// input, --coefficients, and the error paths (one line on stderr, exit 1 usage / 2 data).
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>
#include "tests/test_skip.hpp"

namespace {

constexpr double kOfficialTolerance_nT = 0.01 + 1e-9;  // published to 0.01 nT

struct Run {
  int exit_code = -1;
  std::string out;  // stdout
  std::string err;  // stderr
};

Run run_magcal(const std::string& args) {
  const std::string err_path = std::filesystem::temp_directory_path() /
                               ("magcal_cli_field_test_" + std::to_string(::getpid()) + ".err");
  const std::string cmd = std::string(MAGCAL_BIN_DIR) + "/magcal " + args + " 2>" + err_path;
  Run r;
  FILE* p = ::popen(cmd.c_str(), "r");
  REQUIRE(p != nullptr);
  std::array<char, 4096> buf;
  size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int status = ::pclose(p);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream e(err_path);
  r.err.assign(std::istreambuf_iterator<char>(e), std::istreambuf_iterator<char>());
  std::filesystem::remove(err_path);
  return r;
}

int count_lines(const std::string& s) {
  int n = 0;
  for (char c : s) n += c == '\n';
  return n;
}

void require_one_line_error(const Run& r, int exit_code, const std::string& contains) {
  INFO("stdout: " << r.out << "\nstderr: " << r.err);
  CHECK(r.exit_code == exit_code);
  CHECK(r.out.empty());
  CHECK(count_lines(r.err) == 1);
  CHECK(r.err.find(contains) != std::string::npos);
}

}  // namespace

TEST_CASE("magcal field --json reproduces official IGRF-14 test values", "[cli][field]") {
  // pyIGRF tests_igrf14.py (shared/data/igrf14_official_testvalues.csv): X, Y, Z geocentric.
  struct Case {
    const char* args;
    double x, y, z;
  };
  const Case cases[] = {
      {"--time 2025-01-01T00:00:00Z --r-km 6375 --colat-deg 56 --lon-deg -3", 28927.56, 261.98,
       30910.08},
      {"--time 2010-01-01 --r-km 6371 --colat-deg 170 --lon-deg 0", 17529.48, -7143.78, -42722.46},
      {"--time 2030-01-01 --r-km 6375 --colat-deg 45 --lon-deg -5", 22959.82, 224.80, 40764.14},
  };
  for (const Case& c : cases) {
    const Run r = run_magcal(std::string("field ") + c.args + " --json");
    INFO(c.args << "\n" << r.err);
    REQUIRE(r.exit_code == 0);
    const auto j = nlohmann::json::parse(r.out);
    CHECK(std::abs(j.at("north_nT").get<double>() - c.x) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("east_nT").get<double>() - c.y) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("down_nT").get<double>() - c.z) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("btheta_nT").get<double>() + c.x) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("bphi_nT").get<double>() - c.y) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("br_nT").get<double>() + c.z) < kOfficialTolerance_nT);
    CHECK(std::abs(j.at("total_nT").get<double>() - std::sqrt(c.x * c.x + c.y * c.y + c.z * c.z)) <
          0.02);
    CHECK(j.at("model") == "IGRF-14");
  }
}

TEST_CASE("magcal field geodetic input", "[cli][field]") {
  // At the north pole, geodetic and geocentric NED coincide; the WGS-84 polar radius is
  // b = a (1 - f) = 6356.752314245 km.
  const Run geodetic =
      run_magcal("field --time 2024-06-01 --lat-deg 90 --lon-deg 10 --alt-km 0 --json");
  const Run geocentric =
      run_magcal("field --time 2024-06-01 --r-km 6356.752314245 --colat-deg 0 --lon-deg 10 --json");
  REQUIRE(geodetic.exit_code == 0);
  REQUIRE(geocentric.exit_code == 0);
  const auto a = nlohmann::json::parse(geodetic.out), b = nlohmann::json::parse(geocentric.out);
  for (const char* key : {"north_nT", "east_nT", "down_nT", "total_nT", "br_nT"})
    CHECK(std::abs(a.at(key).get<double>() - b.at(key).get<double>()) < 1e-3);
  CHECK(a.at("frame") == "geodetic");

  // Mid-latitudes: same total field, geodetic "down" tilted from geocentric by ~0.19 deg.
  const Run mid =
      run_magcal("field --time 2024-06-01 --lat-deg 45 --lon-deg 10 --alt-km 400 --json");
  REQUIRE(mid.exit_code == 0);
  const auto m = nlohmann::json::parse(mid.out);
  const double n = m.at("north_nT"), e = m.at("east_nT"), d = m.at("down_nT");
  CHECK(std::abs(std::sqrt(n * n + e * e + d * d) - m.at("total_nT").get<double>()) < 1e-6);
  CHECK(std::abs(d - (-m.at("br_nT").get<double>())) > 1.0);  // not the geocentric component

  // Human-readable output names the components.
  const Run table = run_magcal("field --time 2024-06-01 --lat-deg 45 --lon-deg 10 --alt-km 400");
  REQUIRE(table.exit_code == 0);
  CHECK(table.out.find("total") != std::string::npos);
  CHECK(table.out.find("IGRF-14") != std::string::npos);
}

TEST_CASE("magcal field --coefficients loads .txt and .shc files", "[cli][field]") {
  const std::string dir = MAGCAL_SHARED_DATA_DIR;
  if (!std::filesystem::exists(dir + "/IGRF14.shc")) {
    magcal::test::skip_or_fail("IGRF14.shc not found in " + dir);
    return;
  }
  const std::string where = " --time 2020-01-01 --r-km 6700 --colat-deg 15 --lon-deg 90 --json";
  const Run builtin = run_magcal("field" + where);
  const Run shc = run_magcal("field --coefficients " + dir + "/IGRF14.shc" + where);
  const Run txt = run_magcal("field --coefficients " + dir + "/igrf14coeffs.txt" + where);
  REQUIRE(builtin.exit_code == 0);
  REQUIRE(shc.exit_code == 0);
  REQUIRE(txt.exit_code == 0);
  const auto a = nlohmann::json::parse(builtin.out), b = nlohmann::json::parse(shc.out),
             c = nlohmann::json::parse(txt.out);
  for (const char* key : {"north_nT", "east_nT", "down_nT"}) {
    CHECK(std::abs(a.at(key).get<double>() - b.at(key).get<double>()) < 1e-8);
    CHECK(a.at(key).get<double>() == c.at(key).get<double>());
  }
  // Official value for this point (X 3734.07, Y 1294.17, Z 50833.13).
  CHECK(std::abs(b.at("down_nT").get<double>() - 50833.13) < kOfficialTolerance_nT);
}

TEST_CASE("magcal field errors: one line on stderr, exit 1 or 2", "[cli][field]") {
  const std::string where = " --r-km 6371.2 --colat-deg 45 --lon-deg 10";
  require_one_line_error(run_magcal("field --time 2031-01-01" + where), 2,
                         "outside IGRF-14's validity");
  require_one_line_error(run_magcal("field --time 1899-12-31T23:00:00Z" + where), 2, "validity");
  require_one_line_error(run_magcal("field --time yesterday" + where), 1, "cannot parse --time");
  require_one_line_error(run_magcal("field --time 2025-02-30" + where), 1, "cannot parse --time");
  require_one_line_error(run_magcal("field --time 2025-01-01 --r-km 6371 --lon-deg 1"), 1,
                         "--colat-deg");
  require_one_line_error(run_magcal("field --time 2025-01-01 --lon-deg 1"), 1, "either");
  require_one_line_error(
      run_magcal("field --time 2025-01-01 --r-km 6371 --colat-deg 190 --lon-deg 1"), 1,
      "--colat-deg");
  require_one_line_error(run_magcal("field --time 2025-01-01 --r-km -5 --colat-deg 10 --lon-deg 1"),
                         1, "--r-km");
  require_one_line_error(run_magcal("field --time 2025-01-01 --lat-deg 95 --alt-km 0 --lon-deg 1"),
                         1, "--lat-deg");
  require_one_line_error(
      run_magcal("field --time 2025-01-01 --r-km 6371 --colat-deg nan --lon-deg 1"), 1, "finite");
  // CLI11 itself: mixing geocentric and geodetic, missing --time.
  CHECK(run_magcal("field --time 2025-01-01 --r-km 6371 --lat-deg 3 --lon-deg 1").exit_code == 1);
  CHECK(run_magcal("field --r-km 6371 --colat-deg 3 --lon-deg 1").exit_code == 1);

  // Coefficient files: missing, and corrupt (the error names the line).
  require_one_line_error(
      run_magcal("field --time 2025-01-01 --coefficients /nonexistent/x.txt" + where), 2,
      "cannot open");
  const auto bad = std::filesystem::temp_directory_path() /
                   ("magcal_cli_field_bad_" + std::to_string(::getpid()) + ".txt");
  {
    std::ofstream f(bad);
    f << "# broken\nc/s deg ord IGRF SV\ng/h n m 2020.0 2020-25\ng 1 0 -29000 oops\n";
  }
  require_one_line_error(
      run_magcal("field --time 2021-01-01 --coefficients " + bad.string() + where), 2,
      "line 4: bad number 'oops'");
  {
    std::ofstream f(bad);
    f << "# degree-1 model 2020-2025\nc/s deg ord IGRF SV\ng/h n m 2020.0 2020-25\n"
         "g 1 0 -29000 10\ng 1 1 -1500 0\nh 1 1 4600 0\n";
  }
  // A valid custom file: its own validity applies (2020-2025), not IGRF-14's.
  CHECK(run_magcal("field --time 2021-01-01 --coefficients " + bad.string() + where).exit_code ==
        0);
  require_one_line_error(
      run_magcal("field --time 2026-01-01 --coefficients " + bad.string() + where), 2,
      "2020.0-2025.0");
  std::filesystem::remove(bad);
}
