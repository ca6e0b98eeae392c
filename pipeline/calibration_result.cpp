#include "pipeline/calibration_result.hpp"

namespace magcal {

const char* to_string(CalibrationStatus s) {
  switch (s) {
    case CalibrationStatus::kOk:
      return "ok";
    case CalibrationStatus::kNotConverged:
      return "not_converged";
    case CalibrationStatus::kUnobservable:
      return "unobservable";
    case CalibrationStatus::kFailed:
      return "failed";
    case CalibrationStatus::kRejected:
      return "rejected";
  }
  return "failed";
}

}  // namespace magcal
