// SystemdNotifier against a real unix datagram socket standing in for systemd's notify socket:
// the messages systemd would read (READY=1, WATCHDOG=1, STOPPING=1, STATUS=...), the watchdog
// rate limit (half of $WATCHDOG_USEC) and the no-op without $NOTIFY_SOCKET.
#include <catch2/catch.hpp>

#include <unistd.h>

#include <cstdlib>
#include <string>
#include <vector>

#include "service/daemon/ops/systemd_notifier.hpp"
#include "tests/service/daemon/notify_socket.hpp"

using magcal::SystemdNotifier;
using magcal::test::NotifySocket;
using namespace std::chrono_literals;

namespace {

void clear_systemd_environment() {
  unsetenv("NOTIFY_SOCKET");
  unsetenv("WATCHDOG_USEC");
  unsetenv("WATCHDOG_PID");
}

}  // namespace

TEST_CASE("without NOTIFY_SOCKET every call is a no-op", "[systemd_notifier]") {
  NotifySocket sock;
  clear_systemd_environment();
  setenv("WATCHDOG_USEC", "30000000", 1);  // a watchdog alone does not enable anything
  SystemdNotifier notifier;
  CHECK_FALSE(notifier.enabled());
  CHECK(notifier.watchdog_interval() == 0us);
  CHECK_FALSE(notifier.ready());
  CHECK_FALSE(notifier.watchdog_ping());
  CHECK_FALSE(notifier.status("running"));
  CHECK_FALSE(notifier.stopping());
  CHECK(sock.drain().empty());
  clear_systemd_environment();
}

TEST_CASE("ready, status and stopping reach the notify socket", "[systemd_notifier]") {
  NotifySocket sock;
  clear_systemd_environment();
  setenv("NOTIFY_SOCKET", sock.path().c_str(), 1);
  SystemdNotifier notifier;
  CHECK(notifier.enabled());
  CHECK(notifier.watchdog_interval() == 0us);  // no WatchdogSec=
  CHECK_FALSE(notifier.watchdog_ping());       // so no pings

  CHECK(notifier.ready());
  CHECK(notifier.status("ingesting: 12 spacecraft\nqueue 0"));
  CHECK(notifier.stopping());
  CHECK(sock.drain() == std::vector<std::string>{
                            "READY=1", "STATUS=ingesting: 12 spacecraft queue 0", "STOPPING=1"});
  clear_systemd_environment();
}

TEST_CASE("watchdog pings are rate-limited to half of WATCHDOG_USEC", "[systemd_notifier]") {
  NotifySocket sock;
  clear_systemd_environment();
  setenv("NOTIFY_SOCKET", sock.path().c_str(), 1);
  setenv("WATCHDOG_USEC", "30000000", 1);  // WatchdogSec=30s
  SystemdNotifier notifier;
  REQUIRE(notifier.watchdog_interval() == 30s);

  const auto t0 = SystemdNotifier::Clock::now();
  CHECK(notifier.watchdog_ping(t0));  // the first call always pings
  CHECK_FALSE(notifier.watchdog_ping(t0 + 1ms));
  CHECK_FALSE(notifier.watchdog_ping(t0 + 14999ms));
  CHECK(notifier.watchdog_ping(t0 + 15s));
  CHECK_FALSE(notifier.watchdog_ping(t0 + 15s + 1ms));
  CHECK_FALSE(notifier.watchdog_ping(t0 + 29999ms));
  CHECK(notifier.watchdog_ping(t0 + 30s));
  // A loop calling it every 100 ms for 60 s sends one ping per 15 s.
  int sent = 0;
  for (auto t = t0 + 30s + 100ms; t < t0 + 90s; t += 100ms) sent += notifier.watchdog_ping(t);
  CHECK(sent == 3);  // at 45, 60 and 75 s
  // After STOPPING=1 systemd no longer expects pings, and none are sent.
  CHECK(notifier.stopping());
  CHECK_FALSE(notifier.watchdog_ping(t0 + 200s));
  auto messages = sock.drain();
  REQUIRE(messages.size() == 7);
  CHECK(messages.back() == "STOPPING=1");
  messages.pop_back();
  for (const auto& m : messages) CHECK(m == "WATCHDOG=1");
  clear_systemd_environment();
}

TEST_CASE("a watchdog meant for another process is off", "[systemd_notifier]") {
  NotifySocket sock;
  clear_systemd_environment();
  setenv("NOTIFY_SOCKET", sock.path().c_str(), 1);
  setenv("WATCHDOG_USEC", "30000000", 1);
  setenv("WATCHDOG_PID", std::to_string(getpid() + 1).c_str(), 1);
  SystemdNotifier other;
  CHECK(other.watchdog_interval() == 0us);
  CHECK_FALSE(other.watchdog_ping());

  setenv("WATCHDOG_PID", std::to_string(getpid()).c_str(), 1);
  SystemdNotifier self;
  CHECK(self.watchdog_interval() == 30s);
  CHECK(self.watchdog_ping());
  CHECK(sock.drain() == std::vector<std::string>{"WATCHDOG=1"});
  clear_systemd_environment();
}

TEST_CASE("a notify socket nobody listens on fails softly", "[systemd_notifier]") {
  std::string path;
  {
    NotifySocket gone;
    path = gone.path();
  }  // socket closed and its directory removed
  clear_systemd_environment();
  setenv("NOTIFY_SOCKET", path.c_str(), 1);
  SystemdNotifier notifier;
  CHECK(notifier.enabled());
  CHECK_FALSE(notifier.ready());
  CHECK_FALSE(notifier.stopping());
  clear_systemd_environment();
}
