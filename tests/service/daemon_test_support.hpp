// Test support for the tests that run magcald as a real process: spawning with the output in a
// file, waiting for an exit (or a condition) against a deadline, and reading what it published
// with an independent decoder (lcm::LogFile + the generated types).
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <functional>
#include <iterator>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>
#include <lcm/lcm-cpp.hpp>

#include "schemas/magcal_messages.hpp"

extern char** environ;

namespace magcal::test {

using Clock = std::chrono::steady_clock;

// posix_spawn with stdout/stderr appended to `log_path` (and stdin from `stdin_path` if given).
inline pid_t spawn(const std::vector<std::string>& args, const std::string& log_path,
                   const std::string& stdin_path = "") {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  if (!stdin_path.empty())
    posix_spawn_file_actions_addopen(&fa, 0, stdin_path.c_str(), O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&fa, 1, log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid = -1;
  const int rc = posix_spawnp(&pid, argv[0], &fa, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&fa);
  return rc == 0 ? pid : -1;
}

// Exit code, or -1 on timeout (the process is then killed), -2 if killed by a signal.
inline int wait_exit(pid_t pid, double timeout_s) {
  const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < deadline) {
    int status = 0;
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : -2;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ::kill(pid, SIGKILL);
  ::waitpid(pid, nullptr, 0);
  return -1;
}

inline bool wait_until(const std::function<bool()>& cond, double timeout_s) {
  const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < deadline) {
    if (cond()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return cond();
}

inline int run(const std::vector<std::string>& args, const std::string& log,
               double timeout_s = 60) {
  const pid_t pid = spawn(args, log);
  return pid < 0 ? -3 : wait_exit(pid, timeout_s);
}

inline std::string slurp(const std::string& path) {
  std::ifstream in(path);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Every event of an LCM log, decoded by the generated types (an independent reader).
struct Published {
  std::vector<calibration_t> calibrations;
  std::vector<daemon_status_t> statuses;
  int undecodable = 0;
};
inline Published read_published(const std::string& path) {
  Published p;
  lcm::LogFile log(path, "r");
  if (!log.good()) return p;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel == "MAGCAL_CALIBRATION") {
      calibration_t c;
      if (c.decode(e->data, 0, e->datalen) == e->datalen) {
        p.calibrations.push_back(c);
      } else {
        ++p.undecodable;
      }
    } else if (e->channel == "MAGCAL_STATUS") {
      daemon_status_t s;
      if (s.decode(e->data, 0, e->datalen) == e->datalen) {
        p.statuses.push_back(s);
      } else {
        ++p.undecodable;
      }
    }
  }
  return p;
}

// The count of one rejection reason in a status message (fails the test if it is absent).
inline int64_t rejected(const daemon_status_t& s, const std::string& reason) {
  for (int i = 0; i < s.n_reasons; ++i) {
    if (s.rejected_reason[static_cast<size_t>(i)] == reason)
      return s.rejected_count[static_cast<size_t>(i)];
  }
  FAIL("reason " << reason << " missing from the status message");
  return -1;
}

}  // namespace magcal::test
