// Test support for the operations-server tests: a replayed day in a database (the real `magcal
// sim` + `magcald` binaries, built once per test process), `magcal serve` as a real process,
// and HTTP GET through cpp-httplib's client.
#pragma once

#include <signal.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <regex>
#include <string>

#include <httplib.h>
#include <catch2/catch.hpp>

#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

namespace magcal::test {

struct HttpResult {
  int status = -1;  // -1: no answer
  std::string body, content_type;
};

inline HttpResult http_get(int port, const std::string& path) {
  httplib::Client client("127.0.0.1", port);
  client.set_read_timeout(30, 0);
  HttpResult out;
  if (auto res = client.Get(path.c_str())) {
    out.status = res->status;
    out.body = res->body;
    out.content_type = res->get_header_value("Content-Type");
  }
  return out;
}

// The folder of the helpers below, with 24 h of the paper scenario (seed 1) as day.lcm.
inline const TempDir& simulated_day_dir() {
  static TempDir dir("magcal_http_day");
  static bool simulated = false;
  if (!simulated) {
    REQUIRE(run({std::string(MAGCAL_BIN_DIR) + "/magcal", "sim", "--scenario", "paper", "--hours",
                 "24", "--seed", "1", "--out", dir.file("day.lcm"), "--batch", "200"},
                dir.file("sim.log")) == 0);
    simulated = true;
  }
  return dir;
}

// The simulated day replayed through magcald into `name`.db with `config` (TOML text).
inline std::string replay_simulated_day(const std::string& name, const std::string& config) {
  const TempDir& dir = simulated_day_dir();
  {
    std::ofstream out(dir.file(name + ".toml"));
    out << config;
  }
  const std::string db = dir.file(name + ".db");
  REQUIRE(run({std::string(MAGCAL_BIN_DIR) + "/magcald", "--config", dir.file(name + ".toml"),
               "--db", db, "--lcm-url", "file://" + dir.file("day.lcm") + "?speed=0", "--log-level",
               "warn", "--http-listen", ""},
              dir.file(name + ".log"), 300) == 0);
  return db;
}

// The day replayed with refits on the data clock every 6 h (as deploy/demo.sh): ~1440 UKF
// snapshots and three refits of PAPER-1. Built once per process.
inline const std::string& replayed_day_db() {
  static const std::string db =
      replay_simulated_day("day", "[refit]\nclock = \"data\"\nevery_hours = 6\n");
  return db;
}

// The day replayed on the default wall clock: only the first refit runs (the day replays in
// seconds), so the UKF snapshots after it are judged without a newer one. Built once.
inline const std::string& wall_clock_day_db() {
  static const std::string db = replay_simulated_day("wall", "");
  return db;
}

// `magcal serve --db DB --listen 127.0.0.1:0` as a child process; port() from its first line.
class ServeProcess {
 public:
  ServeProcess(const std::string& db, const TempDir& dir) : log_(dir.file("serve.log")) {
    pid_ = spawn(
        {std::string(MAGCAL_BIN_DIR) + "/magcal", "serve", "--db", db, "--listen", "127.0.0.1:0"},
        log_);
    REQUIRE(pid_ > 0);
    const std::regex url("http://127\\.0\\.0\\.1:([0-9]+)/");
    REQUIRE(wait_until(
        [&] {
          std::smatch m;
          const std::string text = slurp(log_);
          if (!std::regex_search(text, m, url)) return false;
          port_ = std::stoi(m[1]);
          return true;
        },
        30));
  }
  ~ServeProcess() {
    if (pid_ > 0) stop();
  }
  int port() const { return port_; }
  // SIGTERM; returns the exit code (0 expected).
  int stop() {
    ::kill(pid_, SIGTERM);
    const int code = wait_exit(pid_, 30);
    pid_ = -1;
    return code;
  }
  std::string log() const { return slurp(log_); }

 private:
  std::string log_;
  pid_t pid_ = -1;
  int port_ = 0;
};

}  // namespace magcal::test
