#include "service/io/sample_checks.hpp"

#include <sys/stat.h>

#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <limits>

#include <lcm/lcm-cpp.hpp>

namespace magcal {

namespace {

int32_t read_int32_be(const uint8_t* b) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v = (v << 8) | b[i];
  return static_cast<int32_t>(v);
}

// Bytes of an encoded mag_sample_t after its sat_id: seq, b_sensor_nT, has_position,
// r_ecef_m, has_attitude, q_body_from_eci, has_reference, h_body_nT, temperature_C.
constexpr int64_t kSampleTailBytes = 8 + 3 * 8 + 1 + 3 * 8 + 1 + 4 * 8 + 1 + 3 * 8 + 4;
constexpr int64_t kMinEncodedSampleBytes = 8 + 4 + 1 + kSampleTailBytes;  // sat_id ""

// An LCM string at pos (int32 length including the NUL, then the bytes) that fits.
bool skip_string(const uint8_t* b, int64_t size, int64_t& pos) {
  if (size - pos < 4) return false;
  const int32_t len = read_int32_be(b + pos);
  pos += 4;
  if (len < 1 || len > size - pos) return false;
  pos += len;
  return true;
}

bool skip_sample(const uint8_t* b, int64_t size, int64_t& pos) {
  if (size - pos < 8) return false;
  pos += 8;  // utime
  if (!skip_string(b, size, pos) || size - pos < kSampleTailBytes) return false;
  pos += kSampleTailBytes;
  return true;
}

}  // namespace

bool well_formed_lcm_frame(const void* data, int size, bool batch) {
  if (size < 8) return false;
  const auto* b = static_cast<const uint8_t*>(data);
  int64_t pos = 8;  // fingerprint, checked by the caller
  if (!batch) return skip_sample(b, size, pos) && pos == size;
  if (!skip_string(b, size, pos) || size - pos < 4) return false;
  const int32_t n = read_int32_be(b + pos);
  pos += 4;
  if (n < 0 || n > (size - pos) / kMinEncodedSampleBytes) return false;
  for (int32_t i = 0; i < n; ++i) {
    if (!skip_sample(b, size, pos)) return false;
  }
  return pos == size;
}

double plausible_temperature_C(double temperature_C) {
  // (NaN fails both comparisons: stays unknown)
  return temperature_C >= kMinPlausibleTemperature_C && temperature_C <= kMaxPlausibleTemperature_C
             ? temperature_C
             : std::numeric_limits<double>::quiet_NaN();
}

std::string unreadable_lcm_log_reason(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return path + ": " + std::strerror(errno);
  if (S_ISDIR(st.st_mode)) return path + ": is a directory, not an LCM log";
  if (FILE* f = std::fopen(path.c_str(), "rb")) {
    std::fclose(f);
  } else {
    return path + ": " + std::strerror(errno);
  }
  if (st.st_size == 0) return path + ": empty file, not an LCM log";
  lcm::LogFile log(path, "r");
  if (!log.good() || log.readNextEvent() == nullptr) {
    return path + ": no LCM event can be read at its start (not an LCM log, or corrupt)";
  }
  return "";
}

}  // namespace magcal
