// Test support for the tests that run magcald as a real process (spawning and waiting:
// tests/process_support.hpp): its ports and logs, and reading what it published with an
// independent decoder (lcm::LogFile + the generated types).
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <functional>
#include <iterator>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>
#include <lcm/lcm-cpp.hpp>

#include "schemas/magcal_messages.hpp"
#include "tests/process_support.hpp"

namespace magcal::test {

// Multicast over loopback works here (toolchain.md: not in every network namespace).
inline bool multicast_available(const std::string& url) {
  lcm::LCM a(url);
  if (!a.good()) return false;
  bool got = false;
  a.subscribeFunction(
      "MAGCAL_PROBE",
      +[](const lcm::ReceiveBuffer*, const std::string&, bool* flag) { *flag = true; }, &got);
  for (int i = 0; i < 5 && !got; ++i) {
    uint8_t byte = 1;
    a.publish("MAGCAL_PROBE", &byte, 1);
    a.handleTimeout(200);
  }
  return got;
}

// The port magcald's operations server bound, from its log line "operations server:
// http://ADDR:PORT/ ..." (with --http-listen ADDR:0); -1 when it does not appear within timeout_s.
inline int wait_http_port(const std::string& log_path, double timeout_s) {
  int port = -1;
  wait_until(
      [&] {
        std::smatch m;
        const std::string log = slurp(log_path);
        if (!std::regex_search(log, m, std::regex(R"(operations server: http://[^ ]*:(\d+)/)")))
          return false;
        port = std::stoi(m[1].str());
        return true;
      },
      timeout_s);
  return port;
}

// Appends `message` (an LCM type), encoded, to a log as event `eventnum` at `timestamp_utime`.
template <class Message>
void write_log_event(lcm::LogFile& out, int64_t eventnum, int64_t timestamp_utime,
                     const std::string& channel, const Message& message) {
  std::vector<uint8_t> bytes(static_cast<size_t>(message.getEncodedSize()));
  message.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  lcm::LogEvent e;
  e.eventnum = eventnum;
  e.timestamp = timestamp_utime;
  e.channel = channel;
  e.datalen = static_cast<int32_t>(bytes.size());
  e.data = bytes.data();
  out.writeEvent(&e);
}

constexpr int kLogBatch = 50;                   // samples per mag_batch_t frame of write_batch_log
constexpr int64_t kLogStep_utime = 10'000'000;  // 10 s between its samples

// The k-th valid sample of `sat` (has_reference, seq k) kLogStep_utime apart from t0_utime: a
// field turning slowly through all directions, seen with a constant bias.
inline magcal::mag_sample_t turning_field_sample(const std::string& sat, int64_t t0_utime, int k) {
  magcal::mag_sample_t s{};
  s.utime = t0_utime + k * kLogStep_utime;
  s.sat_id = sat;
  s.seq = k;
  const double a = 0.01 * k, b = 0.0037 * k;
  const double h[3] = {30000.0 * std::cos(a) * std::cos(b), 30000.0 * std::sin(a) * std::cos(b),
                       30000.0 * std::sin(b)};
  for (int i = 0; i < 3; ++i) {
    s.h_body_nT[i] = h[i];
    s.b_sensor_nT[i] = h[i] + 100.0 * (i + 1);
  }
  s.has_reference = true;
  s.temperature_C = std::nanf("");
  return s;
}

// A replay log of n valid samples of `sat` (has_reference) from t0_utime, kLogBatch per
// mag_batch_t frame on MAGCAL_BATCH; consecutive frames are `frame_spacing_us` apart in log
// time, so `?speed=1` (or lcm-logplayer -s 1) plays them over n/kLogBatch spacings.
inline void write_batch_log(const std::string& path, const std::string& sat, int64_t t0_utime,
                            int n, int64_t frame_spacing_us) {
  lcm::LogFile out(path, "w");
  REQUIRE(out.good());
  int64_t event = 0;
  for (int first = 0; first < n; first += kLogBatch) {
    magcal::mag_batch_t batch;
    batch.sat_id = sat;
    for (int k = first; k < std::min(n, first + kLogBatch); ++k) {
      batch.samples.push_back(turning_field_sample(sat, t0_utime, k));
    }
    batch.n = static_cast<int32_t>(batch.samples.size());
    write_log_event(out, event, t0_utime + event * frame_spacing_us, "MAGCAL_BATCH", batch);
    ++event;
  }
}

// Another process (the sqlite3 shell) takes the write lock of `db` and holds it for `hold_s`;
// returns once it holds it (its script and output go to script_path and log_path).
inline pid_t hold_write_lock(const std::string& script_path, const std::string& log_path,
                             const std::string& db, int hold_s) {
  {
    std::ofstream script(script_path);
    script << "BEGIN EXCLUSIVE;\n.print locked\n.shell sleep " << hold_s << "\nCOMMIT;\n";
  }
  const pid_t locker = spawn({"sqlite3", db}, log_path, script_path);
  REQUIRE(locker > 0);
  REQUIRE(wait_until([&] { return slurp(log_path).find("locked") != std::string::npos; }, 10));
  return locker;
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
