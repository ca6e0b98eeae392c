// A throwaway PostgreSQL server for tests (toolchain.md "PostgreSQL"): a cluster made by initdb
// (as the postgres user when running as root: initdb refuses root; made once per build tree and
// copied) in a fresh temporary directory, started
// with pg_ctl on a Unix socket in that directory and on 127.0.0.1 at a free port, fsync off.
// Stopped and removed by the destructor, and by a watchdog process when the test process dies
// without it (a crash, a CTest timeout): pg_ctl detaches the server, which would otherwise
// outlive the test.
//
// The server programs are not on PATH: they are taken from `pg_config --bindir`
// (libpq-dev; initdb and pg_ctl come with postgresql-15). Without them the test is skipped
// (tests/test_skip.hpp; with CI=true it fails).
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <pwd.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>

#include "storage/postgres/pg_database.hpp"
#include "tests/process_support.hpp"
#include "tests/test_skip.hpp"

namespace magcal::test {

class PgTestServer {
 public:
  PgTestServer() {
    char pattern[] = "/tmp/magcal-pg.XXXXXX";
    if (::mkdtemp(pattern) == nullptr) throw std::runtime_error("mkdtemp failed");
    dir_ = pattern;
    if (run({"pg_config", "--bindir"}, file("pg_config.out"), 30) == 0) {
      bindir_ = slurp(file("pg_config.out"));
      while (!bindir_.empty() && (bindir_.back() == '\n' || bindir_.back() == ' ')) {
        bindir_.pop_back();
      }
    }
    if (::access(pg_tool("initdb").c_str(), X_OK) != 0 ||
        ::access(pg_tool("pg_ctl").c_str(), X_OK) != 0) {
      unavailable_ = "PostgreSQL server programs (initdb, pg_ctl in `pg_config --bindir` = '" +
                     bindir_ + "'; Debian package postgresql-15)";
      return;
    }
    if (::geteuid() == 0) {
      const passwd* user = ::getpwnam("postgres");
      if (user == nullptr) {
        unavailable_ = "user postgres (to run initdb as root; Debian package postgresql-15)";
        return;
      }
      if (::chown(dir_.c_str(), user->pw_uid, user->pw_gid) != 0) {
        throw std::runtime_error("chown " + dir_ + " failed");
      }
      as_server_user_ = {"/usr/sbin/runuser", "-u", "postgres", "--"};
    }
    start_watchdog();
    make_cluster();
    if (!error_.empty()) return;
    start();
  }

  ~PgTestServer() {
    if (running_) {
      run(server_command({pg_tool("pg_ctl"), "-D", data(), "-m", "immediate", "-w", "-s", "stop"}),
          "/dev/null", 60);
    }
    std::error_code ignored;
    std::filesystem::remove_all(dir_, ignored);
    if (watchdog_input_ >= 0) {
      ::close(watchdog_input_);  // the watchdog finds nothing left to do and exits
      ::waitpid(watchdog_pid_, nullptr, 0);
    }
  }

  PgTestServer(const PgTestServer&) = delete;
  PgTestServer& operator=(const PgTestServer&) = delete;

  // "" when the server runs; else what is missing (a skip) ...
  const std::string& unavailable_reason() const { return unavailable_; }
  // ... or what failed with the programs present (a failure).
  const std::string& error() const { return error_; }

  // Starts (again) after stop(), on the same port; throws with the server log when it does not
  // come up.
  void start() {
    // The first start picks a free port: another process may take it first, then try another.
    const bool first = port_ == 0;
    for (int attempt = 0; attempt < (first ? 3 : 1) && !running_; ++attempt) {
      if (first) port_ = free_port();
      const std::string options = "-k " + dir_ + " -c listen_addresses=127.0.0.1 -p " +
                                  std::to_string(port_) +
                                  " -c fsync=off -c synchronous_commit=off -c full_page_writes=off";
      running_ = run(server_command({pg_tool("pg_ctl"), "-D", data(), "-l", file("server.log"),
                                     "-w", "-s", "-t", "60", "-o", options, "start"}),
                     file("pg_ctl.log"), 90) == 0;
    }
    if (!running_) throw std::runtime_error("pg_ctl start failed: " + slurp(file("server.log")));
  }

  // A fast shutdown: open sessions are terminated (SQLSTATE 57P01).
  void stop() {
    if (!running_) return;
    running_ = false;
    if (run(server_command({pg_tool("pg_ctl"), "-D", data(), "-m", "fast", "-w", "-s", "stop"}),
            file("pg_ctl.log"), 60) != 0) {
      throw std::runtime_error("pg_ctl stop failed: " + slurp(file("pg_ctl.log")));
    }
  }

  // The URI of database `name` over the Unix socket, and over TCP.
  std::string uri(const std::string& name) const {
    return "postgresql://magcal@/" + name + "?host=" + dir_ + "&port=" + std::to_string(port_);
  }
  std::string tcp_uri(const std::string& name) const {
    return "postgresql://magcal@127.0.0.1:" + std::to_string(port_) + "/" + name;
  }

  // Creates a new, empty database and returns its URI.
  std::string create_database() {
    const std::string name = "magcal_test_" + std::to_string(++databases_);
    storage::OpenOptions no_schema;
    no_schema.migrate_to = 0;  // the maintenance database stays as it is
    storage::PgDatabase admin(uri("postgres"), no_schema);
    admin.exec("CREATE DATABASE " + name);
    return uri(name);
  }

  const std::string& dir() const { return dir_; }

  // Freezes (SIGSTOP) or thaws (SIGCONT) the server: the postmaster and every process it
  // started. A frozen server keeps accepting connections (the kernel completes them) and answers
  // nothing: a hung host whose TCP stack still runs.
  void freeze(bool frozen) {
    const std::string pid_text = slurp(data() + "/postmaster.pid");
    const pid_t postmaster = static_cast<pid_t>(std::atol(pid_text.c_str()));
    if (postmaster <= 0) throw std::runtime_error("no postmaster.pid in " + data());
    const int signal = frozen ? SIGSTOP : SIGCONT;
    // The postmaster first when freezing (it starts no child after that), last when thawing.
    if (frozen) ::kill(postmaster, signal);
    for (const auto& entry : std::filesystem::directory_iterator("/proc")) {
      const std::string name = entry.path().filename();
      if (name.find_first_not_of("0123456789") != std::string::npos) continue;
      // /proc/PID/stat: "pid (comm) state ppid ...", comm may hold spaces and parentheses.
      std::string stat;
      try {
        stat = slurp(entry.path().string() + "/stat");
      } catch (const std::exception&) {
        continue;  // the process ended meanwhile (ESRCH): nothing to signal
      }
      const size_t after_comm = stat.rfind(')');
      if (after_comm == std::string::npos) continue;
      if (std::atol(stat.c_str() + after_comm + 4) == postmaster) {
        ::kill(static_cast<pid_t>(std::atol(name.c_str())), signal);
      }
    }
    if (!frozen) ::kill(postmaster, signal);
  }
  std::string pg_tool(const std::string& program) const { return bindir_ + "/" + program; }

 private:
  std::string file(const std::string& name) const { return dir_ + "/" + name; }
  std::string data() const { return file("data"); }

  // initdb takes 1-4 s and its result depends only on the PostgreSQL build and the options:
  // made once per build tree and PostgreSQL version and copied for each server (~0.2 s; cp -a
  // keeps the owner and the modes the server insists on). Processes racing to make it each
  // copy their own; the first rename wins.
  void make_cluster() {
    std::string version = bindir_;
    std::replace(version.begin(), version.end(), '/', '_');
    const std::string cache = std::string(MAGCAL_BIN_DIR) + "/../pg-test-clusters";
    const std::string cached = cache + "/v1" + version;
    if (std::filesystem::exists(cached)) {
      if (run({"cp", "-a", cached, data()}, file("cp.log"), 60) != 0) {
        error_ = "cannot copy " + cached + ": " + slurp(file("cp.log"));
      }
      return;
    }
    const std::string log = file("initdb.log");
    if (run(server_command({pg_tool("initdb"), "-D", data(), "-U", "magcal", "--auth=trust", "-E",
                            "UTF8", "--locale=C.UTF-8", "--no-sync", "--no-instructions"}),
            log, 120) != 0) {
      error_ = "initdb failed: " + slurp(log);
      return;
    }
    std::error_code ignored;  // without a cache the next server runs initdb again
    std::filesystem::create_directories(cache, ignored);
    const std::string copy = cached + ".tmp" + std::to_string(::getpid());
    if (run({"cp", "-a", data(), copy}, file("cp.log"), 60) == 0) {
      std::filesystem::rename(copy, cached, ignored);
    }
    std::filesystem::remove_all(copy, ignored);
  }

  std::vector<std::string> server_command(std::vector<std::string> args) const {
    args.insert(args.begin(), as_server_user_.begin(), as_server_user_.end());
    return args;
  }

  static int free_port() {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof addr;
    if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 ||
        ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
      if (fd >= 0) ::close(fd);
      throw std::runtime_error("no free port on 127.0.0.1");
    }
    ::close(fd);
    return ntohs(addr.sin_port);
  }

  // A process in its own session that waits for this process's end (EOF on a pipe only this
  // process holds: close-on-exec keeps it out of every other child), then stops the server and
  // removes the directory. After a normal destruction it finds nothing to do.
  void start_watchdog() {
    int fds[2];
    if (::pipe2(fds, O_CLOEXEC) != 0) throw std::runtime_error("pipe2 failed");
    std::string stop;
    for (const std::string& arg :
         server_command({pg_tool("pg_ctl"), "-D", data(), "-m", "immediate", "-w", "-s", "stop"})) {
      stop += "'" + arg + "' ";
    }
    const std::string script = "cat >/dev/null; " + stop + ">/dev/null 2>&1; rm -rf '" + dir_ + "'";
    watchdog_pid_ = spawn({"/usr/bin/setsid", "/bin/sh", "-c", script}, "/dev/null",
                          "/dev/fd/" + std::to_string(fds[0]));
    ::close(fds[0]);
    if (watchdog_pid_ < 0) {
      ::close(fds[1]);
      throw std::runtime_error("cannot start the watchdog (setsid, sh)");
    }
    watchdog_input_ = fds[1];
  }

  std::string dir_, bindir_, unavailable_, error_;
  std::vector<std::string> as_server_user_;
  int port_ = 0;
  bool running_ = false;
  int databases_ = 0;
  pid_t watchdog_pid_ = -1;
  int watchdog_input_ = -1;
};

// Commits of database `uri` wait for a synchronous standby (synchronous_commit on) in the sessions
// opened from now: the test server has it off on its command line, which a database setting
// overrides.
inline void wait_for_standby_commits(const std::string& uri) {
  storage::PgDatabase admin(uri);
  admin.exec("SET synchronous_commit = off");  // its own commits never wait
  const std::string name = admin.execute("SELECT current_database()").get_text(0, 0);
  admin.exec("ALTER DATABASE " + name + " SET synchronous_commit = on");
}

// A synchronous standby that does not exist (`absent`) holds every such commit until it is
// released (false): a server whose standby is down. Applied when a new session sees it.
inline void set_absent_synchronous_standby(const std::string& uri, bool absent) {
  storage::PgDatabase admin(uri);
  admin.exec("SET synchronous_commit = off");
  admin.exec(absent ? "ALTER SYSTEM SET synchronous_standby_names = 'magcal_absent_standby'"
                    : "ALTER SYSTEM RESET synchronous_standby_names");
  admin.exec("SELECT pg_reload_conf()");
  const std::string want = absent ? "magcal_absent_standby" : "";
  for (int i = 0; i < 100; ++i) {
    storage::PgDatabase probe(uri);
    probe.exec("SET synchronous_commit = off");
    if (probe.execute("SHOW synchronous_standby_names").get_text(0, 0) == want) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  throw std::runtime_error("synchronous_standby_names not applied after 10 s");
}

// The server shared by the tests of this process (started at the first call), or nullptr when
// the PostgreSQL programs are absent (the test is then skipped: return at once).
inline PgTestServer* pg_server_or_skip() {
  static const auto server = std::make_unique<PgTestServer>();
  if (!server->error().empty()) FAIL(server->error());
  if (!server->unavailable_reason().empty()) {
    skip_or_fail(server->unavailable_reason());
    return nullptr;
  }
  return server.get();
}

}  // namespace magcal::test
