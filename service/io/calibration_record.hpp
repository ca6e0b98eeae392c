// Conversions between the pipeline's values and what storage keeps / LCM carries:
//   CalibrationResult  -> storage::CalibrationRecord (history row; calibration_t through
//                         message_from_record) and back (previous accepted refit for the change
//                         gate);
//   calibration_t (LCM) <-> storage::CalibrationRecord (storage knows no wire format);
//   CalibrationSample  -> storage::StoredSample and back (refit windows, UKF re-runs);
//   FilterState (pipeline) <-> storage::FilterState (x, P, times; the remaining fields go into
//                         the counters blob, one versioned format, so a restore is bit-exact).
#pragma once

#include <string>

#include "pipeline/calibration_result.hpp"
#include "pipeline/filter_common.hpp"
#include "schemas/magcal_messages.hpp"
#include "storage/calibration_history.hpp"
#include "storage/filter_state_store.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

storage::CalibrationRecord record_from_result(const std::string& sat_id,
                                              const CalibrationResult& result);
CalibrationResult result_from_record(const storage::CalibrationRecord& record);
// calibration_t unchanged by the temperature model: bias_nT is then the bias at the reference
// temperature (see message_from_result). What goes out on LCM never carries NaN or Inf (a reader
// cannot tell them from corruption): a non-finite residual_rms_nT (unknown, e.g. a failed refit) is
// sent as -1; non-finite bias_nT, D, cov or R_sensor_from_body entries are sent as 0 and the status
// becomes 3 (failed) unless it already says not converged (1) or unobservable (2).
calibration_t message_from_result(const std::string& sat_id, const CalibrationResult& result);
// calibration_t <-> record (verdict from status: 4 = rejected; reasons are not in the message).
storage::CalibrationRecord record_from_message(const calibration_t& msg);
calibration_t message_from_record(const storage::CalibrationRecord& record);

// `sample` carries the reference field and the temperature (as to_reference_sample() judged
// it); `msg` the rest (seq, attitude, position).
void fill_stored_sample(const mag_sample_t& msg, const std::string& sat_id,
                        const CalibrationSample& sample, int64_t receive_utime,
                        storage::StoredSample& out);
CalibrationSample calibration_sample_from_stored(const storage::StoredSample& s);
inline double reference_norm_nT(const CalibrationSample& s) {
  return s.has_reference_direction ? s.h_body_nT.norm() : s.h_body_nT.x();
}

storage::FilterState stored_filter_state(const std::string& sat_id, const std::string& method,
                                         const FilterState& state);
// "" when restored into `out`; else why not (a blob of an unknown version, or not this code's:
// the caller starts cold).
std::string filter_state_from_stored(const storage::FilterState& stored, FilterState& out);

}  // namespace magcal
