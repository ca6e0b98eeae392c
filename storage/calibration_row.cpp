#include "storage/calibration_row.hpp"

#include <cstdio>

#include "pipeline/time_utc.hpp"

#ifndef MAGCAL_VERSION
#define MAGCAL_VERSION "unknown"
#endif

namespace magcal::storage {

namespace calibration_row {

void check_appendable(const CalibrationRecord& r) {
  if (r.verdict != "accepted" && r.verdict != "rejected") {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "verdict must be 'accepted' or 'rejected', not '" + r.verdict + "'");
  }
  if (r.status < 0 || r.status > 4) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "status out of range: " + std::to_string(r.status));
  }
}

std::string json_string_array(const std::vector<std::string>& items) {
  std::string out = "[";
  for (size_t k = 0; k < items.size(); ++k) {
    if (k) out += ',';
    out += '"';
    for (const char c : items[k]) {
      switch (c) {
        case '"':
          out += "\\\"";
          break;
        case '\\':
          out += "\\\\";
          break;
        case '\n':
          out += "\\n";
          break;
        case '\t':
          out += "\\t";
          break;
        case '\r':
          out += "\\r";
          break;
        default:
          if (static_cast<unsigned char>(c) < 0x20) {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\u%04x", c);
            out += buf;
          } else {
            out += c;
          }
      }
    }
    out += '"';
  }
  return out + "]";
}

int64_t created_utime(const CalibrationRecord& r) {
  return r.created_utime != 0 ? r.created_utime : now_utime();
}

std::string_view software_version(const CalibrationRecord& r) {
  return r.software_version.empty() ? std::string_view(MAGCAL_VERSION)
                                    : std::string_view(r.software_version);
}

}  // namespace calibration_row

}  // namespace magcal::storage
