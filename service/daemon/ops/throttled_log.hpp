// Rate-limited warnings for bad input (F Prime's event throttling): per key, the first
// `burst` occurrences are logged, then at most one line per `period_s`, which reports how many
// were suppressed since the last line. Counting is exact; only the log lines are limited.
// Single-threaded (one per thread).
#pragma once

#include <chrono>
#include <cstdint>
#include <string>
#include <unordered_map>

namespace magcal {

class ThrottledLog {
 public:
  explicit ThrottledLog(int burst = 5, double period_s = 10.0)
      : burst_(burst), period_s_(period_s) {}

  // Logs `message` at warning level under `key` unless throttled.
  void warn(const std::string& key, const std::string& message);

  // Occurrences of `key` not logged so far (for tests and the final summary).
  int64_t suppressed(const std::string& key) const;

 private:
  struct Entry {
    int64_t seen = 0;
    int64_t suppressed = 0;
    std::chrono::steady_clock::time_point last_logged{};
  };
  int burst_;
  double period_s_;
  std::unordered_map<std::string, Entry> entries_;
};

}  // namespace magcal
