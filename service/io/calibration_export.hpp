// The uplink table of `magcal export` (docs/export.md, format version kExportFormatVersion) and
// the reading of a calibration from a JSON file (`magcal fit --json`, one object of `magcal
// history --format json`), for `magcal export` and `magcal compare`.
//
// The table is pipeline/calibration_table.hpp's, B_cal = M B - o - o_T (T - T0) - o_r (t - t_ref)
// in the body frame, each value rounded to float32, with the error that rounding causes in B_cal
// and the calibration it came from (b, D, R, k_T, r in double precision).
//   JSON: one object; keys in docs/export.md.
//   CSV:  rows `name,value,unit` (header row first); names in docs/export.md.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "pipeline/calibration_result.hpp"

namespace magcal {

inline constexpr int kExportFormatVersion = 1;
// The |B| the rounding error is stated for by default: above the largest field at the Earth's
// surface (~66 000 nT), so a bound for any orbit.
inline constexpr double kDefaultRoundingField_nT = 70'000.0;

// Where the calibration came from, as the table names it.
struct CalibrationOrigin {
  std::string sat_id;  // empty: unknown (a fit's JSON)
  int64_t id = 0;      // calibrations.id; 0: not from a database
  std::string source;  // "history id 12 of magcal.db", "fit.json"
};

nlohmann::json export_table_json(const CalibrationResult& result, const CalibrationOrigin& origin,
                                 double rounding_field_nT);
std::string export_table_csv(const CalibrationResult& result, const CalibrationOrigin& origin,
                             double rounding_field_nT);

// A calibration from the JSON of `magcal fit --json` or one object of `magcal history --format
// json` (an array of exactly one object is taken as that object). nullopt with *error set when
// a required key (method, utime, window_start_utime, window_end_utime, bias_nT, D, covariance)
// is missing or malformed. sat_id and id are copied to *origin when present.
std::optional<CalibrationResult> calibration_from_json(const nlohmann::json& j,
                                                       CalibrationOrigin* origin,
                                                       std::string* error);

}  // namespace magcal
