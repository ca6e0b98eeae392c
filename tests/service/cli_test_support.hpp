// Test support for the CLI tests: a temporary folder and a runner for the real `magcal`
// binary (stdout captured, stderr through a file, exit code decoded).
#pragma once

#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include <catch2/catch.hpp>

namespace magcal::test {

struct TempDir {
  std::filesystem::path path;
  explicit TempDir(const std::string& prefix = "magcal_cli") {
    static int counter = 0;
    path = std::filesystem::temp_directory_path() /
           (prefix + "_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::filesystem::create_directories(path);
  }
  ~TempDir() { std::filesystem::remove_all(path); }
  std::string file(const std::string& name) const { return (path / name).string(); }
};

struct Run {
  int exit_code = -1;
  std::string out, err;
};

inline Run run_magcal(const std::string& args, const TempDir& dir) {
  const std::string err_file = dir.file("stderr.txt");
  const std::string cmd = std::string(MAGCAL_BIN_DIR) + "/magcal " + args + " 2>" + err_file;
  Run r;
  FILE* p = ::popen(cmd.c_str(), "r");
  REQUIRE(p != nullptr);
  char buf[4096];
  size_t n;
  while ((n = std::fread(buf, 1, sizeof buf, p)) > 0) r.out.append(buf, n);
  const int status = ::pclose(p);
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream e(err_file);
  std::stringstream ss;
  ss << e.rdbuf();
  r.err = ss.str();
  return r;
}

}  // namespace magcal::test
