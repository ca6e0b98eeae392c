// Issue 12 "Done when", live: magcald --http-listen fed by lcm-logplayer over udpm (loopback).
// /metrics parses as Prometheus text (an independent reader, tests/service/prometheus_text.hpp,
// and `promtool check metrics`) and magcal_samples_received_total summed over
// spacecraft equals the samples sent; /-/healthy and /-/ready answer 200; /-/healthy answers 503
// while another process holds the database's write lock (commits fail and are retried) and 200
// again once it is released, with every sample stored once. Also: a port that is taken stops
// magcald at start with exit code 2 and a clear message.
// No sleeps to wait for things: every wait polls its condition against a deadline.
#include <catch2/catch.hpp>

#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/service/prometheus_text.hpp"
#include "tests/test_skip.hpp"

namespace {

namespace fs = std::filesystem;
using namespace magcal::test;

const std::string kBin = MAGCAL_BIN_DIR;
constexpr int64_t kT0_utime = 1704081600000000;  // 2024-01-01T04:00:00Z

std::string live_url() {
  const int port = 7500 + static_cast<int>(::getpid() % 200);  // not the default bus
  return "udpm://239.255.76.67:" + std::to_string(port) + "?ttl=0";
}

PromText scrape(int port) {
  const auto reply = http_get(port, "/metrics");
  REQUIRE(reply.status == 200);
  auto p = parse_prometheus_text(reply.body);
  INFO(reply.body);
  REQUIRE(p.error.empty());
  return p;
}

// promtool's lint flags the contract's `_nT` names as camelCase (design.md pins them); every
// other finding, and any parse error, fails.
void check_with_promtool(const TempDir& tmp, const std::string& text) {
  {
    std::ofstream out(tmp.file("metrics.txt"));
    out << text;
  }
  const std::string cmd = "promtool check metrics < " + tmp.file("metrics.txt") + " > " +
                          tmp.file("promtool.out") + " 2>&1";
  const int status = ::system(cmd.c_str());
  const std::string out = slurp(tmp.file("promtool.out"));
  INFO(out);
  std::istringstream lines(out);
  std::string line;
  int findings = 0;
  while (std::getline(lines, line)) {
    if (line.empty()) continue;
    ++findings;
    const bool camel =
        line.find("_nT metric names should be written in 'snake_case'") != std::string::npos;
    CHECK(camel);
  }
  // Exit 0 (clean) or 3 (lint findings only, all of them the _nT names); 1 = parse error.
  CHECK((WEXITSTATUS(status) == 0 || (WEXITSTATUS(status) == 3 && findings > 0)));
}

// False (after the skip marker, or a failure in CI) when multicast does not work here.
bool multicast_or_skip(const std::string& url) {
  if (multicast_available(url)) return true;
  skip_or_fail("multicast over loopback unavailable here: live udpm test");
  return false;
}

// magcald live on `url` (database tmp/m.db, log tmp/magcald.log) with the server on any free
// loopback port; returns once /-/ready answers 200.
struct LiveDaemon {
  pid_t pid = -1;
  int port = -1;
};
LiveDaemon start_live(const TempDir& tmp, const std::string& url,
                      const std::vector<std::string>& extra_args = {}) {
  std::vector<std::string> args{kBin + "/magcald",
                                "--db",
                                tmp.file("m.db"),
                                "--lcm-url",
                                url + "&recv_buf_size=4194304",
                                "--http-listen",
                                "127.0.0.1:0"};
  args.insert(args.end(), extra_args.begin(), extra_args.end());
  LiveDaemon d;
  d.pid = spawn(args, tmp.file("magcald.log"));
  REQUIRE(d.pid > 0);
  d.port = wait_http_port(tmp.file("magcald.log"), 20);
  INFO(slurp(tmp.file("magcald.log")));
  REQUIRE(d.port > 0);
  REQUIRE(wait_until([&] { return http_get(d.port, "/-/ready").status == 200; }, 20));
  return d;
}

constexpr int kLiveSamples = 6000;  // 120 frames of 50, two spacecraft

// magcald live on `url` fed both spacecraft's logs by lcm-logplayer; returns once every sample is
// stored (or the deadline passed: the caller's counts then fail).
LiveDaemon start_live_and_replay(const TempDir& tmp, const std::string& url) {
  const std::string log = tmp.file("day.lcm");
  write_batch_log(log, "HTTP-A", kT0_utime, kLiveSamples / 2, 1000);
  write_batch_log(tmp.file("b.lcm"), "HTTP-B", kT0_utime, kLiveSamples / 2, 1000);
  const LiveDaemon d = start_live(tmp, url, {"--station", "gs-http"});
  CHECK(http_get(d.port, "/-/healthy").status == 200);
  REQUIRE(run({"lcm-logplayer", "-l", url, "-s", "0", log}, tmp.file("player.log")) == 0);
  REQUIRE(run({"lcm-logplayer", "-l", url, "-s", "0", tmp.file("b.lcm")}, tmp.file("player.log")) ==
          0);
  const bool all = wait_until(
      [&] { return scrape(d.port).sum("magcal_samples_stored_total") >= kLiveSamples; }, 30);
  CHECK(all);
  return d;
}

}  // namespace

TEST_CASE("live magcald --http-listen fed by lcm-logplayer: /metrics, healthy, ready",
          "[daemon][http][multicast]") {
  const std::string url = live_url();
  if (!multicast_or_skip(url)) return;
  TempDir tmp("magcald_http_live");
  constexpr int kSamples = kLiveSamples;
  const auto [d, port] = start_live_and_replay(tmp, url);
  const std::string text = http_get(port, "/metrics").body;
  const PromText p = parse_prometheus_text(text);
  REQUIRE(p.error.empty());

  CHECK(p.sum("magcal_samples_received_total") == kSamples);
  CHECK(p.value("magcal_samples_received_total", {{"sat", "HTTP-A"}}) == kSamples / 2);
  CHECK(p.value("magcal_samples_received_total", {{"sat", "HTTP-B"}}) == kSamples / 2);
  CHECK(p.value("magcal_samples_stored_total", {{"sat", "HTTP-B"}}) == kSamples / 2);
  CHECK(p.sum("magcal_samples_rejected_total") == 0);
  CHECK(p.sum("magcal_samples_missing_total") == 0);
  CHECK(p.value("magcal_queue_overflow_total") == 0);
  CHECK(p.value("magcal_storage_healthy") == 1);
  CHECK(p.value("magcal_build_info", {{"version", MAGCAL_VERSION}}) == 1);
  CHECK(p.value("magcal_station_info", {{"station", "gs-http"}}) == 1);
  CHECK(p.value("magcal_storage_commit_seconds_count") >= 1);
  CHECK(p.value("magcal_sqlite_commit_seconds_count") ==
        p.value("magcal_storage_commit_seconds_count"));
  // Every sample was in a UKF snapshot's period: the newest one per spacecraft is exposed.
  CHECK(p.value("magcal_ukf_bias_sigma_nT", {{"sat", "HTTP-A"}, {"axis", "z"}}).has_value());
  CHECK(http_get(port, "/-/healthy").status == 200);
  CHECK(http_get(port, "/-/ready").status == 200);

  ::kill(d, SIGTERM);
  CHECK(wait_exit(d, 30) == 0);
  // The server went down with the daemon.
  CHECK(http_get(port, "/-/healthy").status == -1);
}

// Its own test case: the tool is looked for before any assertion, so a missing promtool never
// turns a failure into a skip.
TEST_CASE("live magcald's /metrics passes promtool check metrics", "[daemon][http][multicast]") {
  if (::system("command -v promtool > /dev/null 2>&1") != 0) {
    skip_or_fail("promtool (Debian prometheus) not installed");
    return;
  }
  const std::string url = live_url();
  if (!multicast_or_skip(url)) return;
  TempDir tmp("magcald_http_promtool");
  const auto [d, port] = start_live_and_replay(tmp, url);
  check_with_promtool(tmp, http_get(port, "/metrics").body);
  ::kill(d, SIGTERM);
  CHECK(wait_exit(d, 30) == 0);
}

TEST_CASE("live magcald: /-/healthy is 503 while storage fails and is retried, 200 after",
          "[daemon][http][fault][multicast]") {
  const std::string url = live_url();
  if (!multicast_or_skip(url)) return;
  TempDir tmp("magcald_http_fault");
  const std::string log = tmp.file("day.lcm");
  const std::string db = tmp.file("m.db");
  constexpr int kSamples = 4000;                                 // 80 frames
  write_batch_log(log, "HTTP-F", kT0_utime, kSamples, 100'000);  // over 8 s at -s 1
  {
    std::ofstream cfg(tmp.file("d.toml"));
    cfg << "[storage]\nbusy_timeout_ms = 100\nmax_failure_s = 30\n";
  }
  const auto [d, port] = start_live(tmp, url, {"--config", tmp.file("d.toml")});
  const pid_t player = spawn({"lcm-logplayer", "-l", url, "-s", "1", log}, tmp.file("player.log"));
  REQUIRE(player > 0);
  REQUIRE(wait_until([&] { return scrape(port).sum("magcal_samples_stored_total") >= 200; }, 20));
  CHECK(http_get(port, "/-/healthy").status == 200);

  // Another process holds the write lock for 3 s (30x the busy timeout) while frames arrive.
  const pid_t locker = hold_write_lock(tmp.file("lock.sql"), tmp.file("lock.log"), db, 3);
  const bool went_503 = wait_until([&] { return http_get(port, "/-/healthy").status == 503; }, 3);
  CHECK(went_503);
  if (went_503) {
    const auto p = scrape(port);
    CHECK(p.value("magcal_storage_healthy") == 0);  // says the same
  }
  CHECK(http_get(port, "/-/ready").status == 200);  // still ready: only storage is failing
  REQUIRE(wait_exit(locker, 20) == 0);
  CHECK(wait_until([&] { return http_get(port, "/-/healthy").status == 200; }, 10));

  REQUIRE(wait_exit(player, 30) == 0);
  const bool all =
      wait_until([&] { return scrape(port).sum("magcal_samples_stored_total") >= kSamples; }, 30);
  CHECK(all);
  const auto p = scrape(port);
  CHECK(p.sum("magcal_samples_received_total") == kSamples);
  CHECK(p.sum("magcal_samples_stored_total") == kSamples);
  CHECK(p.sum("magcal_samples_rejected_total") == 0);
  CHECK(p.value("magcal_storage_healthy") == 1);
  // The failed attempts were timed too: at least one waited the busy timeout.
  const double slow = p.value("magcal_sqlite_commit_seconds_count").value_or(0) -
                      p.value("magcal_sqlite_commit_seconds_bucket", {{"le", "0.05"}}).value_or(0);
  CHECK(slow >= 1);
  CHECK(http_get(port, "/-/healthy").status == 200);
  ::kill(d, SIGTERM);
  CHECK(wait_exit(d, 30) == 0);
}

TEST_CASE("live magcald: a new spacecraft that sends one frame is stored while it runs",
          "[daemon][http][multicast]") {
  // One mag_batch_t of 3 samples: too few, and one frame, to corroborate its own time. Nothing
  // contradicts it either: it is stored within kFirstHoldMax_s (10 s), not held until shutdown.
  const std::string url = live_url();
  if (!multicast_or_skip(url)) return;
  TempDir tmp("magcald_http_lone");
  write_batch_log(tmp.file("lone.lcm"), "HTTP-LONE", kT0_utime, 3, 1000);
  const auto [d, port] = start_live(tmp, url);
  REQUIRE(run({"lcm-logplayer", "-l", url, "-s", "0", tmp.file("lone.lcm")},
              tmp.file("player.log")) == 0);
  REQUIRE(wait_until([&] { return scrape(port).sum("magcal_samples_received_total") >= 3; }, 10));
  const auto received = Clock::now();
  const bool stored = wait_until(
      [&] {
        return scrape(port).value("magcal_samples_stored_total", {{"sat", "HTTP-LONE"}}) == 3;
      },
      20);
  const double after_s = std::chrono::duration<double>(Clock::now() - received).count();
  INFO(slurp(tmp.file("magcald.log")));
  CHECK(stored);
  CHECK(after_s < 15.0);
  CHECK(scrape(port).sum("magcal_samples_rejected_total") == 0);
  ::kill(d, SIGTERM);
  CHECK(wait_exit(d, 30) == 0);
  std::printf("single-frame spacecraft: stored %.1f s after it was received\n", after_s);
}

TEST_CASE("a listen port that is taken stops magcald at start: exit 2, a clear message",
          "[daemon][http]") {
  TempDir tmp("magcald_http_taken");
  write_batch_log(tmp.file("day.lcm"), "HTTP-T", kT0_utime, 100, 1000);
  const std::string replay = "file://" + tmp.file("day.lcm") + "?speed=0";
  // A first magcald holds a port (a live one stays up until SIGTERM).
  const std::string url = live_url();
  const pid_t first = spawn({kBin + "/magcald", "--db", tmp.file("a.db"), "--lcm-url", url,
                             "--http-listen", "127.0.0.1:0"},
                            tmp.file("a.log"));
  REQUIRE(first > 0);
  const int port = wait_http_port(tmp.file("a.log"), 20);
  INFO(slurp(tmp.file("a.log")));
  REQUIRE(port > 0);
  const int rc = run({kBin + "/magcald", "--db", tmp.file("b.db"), "--lcm-url", replay,
                      "--http-listen", "127.0.0.1:" + std::to_string(port)},
                     tmp.file("b.log"), 30);
  const std::string out = slurp(tmp.file("b.log"));
  INFO(out);
  CHECK(rc == 2);
  CHECK_THAT(out, Catch::Contains("--http-listen 127.0.0.1:" + std::to_string(port)));
  // The port is checked before the database is created: no empty file is left behind.
  CHECK_FALSE(fs::exists(tmp.file("b.db")));
  // A bad value is a usage error (exit 1) naming the flag.
  CHECK(run({kBin + "/magcald", "--db", tmp.file("c.db"), "--lcm-url", replay, "--http-listen",
             "9780"},
            tmp.file("c.log"), 30) == 1);
  CHECK_THAT(slurp(tmp.file("c.log")), Catch::Contains("--http-listen: expected"));
  // "" is off: the replay runs without a server.
  CHECK(run({kBin + "/magcald", "--db", tmp.file("d.db"), "--lcm-url", replay, "--http-listen", ""},
            tmp.file("d.log"), 30) == 0);
  CHECK_THAT(slurp(tmp.file("d.log")), !Catch::Contains("operations server:"));
  // An existing database is not touched by a start that fails on the port.
  const std::string before = slurp(tmp.file("d.db"));
  REQUIRE(before.size() > 0);
  const auto mtime = fs::last_write_time(tmp.file("d.db"));
  CHECK(run({kBin + "/magcald", "--db", tmp.file("d.db"), "--lcm-url", replay, "--http-listen",
             "127.0.0.1:" + std::to_string(port)},
            tmp.file("e.log"), 30) == 2);
  CHECK(slurp(tmp.file("d.db")) == before);
  CHECK(fs::last_write_time(tmp.file("d.db")) == mtime);
  CHECK_FALSE(fs::exists(tmp.file("d.db-wal")));
  CHECK_FALSE(fs::exists(tmp.file("d.db-shm")));
  ::kill(first, SIGTERM);
  CHECK(wait_exit(first, 30) == 0);
}
