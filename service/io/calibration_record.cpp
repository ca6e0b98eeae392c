#include "service/io/calibration_record.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include <variant>

#include <Eigen/Cholesky>

#include "pipeline/packed_triangle.hpp"

namespace magcal {
namespace {

// The filter-state blob (storage::FilterState::counters): every field of the pipeline's
// FilterState beyond x, S and the times, native little-endian, in the one order
// filter_state_fields() lists. It starts with the 4-byte magic "MCF" + a version digit:
//   1  P blob = the covariance; the counters only (before the square-root filters);
//   2  P blob = the Cholesky factor S, the noise estimate, the moments and the snapshot period;
//      the reported covariance's blocks, the model error and the bias motion were appended in
//      later releases and may be absent (read as their defaults);
//   3  the same fields as 2, every section present, nothing after them;
//   4  3 and the bias-motion blocks' sensitivity to D (read as zero from 2 and 3: their blocks
//      then count as solved, without the correction to the current D);
//   5  (written now) 4 and the anchor refit's bias rate and its random walk (read as zero from
//      2-4: the filter then predicts no drift until the next re-anchor).
// A filter keeps only one of the start's lag-1 products and the bias-motion block start (the
// first until it starts, the other from then on): the one it does not keep is written as zeros
// (the block's time as -1), and ignored when read. A blob of another version or not starting
// with "MCF" is refused with a message naming it.
constexpr uint32_t kFilterBlobMagicBase = 0x4D434600;  // "MCF" + version digit, little-endian
constexpr int kFilterBlobVersion = 5;
constexpr int kOldestFilterBlobVersion = 1;

class BlobWriter {
 public:
  explicit BlobWriter(std::vector<uint8_t>& out) : out_(out) {}
  template <typename T>
  void operator()(const T& v) {
    const auto* p = reinterpret_cast<const uint8_t*>(&v);
    out_.insert(out_.end(), p, p + sizeof(T));
  }
  void flag(bool v) { (*this)(static_cast<uint8_t>(v ? 1 : 0)); }
  template <typename Derived>
  void each(const Eigen::DenseBase<Derived>& m) {
    for (Eigen::Index i = 0; i < m.size(); ++i) (*this)(m(i));
  }
  // Every section is written.
  bool section() const { return true; }

 private:
  std::vector<uint8_t>& out_;
};

class BlobReader {
 public:
  BlobReader(const std::vector<uint8_t>& in, int version) : in_(in), version_(version) {}
  template <typename T>
  void operator()(T& v) {
    if (!ok_ || pos_ + sizeof(T) > in_.size()) {
      ok_ = false;
      return;
    }
    std::memcpy(&v, in_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
  }
  void flag(bool& v) {
    uint8_t byte = 0;
    (*this)(byte);
    v = byte != 0;
  }
  template <typename Derived>
  void each(Eigen::DenseBase<Derived>& m) {
    for (Eigen::Index i = 0; i < m.size(); ++i) (*this)(m(i));
  }
  // A section appended within version 2 may be absent: the blob ends before it.
  bool section() const { return version_ >= 3 || pos_ < in_.size(); }
  bool ok() const { return ok_; }
  bool at_end() const { return pos_ == in_.size(); }
  size_t pos() const { return pos_; }

 private:
  const std::vector<uint8_t>& in_;
  int version_;
  size_t pos_ = 0;
  bool ok_ = true;
};

// The blob keeps the layout it had before the filter state was packed: full 9 x 9 matrices, A and
// the score meat apart, and both the start's lag-1 products and the bias-motion block start,
// where FilterState holds triangles, A + meat and one of the two (filter_common.hpp). These are
// the unpacked fields, taken from a state to write it (A + meat as A, the meat zero: the sum is
// what every release uses) and put into one after reading.
struct UnpackedFields {
  Matrix9d anchor_information = Matrix9d::Zero();
  Matrix9d score_meat = Matrix9d::Zero();
  Matrix9d model_error_covariance = Matrix9d::Zero();
  ScalarLag1Moments lag1;  // zero once started
  BiasBlockStart block;    // empty (no block open) until started
};

UnpackedFields unpacked_fields(const FilterState& st) {
  UnpackedFields f;
  f.anchor_information = symmetric_from_packed<9>(st.anchor_information_and_meat);  // meat: 0
  f.model_error_covariance = symmetric_from_packed<9>(st.model_error_covariance);
  if (const auto* lag1 = std::get_if<ScalarLag1Moments>(&st.lag1_or_block)) f.lag1 = *lag1;
  if (const auto* block = std::get_if<BiasBlockStart>(&st.lag1_or_block)) f.block = *block;
  return f;
}

// Symmetric parts (what the filter computes is symmetric: exactly what was written); the
// alternative of lag1_or_block the state's `initialized` calls for.
void put_unpacked_fields(const UnpackedFields& f, FilterState& st) {
  const auto packed_symmetric = [](const Matrix9d& M) {
    return packed_upper<9>(Matrix9d(0.5 * (M + M.transpose())));
  };
  st.anchor_information_and_meat = packed_symmetric(f.anchor_information + f.score_meat);
  st.model_error_covariance = packed_symmetric(f.model_error_covariance);
  if (st.initialized) {
    st.lag1_or_block = f.block;
  } else {
    st.lag1_or_block = f.lag1;
  }
}

// The blob's fields after its magic, in order, for writing (State = const FilterState, Fields =
// const UnpackedFields) and reading (both mutable): the one list both directions share.
template <typename Io, typename State, typename Fields>
void filter_state_fields(Io& io, State& st, Fields& f, int version) {
  io.flag(st.initialized);
  io.flag(st.consistent);
  io(st.first_utime);
  io(st.converged_since_utime);
  io(st.n_rejected_invalid);
  io(st.n_rejected_gate);
  io(st.n_inconsistency_events);
  io(st.n_covariance_repairs);
  io(st.nis_window_sum);
  io(st.nis_window_count);
  io(st.last_window_mean_nis);
  if (version == 1) return;
  io.flag(st.has_time);
  io(st.noise_scale2);
  io(st.innovation_c0);
  io(st.innovation_c1);
  io(st.previous_normalised_innovation);
  io.flag(st.has_previous_innovation);
  io.each(st.moments.m);
  io.each(f.lag1.m);
  io.each(f.lag1.previous);
  io(st.moments.n);
  io(st.fisher_condition);
  io(st.samples_since_fisher);
  io(st.period_start_utime);
  io(st.period_n);
  io(st.period_residual_sum2_nT2);
  io(st.period_nis_sum);
  if (!io.section()) return;  // the reported covariance's blocks
  io.each(f.anchor_information);
  io.each(st.score_block);
  io(st.score_block_n);
  io.each(f.score_meat);
  io(st.score_blocks);
  if (!io.section()) return;  // the model error
  io.each(f.model_error_covariance);
  io.flag(st.model_error_known);
  if (!io.section()) return;  // the bias-motion measurement
  io(f.block.utime);
  io.each(f.block.m);
  io(f.block.n);
  io(st.bias_motion_n);
  io(st.bias_motion_sum_t_h);
  io(st.bias_motion_sum_t2_h2);
  io.each(st.bias_motion_sum_nT);
  io.each(st.bias_motion_sum_tm_nT_h);
  io.each(st.bias_motion_sum_m2_nT2);
  io(st.bias_random_walk_nT2_per_hour);
  if (version < 4) return;
  io.each(st.bias_motion_sum_J_nT);
  io.each(st.bias_motion_sum_tJ_nT_h);
  io.each(st.bias_motion_sum_Jd_nT);
  io.each(st.bias_motion_sum_tJd_nT_h);
  if (version < 5) return;
  io.each(st.refit_bias_rate_nT_per_h);
  io.each(st.refit_bias_random_walk_nT2_per_hour);
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
  Eigen::Map<Eigen::Vector3d>(rec.bias_variability_nT2.data()) = r.bias_variability_nT2;
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
  if (r.has_bias_rate)
    rec.has_bias_rate = 1;
  else if (storage::is_refit_method(r.method))
    rec.has_bias_rate = 0;
  if (r.has_bias_rate) {
    for (int i = 0; i < 3; ++i)
      rec.bias_rate_nT_per_h[static_cast<size_t>(i)] = r.bias_rate_nT_per_h(i);
    Eigen::Map<Vector6d>(rec.bias_rate_cov.data()) = pack_symmetric(r.bias_rate_covariance);
  }
  rec.field_direction_error_rms_deg = r.field_error.direction_deg.rms;
  rec.field_direction_error_worst_deg = r.field_error.direction_deg.worst;
  rec.field_magnitude_error_rms_nT = r.field_error.magnitude_nT.rms;
  rec.field_magnitude_error_worst_nT = r.field_error.magnitude_nT.worst;
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
  r.bias_variability_nT2 = Eigen::Map<const Eigen::Vector3d>(rec.bias_variability_nT2.data());
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
  r.has_bias_rate = rec.has_bias_rate == 1;
  if (r.has_bias_rate) {
    for (int i = 0; i < 3; ++i)
      r.bias_rate_nT_per_h(i) = rec.bias_rate_nT_per_h[static_cast<size_t>(i)];
    r.bias_rate_covariance = unpack_symmetric(Eigen::Map<const Vector6d>(rec.bias_rate_cov.data()));
  }
  // Sample counts are not stored (n stays 0).
  r.field_error.direction_deg.rms = rec.field_direction_error_rms_deg;
  r.field_error.direction_deg.worst = rec.field_direction_error_worst_deg;
  r.field_error.magnitude_nT.rms = rec.field_magnitude_error_rms_nT;
  r.field_error.magnitude_nT.worst = rec.field_magnitude_error_worst_nT;
  return r;
}

storage::CalibrationRecord record_from_message(const calibration_t& msg) {
  storage::CalibrationRecord r;
  r.sat_id = msg.sat_id;
  r.method = msg.method;
  r.utime = msg.utime;
  r.window_start_utime = msg.window_start_utime;
  r.window_end_utime = msg.window_end_utime;
  r.n_samples = msg.n_samples;
  std::copy(std::begin(msg.bias_nT), std::end(msg.bias_nT), r.bias_nT.begin());
  std::copy(std::begin(msg.D), std::end(msg.D), r.D.begin());
  std::copy(std::begin(msg.cov), std::end(msg.cov), r.cov.begin());
  for (int i = 0; i < 3; ++i) r.bias_sigma_nT[i] = std::sqrt(r.cov[storage::cov_index(i, i)]);
  r.has_alignment = msg.has_alignment;
  std::copy(std::begin(msg.R_sensor_from_body), std::end(msg.R_sensor_from_body),
            r.R_sensor_from_body.begin());
  r.residual_rms_nT = msg.residual_rms_nT;
  r.status = msg.status;
  // Any non-ok status means the result is not to be used (calibration_t has no verdict).
  r.verdict = msg.status == 0 ? "accepted" : "rejected";
  return r;
}

calibration_t message_from_record(const storage::CalibrationRecord& r) {
  calibration_t msg{};
  msg.utime = r.utime;
  msg.sat_id = r.sat_id;
  msg.method = r.method;
  msg.window_start_utime = r.window_start_utime;
  msg.window_end_utime = r.window_end_utime;
  msg.n_samples = r.n_samples;
  std::copy(r.bias_nT.begin(), r.bias_nT.end(), msg.bias_nT);
  std::copy(r.D.begin(), r.D.end(), msg.D);
  std::copy(r.cov.begin(), r.cov.end(), msg.cov);
  msg.has_alignment = r.has_alignment;
  std::copy(r.R_sensor_from_body.begin(), r.R_sensor_from_body.end(), msg.R_sensor_from_body);
  msg.residual_rms_nT = r.residual_rms_nT;
  msg.status = static_cast<int8_t>(r.status);
  return msg;
}

calibration_t message_from_result(const std::string& sat_id, const CalibrationResult& result) {
  // calibration_t is a fixed contract (its fingerprint is what other tools check), so a result
  // with a bias temperature model goes out as it is stored: bias_nT (and its cov) is the bias at
  // the model's reference temperature T0, not at the current temperature, and neither T0 nor
  // k_T travels. A consumer that needs b(T) = bias_nT + k_T (T - T0) reads them from the
  // history (`magcal history --format json`, GET /api/v1/history).
  calibration_t msg = message_from_record(record_from_result(sat_id, result));
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
  BlobWriter writer(out.counters);
  writer(kFilterBlobMagicBase | static_cast<uint32_t>('0' + kFilterBlobVersion));
  const UnpackedFields fields = unpacked_fields(st);
  filter_state_fields(writer, st, fields, kFilterBlobVersion);
  return out;
}

std::string filter_state_from_stored(const storage::FilterState& in, FilterState& out) {
  FilterState st;
  for (int i = 0; i < 9; ++i) st.x(i) = in.x[static_cast<size_t>(i)];
  Matrix9d blob;
  for (int i = 0; i < 9; ++i) {
    for (int j = 0; j < 9; ++j) blob(i, j) = in.P[static_cast<size_t>(9 * i + j)];
  }
  st.last_utime = in.last_utime;
  st.n_accepted = in.n_samples;
  const auto& b = in.counters;
  uint32_t magic = 0;
  BlobReader header(b, 0);
  header(magic);
  if (!header.ok() || (magic & 0xFFFFFF00u) != kFilterBlobMagicBase) {
    return "not a magcal filter state (" + std::to_string(b.size()) +
           " bytes without the MCF header)";
  }
  const int version = static_cast<int>(magic & 0xFFu) - '0';
  if (version < kOldestFilterBlobVersion || version > kFilterBlobVersion) {
    return "filter state blob version " + std::to_string(version) + ": this magcal reads " +
           std::to_string(kOldestFilterBlobVersion) + " to " + std::to_string(kFilterBlobVersion);
  }
  BlobReader reader(b, version);
  reader(magic);
  UnpackedFields fields;
  filter_state_fields(reader, st, fields, version);
  if (!reader.ok()) {
    return "filter state blob version " + std::to_string(version) + " ends after " +
           std::to_string(b.size()) + " bytes, inside its fields";
  }
  if (version >= 3 && !reader.at_end()) {
    return "filter state blob version " + std::to_string(version) + " has " +
           std::to_string(b.size() - reader.pos()) + " bytes after its fields";
  }
  if (!st.x.allFinite() || !blob.allFinite()) return "filter state x or P is not finite";
  if (version == 1) {  // before the square-root filters: P itself
    st.has_time = st.initialized;
    if (!st.initialized) {
      st.S.setZero();
    } else {
      const Eigen::LLT<Matrix9d> llt(0.5 * (blob + blob.transpose()));
      if (llt.info() != Eigen::Success) return "filter state version 1: P is not positive definite";
      st.S = llt.matrixL();
    }
    st.fisher_condition = std::numeric_limits<double>::infinity();
  } else {
    if (!blob.triangularView<Eigen::StrictlyUpper>().toDenseMatrix().isZero(0.0))
      return "filter state S is not lower triangular";
    st.S = blob;
  }
  put_unpacked_fields(fields, st);
  out = st;
  return "";
}

}  // namespace magcal
