#include "storage/calibration_history.hpp"

#include <limits>

namespace magcal::storage {

const char* status_name(int status) {
  switch (status) {
    case 0:
      return "ok";
    case 1:
      return "not_converged";
    case 2:
      return "unobservable";
    case 3:
      return "failed";
    case 4:
      return "rejected";
    default:
      return "unknown";
  }
}

bool is_refit_method(std::string_view method) {
  return method == "centered" || method == "twostep";
}

void CalibrationHistory::append_all(std::span<const CalibrationRecord> records) {
  for (const CalibrationRecord& r : records) append(r);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_refit(std::string_view sat_id) {
  return newest_refit_until(sat_id, std::numeric_limits<int64_t>::max());
}

std::optional<CalibrationRecord> CalibrationHistory::previous_refit(std::string_view sat_id) {
  const auto latest = latest_refit(sat_id);
  if (!latest || latest->utime == std::numeric_limits<int64_t>::min()) return std::nullopt;
  return newest_refit_until(sat_id, latest->utime - 1);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_accepted_refit(
    std::string_view sat_id) {
  return latest_accepted_refit(sat_id, std::numeric_limits<int64_t>::min(), 0);
}

}  // namespace magcal::storage
