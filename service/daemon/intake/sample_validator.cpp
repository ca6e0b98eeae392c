#include "service/daemon/intake/sample_validator.hpp"

#include <algorithm>
#include <cmath>

#include "pipeline/time_utc.hpp"
#include "service/io/sample_checks.hpp"

namespace magcal {
namespace {

bool all_finite(const double* v, int n) {
  for (int i = 0; i < n; ++i) {
    if (!std::isfinite(v[i])) return false;
  }
  return true;
}

// Well-formed UTF-8 (no overlong forms, surrogates or code points past U+10FFFF): PostgreSQL
// refuses anything else in a text column, and JSON output cannot carry it.
bool is_utf8(const std::string& text) {
  size_t i = 0;
  while (i < text.size()) {
    const auto byte = [&](size_t k) { return static_cast<unsigned char>(text[k]); };
    const unsigned char c = byte(i);
    int more = 0;
    unsigned char lo = 0x80, hi = 0xBF;  // the allowed range of the second byte
    if (c < 0x80) {
      more = 0;
    } else if (c >= 0xC2 && c <= 0xDF) {
      more = 1;
    } else if (c >= 0xE0 && c <= 0xEF) {
      more = 2;
      if (c == 0xE0) lo = 0xA0;
      if (c == 0xED) hi = 0x9F;
    } else if (c >= 0xF0 && c <= 0xF4) {
      more = 3;
      if (c == 0xF0) lo = 0x90;
      if (c == 0xF4) hi = 0x8F;
    } else {
      return false;
    }
    if (text.size() - i <= static_cast<size_t>(more)) return false;
    for (int k = 1; k <= more; ++k) {
      const unsigned char b = byte(i + static_cast<size_t>(k));
      if (k == 1 ? (b < lo || b > hi) : (b < 0x80 || b > 0xBF)) return false;
    }
    i += static_cast<size_t>(more) + 1;
  }
  return true;
}

Eigen::Vector3d vec3(const double* v) {
  return {v[0], v[1], v[2]};
}

}  // namespace

std::optional<RejectReason> check_sample(const mag_sample_t& s, const std::string& batch_sat_id,
                                         const ValidatorOptions& options) {
  const bool in_batch = !batch_sat_id.empty();
  if (in_batch && !s.sat_id.empty() && s.sat_id != batch_sat_id) {
    return RejectReason::kBatchSatMismatch;
  }
  const std::string& sat = sample_sat_id(s, batch_sat_id);
  if (sat.empty() || sat.size() > kMaxSatIdBytes || !is_utf8(sat)) {
    return RejectReason::kInvalidSatId;
  }
  if (!options.whitelist.empty() &&
      !std::binary_search(options.whitelist.begin(), options.whitelist.end(), sat)) {
    return RejectReason::kUnknownSpacecraft;
  }
  if (!is_plausible_utime(s.utime)) return RejectReason::kTimeOutOfRange;
  if (!all_finite(s.b_sensor_nT, 3) || (s.has_position && !all_finite(s.r_ecef_m, 3)) ||
      (s.has_attitude && !all_finite(s.q_body_from_eci, 4)) ||
      (s.has_reference && !all_finite(s.h_body_nT, 3))) {
    return RejectReason::kNonFinite;
  }
  if (s.has_attitude) {
    const double qn = Eigen::Vector4d(s.q_body_from_eci[0], s.q_body_from_eci[1],
                                      s.q_body_from_eci[2], s.q_body_from_eci[3])
                          .norm();
    if (qn < 0.9 || qn > 1.1) return RejectReason::kBadAttitude;
  }
  for (double b : s.b_sensor_nT) {
    if (std::abs(b) > options.range_nT) return RejectReason::kOutOfRange;
  }
  // No field anywhere near a spacecraft or a lab is exactly zero on three axes: a dropout. Stored,
  // one such sample failed every refit of its window (its residual is -|h|, thousands of sigmas).
  if (s.b_sensor_nT[0] == 0.0 && s.b_sensor_nT[1] == 0.0 && s.b_sensor_nT[2] == 0.0) {
    return RejectReason::kZeroVector;
  }
  if (s.has_position) {
    const double r = vec3(s.r_ecef_m).norm();
    if (r < options.min_position_m || r > options.max_position_m) {
      return RejectReason::kAbsurdPosition;
    }
  }
  if (!s.has_reference && !s.has_position) return RejectReason::kNoReference;
  return std::nullopt;
}

std::optional<CalibrationSample> to_reference_sample(const mag_sample_t& s, ReferenceField& field) {
  CalibrationSample out;
  out.utime = s.utime;
  out.b_sensor_nT = vec3(s.b_sensor_nT);
  out.temperature_C = plausible_temperature_C(static_cast<double>(s.temperature_C));
  if (s.has_reference) {
    out.h_body_nT = vec3(s.h_body_nT);
    out.has_reference_direction = true;
    return out;
  }
  const Eigen::Vector3d r = vec3(s.r_ecef_m);
  if (s.has_attitude) {
    const QuaternionWxyz q(s.q_body_from_eci[0], s.q_body_from_eci[1], s.q_body_from_eci[2],
                           s.q_body_from_eci[3]);
    const auto h = field.field_body_nT(s.utime, r, q);
    if (!h) return std::nullopt;
    out.h_body_nT = *h;
    out.has_reference_direction = true;
    return out;
  }
  // Without attitude only the magnitude is meaningful (rotations keep it): skip the ECEF->ECI
  // rotation and store (|h|, 0, 0).
  const auto h = field.field_ecef_nT(s.utime, r);
  if (!h) return std::nullopt;
  out.h_body_nT = Eigen::Vector3d(h->norm(), 0.0, 0.0);
  out.has_reference_direction = false;
  return out;
}

}  // namespace magcal
