#include "service/io/calibration_record.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <Eigen/Cholesky>

namespace magcal {
namespace {

// Counters blob layout: fixed-order int64/double fields, native little-endian. Version 2 adds
// the square-root factor, the noise estimate, the moments and the snapshot period.
constexpr uint32_t kFilterBlobMagic = 0x4D434631;    // "MCF1": P blob = covariance
constexpr uint32_t kFilterBlobMagicV2 = 0x4D434632;  // "MCF2": P blob = Cholesky factor

template <typename T>
void put(std::vector<uint8_t>& out, const T& v) {
  const auto* p = reinterpret_cast<const uint8_t*>(&v);
  out.insert(out.end(), p, p + sizeof(T));
}
template <typename T>
bool get(const std::vector<uint8_t>& in, size_t& pos, T& v) {
  if (pos + sizeof(T) > in.size()) return false;
  std::memcpy(&v, in.data() + pos, sizeof(T));
  pos += sizeof(T);
  return true;
}

}  // namespace

storage::CalibrationRecord record_from_result(const std::string& sat_id,
                                              const CalibrationResult& r) {
  storage::CalibrationRecord rec;
  rec.sat_id = sat_id;
  rec.method = r.method;
  rec.utime = r.utime;
  rec.window_start_utime = r.window_start_utime;
  rec.window_end_utime = r.window_end_utime;
  rec.n_samples = r.n_samples;
  for (int i = 0; i < 3; ++i) rec.bias_nT[static_cast<size_t>(i)] = r.parameters.bias_nT(i);
  const Vector6d d = pack_symmetric(r.parameters.D);
  for (int i = 0; i < 6; ++i) rec.D[static_cast<size_t>(i)] = d(i);
  for (int i = 0; i < 9; ++i) {
    for (int j = i; j < 9; ++j)
      rec.cov[static_cast<size_t>(storage::cov_index(i, j))] = r.covariance(i, j);
  }
  rec.has_alignment = r.has_alignment;
  if (r.has_alignment) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) {
        rec.R_sensor_from_body[static_cast<size_t>(3 * i + j)] =
            r.alignment.R_sensor_from_body(i, j);
      }
    }
    // Unknown (NaN, e.g. restored from a row stored before schema 5) stays unknown.
    if (r.alignment.angle_covariance_rad2.allFinite()) {
      const Vector6d c = pack_symmetric(r.alignment.angle_covariance_rad2);
      rec.alignment_covariance_rad2.emplace();
      for (int i = 0; i < 6; ++i) (*rec.alignment_covariance_rad2)[static_cast<size_t>(i)] = c(i);
    }
  }
  rec.residual_rms_nT = r.residual_rms_nT;
  rec.status = static_cast<int>(r.status);
  rec.verdict = r.accepted ? "accepted" : "rejected";
  rec.rejection_reasons = r.rejection_reasons;
  rec.iterations = r.iterations;
  rec.noise_scale = r.noise_scale;
  rec.residual_autocorrelation = r.residual_autocorrelation;
  // 0 is also "plain sandwich" for a batch result; filters never compute one (unknown).
  rec.covariance_lag_window = std::isfinite(r.noise_scale) ? r.covariance_lag_window : -1;
  rec.residual_rms_all_nT = r.residual_rms_all_nT;
  if (storage::is_refit_method(r.method)) rec.has_nonlinearity = r.has_nonlinearity ? 1 : 0;
  for (int i = 0; i < 3; ++i) rec.k3[static_cast<size_t>(i)] = r.nonlinearity_k3(i);
  rec.nis_mean = r.nis_mean;
  rec.measurement_noise_nT = r.measurement_noise_nT;
  for (int i = 0; i < 9; ++i) rec.model_error[static_cast<size_t>(i)] = r.model_error(i);
  // Refits say whether they modelled the temperature (0 / 1); an online result only has one
  // when it applies its anchor refit's (the caller sets temperature_model_refit_id).
  if (r.has_temperature_model)
    rec.has_temperature_model = 1;
  else if (storage::is_refit_method(r.method))
    rec.has_temperature_model = 0;
  if (r.has_temperature_model) {
    rec.reference_temperature_C = r.reference_temperature_C;
    for (int i = 0; i < 3; ++i)
      rec.temperature_coefficient_nT_per_C[static_cast<size_t>(i)] =
          r.temperature_coefficient_nT_per_C(i);
    size_t k = 0;
    for (int i = 0; i < 3; ++i) {
      for (int j = i; j < 3; ++j)
        rec.temperature_coefficient_cov[k++] = r.temperature_coefficient_covariance(i, j);
    }
  }
  return rec;
}

CalibrationResult result_from_record(const storage::CalibrationRecord& rec) {
  CalibrationResult r;
  r.method = rec.method;
  r.utime = rec.utime;
  r.window_start_utime = rec.window_start_utime;
  r.window_end_utime = rec.window_end_utime;
  r.n_samples = rec.n_samples;
  Vector9d p;
  for (int i = 0; i < 3; ++i) p(i) = rec.bias_nT[static_cast<size_t>(i)];
  for (int i = 0; i < 6; ++i) p(3 + i) = rec.D[static_cast<size_t>(i)];
  r.parameters = CalibrationParameters::from_packed(p);
  for (int i = 0; i < 9; ++i) {
    for (int j = 0; j < 9; ++j)
      r.covariance(i, j) = rec.cov[static_cast<size_t>(storage::cov_index(i, j))];
  }
  r.has_alignment = rec.has_alignment;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      r.alignment.R_sensor_from_body(i, j) = rec.R_sensor_from_body[static_cast<size_t>(3 * i + j)];
    }
  }
  if (rec.alignment_covariance_rad2) {
    r.alignment.angle_covariance_rad2 =
        unpack_symmetric(Eigen::Map<const Vector6d>(rec.alignment_covariance_rad2->data()));
  } else if (rec.has_alignment) {  // stored before schema 5: unknown, never zero
    r.alignment.angle_covariance_rad2.setConstant(std::numeric_limits<double>::quiet_NaN());
  }
  r.residual_rms_nT = rec.residual_rms_nT;
  r.status = static_cast<CalibrationStatus>(rec.status);
  r.accepted = rec.verdict == "accepted";
  r.rejection_reasons = rec.rejection_reasons;
  r.iterations = rec.iterations;
  r.converged = rec.status == 0;
  r.noise_scale = rec.noise_scale;
  r.residual_autocorrelation = rec.residual_autocorrelation;
  r.covariance_lag_window = std::max(0, rec.covariance_lag_window);
  r.residual_rms_all_nT = rec.residual_rms_all_nT;
  r.has_nonlinearity = rec.has_nonlinearity == 1;
  if (r.has_nonlinearity) {
    for (int i = 0; i < 3; ++i) r.nonlinearity_k3(i) = rec.k3[static_cast<size_t>(i)];
  }
  r.nis_mean = rec.nis_mean;
  r.measurement_noise_nT = rec.measurement_noise_nT;
  for (int i = 0; i < 9; ++i) r.model_error(i) = rec.model_error[static_cast<size_t>(i)];
  r.has_temperature_model = rec.has_temperature_model == 1;
  if (r.has_temperature_model) {
    r.reference_temperature_C = rec.reference_temperature_C;
    for (int i = 0; i < 3; ++i)
      r.temperature_coefficient_nT_per_C(i) =
          rec.temperature_coefficient_nT_per_C[static_cast<size_t>(i)];
    size_t k = 0;
    for (int i = 0; i < 3; ++i) {
      for (int j = i; j < 3; ++j) {
        r.temperature_coefficient_covariance(i, j) = rec.temperature_coefficient_cov[k];
        r.temperature_coefficient_covariance(j, i) = rec.temperature_coefficient_cov[k++];
      }
    }
  }
  return r;
}

calibration_t message_from_result(const std::string& sat_id, const CalibrationResult& result) {
  // calibration_t is a fixed contract (its fingerprint is what other tools check), so a result
  // with a bias temperature model goes out as it is stored: bias_nT (and its cov) is the bias at
  // the model's reference temperature T0, not at the current temperature, and neither T0 nor
  // k_T travels. A consumer that needs b(T) = bias_nT + k_T (T - T0) reads them from the
  // history (`magcal history --format json`, GET /api/v1/history).
  calibration_t msg = storage::message_from_record(record_from_result(sat_id, result));
  if (!std::isfinite(msg.residual_rms_nT)) msg.residual_rms_nT = -1.0;
  bool non_finite = false;
  auto sanitize = [&](double* v, int n) {
    for (int i = 0; i < n; ++i) {
      if (!std::isfinite(v[i])) {
        v[i] = 0.0;
        non_finite = true;
      }
    }
  };
  sanitize(msg.bias_nT, 3);
  sanitize(msg.D, 6);
  sanitize(msg.cov, 45);
  sanitize(msg.R_sensor_from_body, 9);
  constexpr int8_t kFailed = static_cast<int8_t>(CalibrationStatus::kFailed);
  if (non_finite && (msg.status == 0 || msg.status > kFailed)) msg.status = kFailed;
  return msg;
}

void fill_stored_sample(const mag_sample_t& msg, const std::string& sat_id,
                        const CalibrationSample& sample, int64_t receive_utime,
                        storage::StoredSample& out) {
  out.sat_id = sat_id;
  out.utime = msg.utime;
  out.seq = msg.seq;
  out.receive_utime = receive_utime;
  for (int i = 0; i < 3; ++i) out.b_sensor_nT[static_cast<size_t>(i)] = msg.b_sensor_nT[i];
  out.has_direction = sample.has_reference_direction;
  out.h_norm_nT = reference_norm_nT(sample);
  for (int i = 0; i < 3; ++i) {
    out.h_body_nT[static_cast<size_t>(i)] = sample.has_reference_direction
                                                ? sample.h_body_nT(i)
                                                : std::numeric_limits<double>::quiet_NaN();
  }
  out.has_attitude = msg.has_attitude;
  for (int i = 0; i < 4; ++i) out.q_body_from_eci[static_cast<size_t>(i)] = msg.q_body_from_eci[i];
  out.has_position = msg.has_position;
  for (int i = 0; i < 3; ++i) out.r_ecef_m[static_cast<size_t>(i)] = msg.r_ecef_m[i];
  out.temperature_C = sample.temperature_C;
}

CalibrationSample calibration_sample_from_stored(const storage::StoredSample& s) {
  CalibrationSample c;
  c.utime = s.utime;
  c.b_sensor_nT = Eigen::Vector3d(s.b_sensor_nT[0], s.b_sensor_nT[1], s.b_sensor_nT[2]);
  c.has_reference_direction = s.has_direction;
  c.h_body_nT = s.has_direction ? Eigen::Vector3d(s.h_body_nT[0], s.h_body_nT[1], s.h_body_nT[2])
                                : Eigen::Vector3d(s.h_norm_nT, 0.0, 0.0);
  c.temperature_C = s.temperature_C;
  return c;
}

storage::FilterState stored_filter_state(const std::string& sat_id, const std::string& method,
                                         const FilterState& st) {
  storage::FilterState out;
  out.sat_id = sat_id;
  out.method = method;
  for (int i = 0; i < 9; ++i) out.x[static_cast<size_t>(i)] = st.x(i);
  // MCF2: the P blob holds the lower Cholesky factor S (P = S S^T), row-major, so a restore is
  // bit-exact for the square-root filters.
  for (int i = 0; i < 9; ++i) {
    for (int j = 0; j < 9; ++j) out.P[static_cast<size_t>(9 * i + j)] = st.S(i, j);
  }
  out.last_utime = st.last_utime;
  out.n_samples = st.n_accepted;
  auto& b = out.counters;
  put(b, kFilterBlobMagicV2);
  put(b, static_cast<uint8_t>(st.initialized));
  put(b, static_cast<uint8_t>(st.consistent));
  put(b, st.first_utime);
  put(b, st.converged_since_utime);
  put(b, st.n_rejected_invalid);
  put(b, st.n_rejected_gate);
  put(b, st.n_inconsistency_events);
  put(b, st.n_covariance_repairs);
  put(b, st.nis_window_sum);
  put(b, st.nis_window_count);
  put(b, st.last_window_mean_nis);
  put(b, static_cast<uint8_t>(st.has_time));
  put(b, st.noise_scale2);
  put(b, st.innovation_c0);
  put(b, st.innovation_c1);
  put(b, st.previous_normalised_innovation);
  put(b, static_cast<uint8_t>(st.has_previous_innovation));
  for (int i = 0; i < st.moments.m.size(); ++i) put(b, st.moments.m(i));
  for (int i = 0; i < st.moments.m_lag1.size(); ++i) put(b, st.moments.m_lag1(i));
  for (int i = 0; i < st.moments.previous.size(); ++i) put(b, st.moments.previous(i));
  put(b, st.moments.n);
  put(b, st.fisher_condition);
  put(b, st.samples_since_fisher);
  put(b, st.period_start_utime);
  put(b, st.period_n);
  put(b, st.period_residual_sum2_nT2);
  put(b, st.period_nis_sum);
  // Appended later (a blob without them restores with the reported covariance = P until the
  // next block completes).
  for (int i = 0; i < st.anchor_information.size(); ++i) put(b, st.anchor_information(i));
  for (int i = 0; i < st.score_block.size(); ++i) put(b, st.score_block(i));
  put(b, st.score_block_n);
  for (int i = 0; i < st.score_meat.size(); ++i) put(b, st.score_meat(i));
  put(b, st.score_blocks);
  for (int i = 0; i < st.model_error_covariance.size(); ++i) put(b, st.model_error_covariance(i));
  put(b, static_cast<uint8_t>(st.model_error_known ? 1 : 0));
  // Appended later: the bias-motion measurement (filter_common.hpp).
  put(b, st.bias_block_start_utime);
  for (int i = 0; i < st.bias_block_start_m.size(); ++i) put(b, st.bias_block_start_m(i));
  put(b, st.bias_block_start_n);
  put(b, st.bias_motion_n);
  put(b, st.bias_motion_sum_t_h);
  put(b, st.bias_motion_sum_t2_h2);
  for (int i = 0; i < 3; ++i) put(b, st.bias_motion_sum_nT(i));
  for (int i = 0; i < 3; ++i) put(b, st.bias_motion_sum_tm_nT_h(i));
  for (int i = 0; i < 3; ++i) put(b, st.bias_motion_sum_m2_nT2(i));
  put(b, st.bias_random_walk_nT2_per_hour);
  return out;
}

bool filter_state_from_stored(const storage::FilterState& in, FilterState& out) {
  FilterState st;
  for (int i = 0; i < 9; ++i) st.x(i) = in.x[static_cast<size_t>(i)];
  Matrix9d blob;
  for (int i = 0; i < 9; ++i) {
    for (int j = 0; j < 9; ++j) blob(i, j) = in.P[static_cast<size_t>(9 * i + j)];
  }
  st.last_utime = in.last_utime;
  st.n_accepted = in.n_samples;
  size_t pos = 0;
  uint32_t magic = 0;
  uint8_t initialized = 0, consistent = 0;
  const auto& b = in.counters;
  if (!get(b, pos, magic) || (magic != kFilterBlobMagic && magic != kFilterBlobMagicV2) ||
      !get(b, pos, initialized) || !get(b, pos, consistent) || !get(b, pos, st.first_utime) ||
      !get(b, pos, st.converged_since_utime) || !get(b, pos, st.n_rejected_invalid) ||
      !get(b, pos, st.n_rejected_gate) || !get(b, pos, st.n_inconsistency_events) ||
      !get(b, pos, st.n_covariance_repairs) || !get(b, pos, st.nis_window_sum) ||
      !get(b, pos, st.nis_window_count) || !get(b, pos, st.last_window_mean_nis)) {
    return false;
  }
  st.initialized = initialized != 0;
  st.consistent = consistent != 0;
  if (!st.x.allFinite() || !blob.allFinite()) return false;
  if (magic == kFilterBlobMagic) {  // MCF1 (before the square-root filters): P itself
    st.has_time = st.initialized;
    if (!st.initialized) {
      st.S.setZero();
    } else {
      const Eigen::LLT<Matrix9d> llt(0.5 * (blob + blob.transpose()));
      if (llt.info() != Eigen::Success) return false;
      st.S = llt.matrixL();
    }
    st.fisher_condition = std::numeric_limits<double>::infinity();
    out = st;
    return true;
  }
  st.S = blob;
  uint8_t has_time = 0, has_prev = 0;
  bool ok = get(b, pos, has_time) && get(b, pos, st.noise_scale2) &&
            get(b, pos, st.innovation_c0) && get(b, pos, st.innovation_c1) &&
            get(b, pos, st.previous_normalised_innovation) && get(b, pos, has_prev);
  for (int i = 0; ok && i < st.moments.m.size(); ++i) ok = get(b, pos, st.moments.m(i));
  for (int i = 0; ok && i < st.moments.m_lag1.size(); ++i) ok = get(b, pos, st.moments.m_lag1(i));
  for (int i = 0; ok && i < st.moments.previous.size(); ++i)
    ok = get(b, pos, st.moments.previous(i));
  ok = ok && get(b, pos, st.moments.n) && get(b, pos, st.fisher_condition) &&
       get(b, pos, st.samples_since_fisher) && get(b, pos, st.period_start_utime) &&
       get(b, pos, st.period_n) && get(b, pos, st.period_residual_sum2_nT2) &&
       get(b, pos, st.period_nis_sum);
  if (!ok) return false;
  if (pos < b.size()) {  // the reported covariance's blocks (see stored_filter_state)
    for (int i = 0; ok && i < st.anchor_information.size(); ++i)
      ok = get(b, pos, st.anchor_information(i));
    for (int i = 0; ok && i < st.score_block.size(); ++i) ok = get(b, pos, st.score_block(i));
    ok = ok && get(b, pos, st.score_block_n);
    for (int i = 0; ok && i < st.score_meat.size(); ++i) ok = get(b, pos, st.score_meat(i));
    ok = ok && get(b, pos, st.score_blocks);
    if (!ok) return false;
  }
  if (pos < b.size()) {  // appended after the blocks: the model-error covariance
    for (int i = 0; ok && i < st.model_error_covariance.size(); ++i)
      ok = get(b, pos, st.model_error_covariance(i));
    uint8_t known = 0;
    ok = ok && get(b, pos, known);
    if (!ok) return false;
    st.model_error_known = known != 0;
  }
  if (pos < b.size()) {  // appended after the model error: the bias-motion measurement
    ok = get(b, pos, st.bias_block_start_utime);
    for (int i = 0; ok && i < st.bias_block_start_m.size(); ++i)
      ok = get(b, pos, st.bias_block_start_m(i));
    ok = ok && get(b, pos, st.bias_block_start_n) && get(b, pos, st.bias_motion_n) &&
         get(b, pos, st.bias_motion_sum_t_h) && get(b, pos, st.bias_motion_sum_t2_h2);
    for (int i = 0; ok && i < 3; ++i) ok = get(b, pos, st.bias_motion_sum_nT(i));
    for (int i = 0; ok && i < 3; ++i) ok = get(b, pos, st.bias_motion_sum_tm_nT_h(i));
    for (int i = 0; ok && i < 3; ++i) ok = get(b, pos, st.bias_motion_sum_m2_nT2(i));
    ok = ok && get(b, pos, st.bias_random_walk_nT2_per_hour);
    if (!ok) return false;
  }
  st.has_time = has_time != 0;
  st.has_previous_innovation = has_prev != 0;
  out = st;
  return true;
}

}  // namespace magcal
