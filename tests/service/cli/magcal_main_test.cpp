// `magcal`'s command line (magcal_main.cpp), run as the real binary: a bad numeric option of
// any subcommand is one clear sentence on stderr with the usage exit code, never CLI11's raw
// range text ("Value 0 not in range 0.000000 to 1797693134862315708...") or "Could not
// convert", and a negative seed is refused instead of wrapping to 2^64 - 1.
#include <algorithm>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>

#include "pipeline/scenario.hpp"
#include "service/io/exit_codes.hpp"
#include "tests/service/cli_test_support.hpp"

using magcal::test::Run;
using magcal::test::run_magcal;
using magcal::test::TempDir;

TEST_CASE("numeric options of every subcommand: one clear sentence, usage exit code") {
  TempDir dir("magcal_main");
  const std::string db = dir.file("none.db");
  const std::string csv = dir.file("none.csv");
  const std::string field = "field --time 2020-01-01T00:00:00Z ";
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"history --db " + db + " --sat A --limit 0",
       "magcal history: --limit must be at least 1 (got 0)"},
      {"history --db " + db + " --sat A --limit -1", "--limit must be at least 1 (got -1)"},
      {"history --db " + db + " --limit 2",
       "magcal history: --sat is required (see magcal history --help)"},
      {"history --db " + db + " --sat A --limit abc", "--limit must be a whole number (got 'abc')"},
      {"history --db " + db + " --sat A --limit 99999999999",
       "--limit must be at most 2147483647 (got 99999999999)"},
      {"evaluate --runs 0", "--runs must be at least 1 (got 0)"},
      {"evaluate --runs 1.5", "--runs must be a whole number (got '1.5')"},
      {"evaluate --seed -1", "--seed must be a whole number from 0 to 18446744073709551615"},
      {"sim --out " + csv + " --seed -1", "--seed must be a whole number from 0"},
      {"sim --out " + csv + " --hours abc", "--hours must be a finite number (got 'abc')"},
      {"sim --out " + csv + " --hours nan", "--hours must be a finite number (got 'nan')"},
      {"sim --out " + csv + " --batch x", "--batch must be a whole number (got 'x')"},
      {"fit --input " + csv + " --sigma-nT abc", "--sigma-nT must be a finite number"},
      {"fit --input " + csv + " --skip-first -1", "--skip-first must be at least 0 (got -1)"},
      {"fit --input " + csv + " --time-offset-s 1s", "--time-offset-s must be a finite number"},
      {"fit --input " + csv + " --alt-km inf", "--alt-km must be a finite number"},
      {"fit --input " + csv + " --gimbal-lock-margin-deg 50",
       "magcal fit: --gimbal-lock-margin-deg must be from 0 to 45 (got 50)"},
      {"fit --input " + csv + " --gimbal-lock-margin-deg -0.5",
       "--gimbal-lock-margin-deg must be from 0 to 45 (got -0.5)"},
      {"fit --input " + csv + " --expected-residual-nT x",
       "--expected-residual-nT must be a finite number"},
      {"fit --input " + csv + " --expected-residual-nT -5",
       "--expected-residual-nT must be positive"},
      {field + "--r-km abc --colat-deg 1 --lon-deg 2", "--r-km must be a finite number"},
      {field + "--r-km 7000 --colat-deg x --lon-deg 2", "--colat-deg must be a finite number"},
      {field + "--lat-deg x --alt-km 1 --lon-deg 2", "--lat-deg must be a finite number"},
      {field + "--lat-deg 1 --alt-km x --lon-deg 2", "--alt-km must be a finite number"},
      {field + "--r-km 7000 --colat-deg 1 --lon-deg e", "--lon-deg must be a finite number"},
  };
  for (const auto& [args, message] : cases) {
    const Run r = run_magcal(args, dir);
    INFO(args << "\nstdout: " << r.out << "\nstderr: " << r.err);
    CHECK(r.exit_code == magcal::kExitUsage);
    CHECK(r.out.empty());
    CHECK(std::count(r.err.begin(), r.err.end(), '\n') == 1);
    CHECK(r.err.find(message) != std::string::npos);
    CHECK(r.err.find("not in range") == std::string::npos);
    CHECK(r.err.find("Could not convert") == std::string::npos);
  }
  CHECK_FALSE(std::filesystem::exists(csv));  // nothing written by a refused sim
}

TEST_CASE("a mistyped --db URI scheme is a bad argument: usage exit code, every subcommand") {
  TempDir dir("magcal_main_db");
  for (const std::string command : {"status", "history --sat A", "refit --sat A", "serve"}) {
    const Run r = run_magcal(command + " --db postgress://magcal@127.0.0.1/m", dir);
    INFO(command << "\nstderr: " << r.err);
    CHECK(r.exit_code == magcal::kExitUsage);
    CHECK(std::count(r.err.begin(), r.err.end(), '\n') == 1);
    CHECK(r.err.find("--db unknown database URI scheme 'postgress://'") != std::string::npos);
  }
}

TEST_CASE("numeric options: good values still reach the subcommands") {
  TempDir dir("magcal_main_ok");
  const std::string csv = dir.file("s.csv");
  const Run sim = run_magcal("sim --hours 0.5 --seed +7 --out " + csv, dir);
  INFO(sim.err);
  CHECK(sim.exit_code == 0);
  CHECK(sim.err.find("seed 7") != std::string::npos);
  const Run field = run_magcal(
      "field --time 2020-01-01T00:00:00Z --r-km 6.9e3 --colat-deg +1.5e1 --lon-deg 20 --json", dir);
  INFO(field.err);
  CHECK(field.exit_code == 0);
  CHECK(field.out.find("total_nT") != std::string::npos);
}

TEST_CASE("an unknown subcommand is named, with the ones there are") {
  TempDir dir("magcal_main_unknown");
  const Run r = run_magcal("bogus --db x.db", dir);
  INFO(r.err);
  CHECK(r.exit_code == magcal::kExitUsage);
  CHECK(r.out.empty());
  CHECK(r.err ==
        "magcal: unknown subcommand 'bogus' (subcommands: field, sim, fit, evaluate, refit, "
        "history, export, compare, status, serve)\n");
}

TEST_CASE("sim: --help lists every preset, an empty --sat-id is refused and nothing written") {
  TempDir dir("magcal_main_sim");
  const Run help = run_magcal("sim --help", dir);
  CHECK(help.exit_code == 0);
  for (const auto& name : magcal::scenario_preset_names()) {
    INFO(help.out);
    CHECK(help.out.find(name) != std::string::npos);
  }
  const std::string out = dir.file("s.csv");
  const Run r = run_magcal("sim --hours 0.1 --out " + out + " --sat-id \"\"", dir);
  INFO(r.err);
  CHECK(r.exit_code == magcal::kExitUsage);
  CHECK(r.err == "magcal sim: --sat-id must be 1..64 characters (got \"\")\n");
  CHECK_FALSE(std::filesystem::exists(out));
}
