// magcald's start-up messages (magcald_main.cpp, Daemon::open), run as the real binary: a
// refused start prints one line on stderr that blames the flag or key at fault and names the
// cause, points nowhere outside the repository, and leaves no database behind; a live start's
// log names the LCM URL it listens on.
#include <signal.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>

#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

using magcal::test::run;
using magcal::test::slurp;
using magcal::test::TempDir;

namespace {

const std::string kMagcald = std::string(MAGCAL_BIN_DIR) + "/magcald";

struct Refusal {
  int exit_code = -1;
  std::string text;  // stdout and stderr
};

// magcald with `args` (a fresh --db in `dir`, the operations server off unless given).
Refusal start(const TempDir& dir, std::vector<std::string> args) {
  args.insert(args.begin(), {kMagcald, "--db", dir.file("never.db")});
  if (std::find(args.begin(), args.end(), "--http-listen") == args.end()) {
    args.insert(args.end(), {"--http-listen", ""});
  }
  static int n = 0;
  const std::string log = dir.file("magcald." + std::to_string(n++) + ".log");
  Refusal r;
  r.exit_code = run(args, log, 30);
  r.text = slurp(log);
  return r;
}

void check_one_line(const Refusal& r, const TempDir& dir) {
  INFO(r.text);
  CHECK(std::count(r.text.begin(), r.text.end(), '\n') == 1);
  CHECK(r.text.rfind("magcald: ", 0) == 0);
  CHECK(r.text.find(".md") == std::string::npos);  // no pointer to a document elsewhere
  CHECK_FALSE(std::filesystem::exists(dir.file("never.db")));
}

}  // namespace

TEST_CASE("a bad flag value is blamed on that flag alone") {
  TempDir dir("magcald_main_flags");
  // --http-listen given and valid, --log-level bad: only --log-level is named.
  Refusal r = start(dir, {"--log-level", "loud"});
  CHECK(r.exit_code == 1);
  check_one_line(r, dir);
  CHECK_THAT(r.text,
             Catch::Contains("--log-level: expected trace|debug|info|warn|error|critical|off, "
                             "got \"loud\""));
  CHECK_THAT(r.text, !Catch::Contains("--http-listen"));
  // And the other way round.
  r = start(dir, {"--log-level", "warn", "--http-listen", "9780"});
  CHECK(r.exit_code == 1);
  check_one_line(r, dir);
  CHECK_THAT(r.text, Catch::Contains("--http-listen: expected \"ADDR:PORT\""));
  CHECK_THAT(r.text, !Catch::Contains("--log-level"));
  // A station id that is no label: refused before anything is opened, blamed on --station.
  r = start(dir, {"--station", "ground station"});
  CHECK(r.exit_code == 1);
  check_one_line(r, dir);
  CHECK_THAT(r.text, Catch::Contains("--station: must be 1-64 printable ASCII characters"));
}

TEST_CASE("a mistyped database URI is a bad value (exit 1), blamed on --db or the key") {
  TempDir dir("magcald_main_db_uri");
  int n = 0;
  for (const std::string scheme : {"postgres ql://", "postgress://"}) {
    const std::string db = scheme + "magcal@127.0.0.1/m";
    const std::string flag_log = dir.file("flag" + std::to_string(n) + ".log");
    const std::string key_log = dir.file("key" + std::to_string(n++) + ".log");
    Refusal r;
    r.exit_code = run({kMagcald, "--db", db, "--http-listen", ""}, flag_log, 30);
    r.text = slurp(flag_log);
    INFO(r.text);
    CHECK(r.exit_code == 1);
    CHECK(std::count(r.text.begin(), r.text.end(), '\n') == 1);
    CHECK_THAT(r.text, Catch::Contains("magcald: --db: unknown database URI scheme '" + scheme));
    // The same from the config file.
    std::ofstream(dir.file("uri.toml")) << "[storage]\ndb_path = \"" << db << "\"\n";
    r.exit_code =
        run({kMagcald, "--config", dir.file("uri.toml"), "--http-listen", ""}, key_log, 30);
    r.text = slurp(key_log);
    CHECK(r.exit_code == 1);
    CHECK_THAT(r.text,
               Catch::Contains("[storage] db_path: unknown database URI scheme '" + scheme));
  }
}

TEST_CASE("an LCM URL that cannot be opened: one line of ours with LCM's reason, nothing else") {
  TempDir dir("magcald_main_lcm");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"bogus://x", "LCM provider \"bogus\" not found"},
      {"udpm://300.1.1.1:7667", "Bad multicast IP address \"300.1.1.1\""},
      {"udpm://239.255.76.67:99999", "Bad multicast port \"99999\""},
      {"nonsense", "invalid URL [nonsense]"},
      {"file://" + dir.file("none.lcm"), dir.file("none.lcm") + ": No such file or directory"},
  };
  for (const auto& [url, reason] : cases) {
    const Refusal r = start(dir, {"--lcm-url", url});
    INFO(url);
    CHECK(r.exit_code == 2);
    check_one_line(r, dir);
    CHECK_THAT(r.text, Catch::Contains("--lcm-url '" + url + "': cannot open LCM URL: " + reason));
    CHECK_THAT(r.text, !Catch::Contains("Error:"));  // LCM's own line is not printed
  }
  // Set in the config file instead, the key is named.
  {
    std::ofstream config(dir.file("bad-url.toml"));
    config << "[lcm]\nurl = \"bogus://x\"\n";
  }
  const Refusal r = start(dir, {"--config", dir.file("bad-url.toml")});
  CHECK(r.exit_code == 2);
  check_one_line(r, dir);
  CHECK_THAT(r.text, Catch::Contains("[lcm] url 'bogus://x': cannot open LCM URL: LCM provider"));
}

TEST_CASE("the start log names the LCM URL a live daemon listens on, also when it is the default") {
  TempDir dir("magcald_main_url");
  // (environment for `env`, what the "up" line says after "lcm ")
  const std::vector<std::pair<std::vector<std::string>, std::string>> cases = {
      {{"LCM_DEFAULT_URL=memq://"}, "lcm 'memq://' (LCM_DEFAULT_URL) (live)"},
      {{"-u", "LCM_DEFAULT_URL"}, "lcm default 'udpm://239.255.76.67:7667?ttl=0' (live)"},
  };
  for (const auto& [env, said] : cases) {
    INFO(said);
    if (env.front() == "-u" && !magcal::test::multicast_available("")) {
      WARN("LCM's default (UDP multicast) cannot open here: case left out");
      continue;
    }
    std::vector<std::string> args = {"env"};
    args.insert(args.end(), env.begin(), env.end());
    args.insert(args.end(), {kMagcald, "--db", dir.file("live.db"), "--http-listen", ""});
    const std::string log = dir.file(env.front() == "-u" ? "default.log" : "env.log");
    const pid_t pid = magcal::test::spawn(args, log);
    REQUIRE(pid > 0);
    const bool up =
        magcal::test::wait_until([&] { return slurp(log).find(" up: ") != std::string::npos; }, 30);
    ::kill(pid, SIGTERM);
    CHECK(magcal::test::wait_exit(pid, 30) == 0);
    const std::string text = slurp(log);
    INFO(text);
    REQUIRE(up);
    CHECK_THAT(text, Catch::Contains(said));
    CHECK_THAT(text, !Catch::Contains("lcm ''"));
  }
}
