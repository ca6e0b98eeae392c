// magcald as systemd runs it with Type=notify and WatchdogSec= (deploy/magcald.service): the
// real process, its $NOTIFY_SOCKET bound by this test. READY=1 comes once the database is open
// and the LCM subscription is live, WATCHDOG=1 keeps coming from the worker loop within the
// watchdog interval, STOPPING=1 when the drain starts, and nothing after it but status.
#include <catch2/catch.hpp>

#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "tests/service/daemon/notify_socket.hpp"
#include "tests/service/daemon_test_support.hpp"

namespace {

namespace fs = std::filesystem;
using namespace magcal::test;

const std::string kBin = MAGCAL_BIN_DIR;

struct Message {
  std::string text;
  double t_s;      // since the spawn
  bool db_exists;  // the database file existed when it arrived
};

}  // namespace

TEST_CASE("magcald speaks sd_notify: READY once open, WATCHDOG within the interval, STOPPING",
          "[daemon][integration][systemd]") {
  const fs::path dir = fs::temp_directory_path() / ("magcald_notify_" + std::to_string(getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  const std::string log = (dir / "day.lcm").string();
  const std::string db = (dir / "magcal.db").string();
  // 2 h of the paper scenario in 4 frames, replayed at 1000x: ~7.2 s of wall time.
  REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "2", "--seed", "3",
               "--out", log, "--batch", "200"},
              (dir / "sim.log").string()) == 0);
  {
    std::ofstream cfg(dir / "magcald.toml");
    cfg << "[refit]\nclock = \"data\"\n";
  }

  NotifySocket notify_socket;

  // WatchdogSec=3s: pings every 1.5 s. The budget beyond that half is for one frame's
  // processing (the filter start's fit is the slowest: ~0.5 s under ASan on a loaded machine).
  constexpr double kWatchdog_s = 3.0;
  setenv("NOTIFY_SOCKET", notify_socket.path().c_str(), 1);
  setenv("WATCHDOG_USEC", "3000000", 1);
  unsetenv("WATCHDOG_PID");  // systemd sets it to the service's pid; absent means "you"
  const auto t0 = Clock::now();
  const pid_t pid = spawn({kBin + "/magcald", "--config", (dir / "magcald.toml").string(), "--db",
                           db, "--lcm-url", "file://" + log + "?speed=1000"},
                          (dir / "magcald.log").string());
  unsetenv("NOTIFY_SOCKET");
  unsetenv("WATCHDOG_USEC");
  REQUIRE(pid > 0);

  std::vector<Message> messages;
  auto receive = [&] {
    for (auto& text : notify_socket.drain()) {
      messages.push_back({std::move(text), std::chrono::duration<double>(Clock::now() - t0).count(),
                          fs::exists(db)});
    }
  };
  int exit_code = -1;
  const auto deadline = t0 + std::chrono::seconds(60);
  while (Clock::now() < deadline) {
    receive();
    int status = 0;
    if (waitpid(pid, &status, WNOHANG) == pid) {
      exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -2;
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  if (exit_code == -1) {
    kill(pid, SIGKILL);
    waitpid(pid, nullptr, 0);
  }
  receive();
  INFO("magcald log:\n" << slurp((dir / "magcald.log").string()));
  REQUIRE(exit_code == 0);

  int ready = -1, stopping = -1;
  std::vector<double> pings_s;
  for (size_t i = 0; i < messages.size(); ++i) {
    const auto& m = messages[i];
    INFO("message " << i << " at " << m.t_s << " s: " << m.text);
    if (m.text == "READY=1") {
      CHECK(ready == -1);
      ready = static_cast<int>(i);
      CHECK(m.db_exists);  // the database is open (created) before READY
    } else if (m.text == "STOPPING=1") {
      CHECK(stopping == -1);
      stopping = static_cast<int>(i);
    } else if (m.text == "WATCHDOG=1") {
      CHECK(stopping == -1);  // none after STOPPING=1
      pings_s.push_back(m.t_s);
    } else {
      CHECK(m.text.rfind("STATUS=", 0) == 0);
    }
  }
  REQUIRE(ready >= 0);
  REQUIRE(stopping > ready);
  // The replay lasts ~7.2 s: pings every half interval, never a gap systemd would take for a
  // hang (the interval).
  REQUIRE(pings_s.size() >= 3);
  for (size_t i = 1; i < pings_s.size(); ++i) {
    INFO("ping " << i << " at " << pings_s[i] << " s");
    CHECK(pings_s[i] - pings_s[i - 1] < kWatchdog_s);
  }
  CHECK(messages[static_cast<size_t>(stopping)].t_s - pings_s.back() < kWatchdog_s);
  fs::remove_all(dir);
}
