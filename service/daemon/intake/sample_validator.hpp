// Validation of incoming samples (design.md "Bad input") and the reference field each stored
// sample keeps.
//
// Stateless checks, in this order (the first failing one is the reason counted):
//   invalid_sat_id      empty sat_id (a batch sample with an empty id inherits the batch's), not
//                       UTF-8, or longer than kMaxSatIdBytes (PostgreSQL refuses either: one
//                       such frame would stop the daemon)
//   batch_sat_mismatch  a batch sample naming another spacecraft than its batch
//   unknown_spacecraft  not on the whitelist (when one is configured)
//   time_out_of_range   utime outside [1990-01-01, 2100-01-01) (pipeline/time_utc.hpp)
//   non_finite          NaN/Inf in b_sensor_nT, or in r_ecef_m / q_body_from_eci / h_body_nT
//                       when their has_* flag is set (temperature_C NaN = unknown, accepted)
//   bad_attitude        has_attitude with a quaternion norm outside [0.9, 1.1]
//   out_of_range        any |b_sensor_nT component| > range_nT
//   absurd_position     has_position with |r_ecef| outside [min, max] (6400-8000 km)
//   no_reference        neither has_reference nor has_position
// The per-spacecraft checks (time plausibility against the stream: time_jump, future_time;
// older_than_window, duplicate) need the tracker: see spacecraft_tracker.hpp.
//
// Reference field (design.md data flow): h_body_nT from the frame when has_reference; else
// IGRF at r_ecef rotated to the body frame with q_body_from_eci when has_attitude; else only
// |h| is known (stored as (|h|, 0, 0) with has_reference_direction = false: stage 1 needs only
// the magnitude, stage 2 skips the sample).
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "pipeline/calibration_types.hpp"
#include "schemas/magcal_messages.hpp"
#include "service/daemon/ops/health.hpp"
#include "service/io/reference_field.hpp"

namespace magcal {

// No spacecraft is named longer; PostgreSQL's index takes keys up to about 2.7 kB only.
constexpr size_t kMaxSatIdBytes = 256;

struct ValidatorOptions {
  double range_nT = 100000.0;
  double min_position_m = 6.4e6;
  double max_position_m = 8.0e6;
  std::vector<std::string> whitelist;  // sorted; empty = everyone
};

// `batch_sat_id` is empty for a single mag_sample_t. nullopt = valid.
std::optional<RejectReason> check_sample(const mag_sample_t& s, const std::string& batch_sat_id,
                                         const ValidatorOptions& options);

// The spacecraft a valid sample belongs to (its own id, or the batch's when empty).
inline const std::string& sample_sat_id(const mag_sample_t& s, const std::string& batch_sat_id) {
  return s.sat_id.empty() ? batch_sat_id : s.sat_id;
}

// The sample as the estimators and the store see it, with its reference field and its
// temperature (NaN when unknown or implausible: plausible_temperature_C, service/io/sample_checks;
// the field reading itself stays valid); nullopt when IGRF refuses the date (reason
// reference_failed). `field` is used only without has_reference.
std::optional<CalibrationSample> to_reference_sample(const mag_sample_t& s, ReferenceField& field);

}  // namespace magcal
