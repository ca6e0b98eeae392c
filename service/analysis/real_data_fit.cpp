#include "service/analysis/real_data_fit.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>

#include <fmt/format.h>

#include "pipeline/alignment_check.hpp"
#include "pipeline/frames.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/reference_field.hpp"
#include "service/io/result_json.hpp"

namespace magcal {
namespace {

// First-pass sigma when none is given: only the relative weights of the first fit depend on
// it (and barely: 4 sigma^2 |y|^2 dominates 6 sigma^4), the refit uses the estimated value.
constexpr double kFirstPassSigma_nT = 100.0;
constexpr int kMaxSigmaPasses = 4;
constexpr double kJointToleranceRad = 1e-7;
constexpr double kSigmaRelTolerance = 0.02;
// As the batch alignment's check (AlignmentCheckOptions::max_systematic_ratio).
const double kMaxResidualRatio = AlignmentCheckOptions{}.max_systematic_ratio;

bool usable(const CalibrationResult& r) {
  return r.status != CalibrationStatus::kFailed && r.status != CalibrationStatus::kUnobservable;
}

// Per-axis population std of a set of vectors.
Eigen::Vector3d per_axis_std(const std::vector<Eigen::Vector3d>& v, Eigen::Vector3d* mean) {
  Eigen::Vector3d m = Eigen::Vector3d::Zero(), sq = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& x : v) m += x;
  m /= static_cast<double>(v.size());
  for (const Eigen::Vector3d& x : v) sq += (x - m).cwiseAbs2();
  if (mean) *mean = m;
  return (sq / static_cast<double>(v.size())).cwiseSqrt();
}

// The quaternion conventions a recording may hold under its w, x, y, z headers, as the
// q_body_from_enu they give (the file's q maps IMU (body) -> ENU, so q_body_from_enu = conj(q)).
struct QuaternionConvention {
  const char* name;  // how a refusal names it
  bool scalar_last;  // the columns hold x, y, z, w
  bool conjugate;    // the file's q maps ENU -> IMU
};
constexpr QuaternionConvention kQuaternionConventions[] = {
    {"", false, false},
    {"the quaternion columns look like x, y, z, w (scalar last) under w, x, y, z headers", true,
     false},
    {"the quaternions look conjugated (ENU -> IMU, not IMU -> ENU)", false, true},
    {"the quaternion columns look like x, y, z, w (scalar last) under w, x, y, z headers, and "
     "conjugated",
     true, true}};

Eigen::Matrix3d body_from_enu(const QuaternionWxyz& q_file, const QuaternionConvention& c) {
  const QuaternionWxyz q =
      c.scalar_last ? QuaternionWxyz(q_file(3), q_file(0), q_file(1), q_file(2)) : q_file;
  return dcm_from_quaternion(c.conjugate ? q : quaternion_conjugate(q));
}

JointAlignmentResult joint_alignment(const std::vector<Eigen::Vector3d>& u,
                                     const std::vector<Eigen::Matrix3d>& A) {
  JointAlignmentOptions jo;
  // The default 1e-12 rad takes hundreds of alternations on 51 000 BROAD pairs (slow under
  // ASan). The alternation converges linearly (rate ~0.85 on BROAD), so the error is ~7x the
  // last step: 1e-7 rad leaves < 1e-6 rad, ~1 % of the angles' sigma there (~1e-4 rad).
  jo.tolerance_rad = kJointToleranceRad;
  return align_with_unknown_reference(u, A, jo);
}

// Residual rms per axis of u_k against R A_k f.
double residual_per_axis_nT(const JointAlignmentResult& joint) {
  return joint.alignment.residual_rms_nT / std::sqrt(3.0);
}

RecordingAlignment align_constant_field(const FieldRecording& rec, const CalibrationParameters& p,
                                        double expected_per_axis_nT) {
  RecordingAlignment out;
  std::vector<Eigen::Vector3d> u;
  std::vector<const QuaternionWxyz*> q_file;
  std::vector<Eigen::Matrix3d> A;
  u.reserve(rec.rows.size());
  A.reserve(rec.rows.size());
  for (const FieldRecordingRow& row : rec.rows) {
    if (!row.has_quaternion) continue;
    u.push_back(p.apply(row.b_sensor_nT));
    q_file.push_back(&row.q_file);
    A.push_back(body_from_enu(row.q_file, kQuaternionConventions[0]));
  }
  out.n_pairs = static_cast<int>(u.size());
  out.joint = joint_alignment(u, A);
  if (!out.joint.alignment.ok() && out.joint.alignment.status != AlignmentStatus::kNotConverged) {
    out.message =
        std::string(to_string(out.joint.alignment.status)) + ": " + out.joint.alignment.message;
    return out;
  }
  const Eigen::Matrix3d& R = out.joint.alignment.estimate.R_sensor_from_body;
  out.rpy = roll_pitch_yaw_from_dcm(R);
  std::vector<Eigen::Vector3d> f_hat(u.size()), f_id(u.size());
  for (std::size_t k = 0; k < u.size(); ++k) {
    f_hat[k] = A[k].transpose() * (R.transpose() * u[k]);
    f_id[k] = A[k].transpose() * u[k];
  }
  out.enu_std_nT = per_axis_std(f_hat, &out.field_enu_nT);
  out.enu_std_identity_nT = per_axis_std(f_id, nullptr);
  out.estimated = true;

  // The check of itself: a constant field leaves the noise; beyond it is a wrong attitude (a
  // convention mix-up, named when another convention fits). Bench captures hold the attitude
  // in arbitrary order, so the whole residual is judged (the batch check's slowly varying part
  // assumes an orbit's smooth time series).
  out.residual_per_axis_nT = residual_per_axis_nT(out.joint);
  if (!(out.residual_per_axis_nT > kMaxResidualRatio * expected_per_axis_nT)) return out;
  out.inconsistency = fmt::format(
      "after the best rotation the residual is {:.1f} nT per axis, more than {:g} x the {:.1f} nT "
      "the noise leaves",
      out.residual_per_axis_nT, kMaxResidualRatio, expected_per_axis_nT);
  double best = out.residual_per_axis_nT;
  const char* named = nullptr;
  std::vector<Eigen::Matrix3d> A_other(u.size());
  for (const QuaternionConvention& c : kQuaternionConventions) {
    if (!c.scalar_last && !c.conjugate) continue;
    for (std::size_t k = 0; k < u.size(); ++k) A_other[k] = body_from_enu(*q_file[k], c);
    const double s = residual_per_axis_nT(joint_alignment(u, A_other));
    if (s < best) best = s, named = c.name;
  }
  if (named && best <= kMaxResidualRatio * expected_per_axis_nT)
    out.inconsistency +=
        fmt::format(": {} ({:.1f} nT per axis so; a diagnosis, not applied)", named, best);
  else
    out.inconsistency += ": check the quaternions' convention, the sensor axes and the field";
  return out;
}

nlohmann::json vec_json(const Eigen::Vector3d& v) {
  return nlohmann::json::array({json_number(v(0)), json_number(v(1)), json_number(v(2))});
}

}  // namespace

std::string RecordingFitOptions::validate() const {
  if (const std::string e = batch.validate(); !e.empty()) return e;
  if (sigma_nT && !(*sigma_nT > 0.0 && std::isfinite(*sigma_nT)))
    return "sigma_nT must be positive";
  if (reference_magnitude_nT &&
      !(*reference_magnitude_nT > 0.0 && std::isfinite(*reference_magnitude_nT)))
    return "the reference magnitude must be a positive number of nT";
  if (reference_magnitude_auto && reference_magnitude_nT)
    return "give the reference magnitude as auto or as a value, not both";
  const bool constant = reference_magnitude_auto || reference_magnitude_nT;
  if (constant && (estimate_time_offset || time_offset_s))
    return "a time-tag offset needs a position stream (IGRF reference), not a constant magnitude";
  if (estimate_time_offset && time_offset_s)
    return "give either a time offset or --estimate-time-offset, not both";
  if (time_offset_s && !std::isfinite(*time_offset_s)) return "the time offset must be finite";
  if (!(offset_max_s > offset_min_s) || !std::isfinite(offset_min_s) ||
      !std::isfinite(offset_max_s))
    return "the offset range must be MIN:MAX with MIN < MAX";
  if (!(offset_step_s > 0.0)) return "the offset step must be positive";
  return {};
}

namespace {

// The halves: each processed like the whole recording, split at the middle row in time, with
// the WHOLE recording's offset (a per-half profile is flatter: on the ISS file it gives 451
// and 490 s and moves the halves' bias apart by 1 uT, against 0.3 uT at the common offset).
// Empty, or why a half failed.
std::string fit_halves(const FieldRecording& rec, const RecordingFitOptions& options,
                       RecordingFitReport& rep) {
  if (options.split_halves && rec.rows.size() >= 2) {
    RecordingFitOptions half_options = options;
    half_options.split_halves = false;
    half_options.alignment = false;
    if (rep.time_offset_applied) {
      half_options.estimate_time_offset = false;
      half_options.time_offset_s = rep.time_offset_s;
    }
    FieldRecording half = rec;
    const auto mid = static_cast<std::ptrdiff_t>(rec.rows.size() / 2);
    for (int part = 0; part < 2; ++part) {
      half.rows.assign(part == 0 ? rec.rows.begin() : rec.rows.begin() + mid,
                       part == 0 ? rec.rows.begin() + mid : rec.rows.end());
      std::string half_error;
      std::optional<RecordingFitReport> h = fit_recording(half, half_options, &half_error);
      if (!h) return fmt::format("half {}: {}", part + 1, half_error);
      (part == 0 ? rep.first_half : rep.second_half) = std::make_shared<RecordingFitReport>(*h);
    }
  }
  return "";
}

// Stage 2 on a constant reference field from the recording's own attitude, refused as the batch
// gates refuse a rotation that is inconsistent with the data.
void align_recording(const FieldRecording& rec, const RecordingFitOptions& options, bool constant,
                     RecordingFitReport& rep) {
  if (options.alignment && constant && rec.has_quaternion_columns && usable(rep.result)) {
    rep.alignment = align_constant_field(rec, rep.result.parameters,
                                         std::max(rep.sigma_used_nT, rep.result.residual_rms_nT));
    if (rep.alignment.estimated) {
      rep.result.has_alignment = true;
      rep.result.alignment = rep.alignment.joint.alignment.estimate;
      rep.result.alignment.inconsistency = rep.alignment.inconsistency;
    }
    if (!rep.alignment.inconsistency.empty()) {  // refused as the batch gates refuse it
      GateVerdict verdict;
      verdict.accepted = false;
      verdict.reasons = rep.result.rejection_reasons;
      verdict.reasons.push_back("alignment_inconsistent: " + rep.alignment.inconsistency);
      apply_verdict(rep.result, verdict);
    }
  } else if (rec.has_quaternion_columns) {
    rep.alignment.message = constant ? "stage 1 failed" : "only with a constant reference field";
  }
}

}  // namespace

std::optional<RecordingFitReport> fit_recording(const FieldRecording& rec,
                                                const RecordingFitOptions& options,
                                                std::string* error) {
  const auto fail = [&](const std::string& msg) -> std::optional<RecordingFitReport> {
    if (error) *error = msg;
    return std::nullopt;
  };
  if (const std::string e = options.validate(); !e.empty()) return fail(e);
  RecordingFitReport rep;
  rep.n_rows = static_cast<int>(rec.rows.size());
  const bool constant = options.reference_magnitude_auto || options.reference_magnitude_nT;

  // Samples with |h| only (stage 1 is attitude-independent; stage 2 is done here).
  SampleSet samples(rec.rows.size());
  ReferenceSeries series;  // |H| on the position grid (IGRF case)
  if (constant) {
    rep.reference = "constant";
    if (options.reference_magnitude_auto) {
      std::vector<Eigen::Vector3d> b(rec.rows.size());
      for (std::size_t k = 0; k < rec.rows.size(); ++k) b[k] = rec.rows[k].b_sensor_nT;
      rep.sphere = fit_sphere(b);
      if (!rep.sphere->ok()) return fail("sphere fit: " + rep.sphere->message);
      rep.reference_magnitude_nT = rep.sphere->radius_nT;
    } else {
      rep.reference_magnitude_nT = *options.reference_magnitude_nT;
    }
    for (std::size_t k = 0; k < rec.rows.size(); ++k) {
      samples[k].utime = rec.rows[k].utime;
      samples[k].b_sensor_nT = rec.rows[k].b_sensor_nT;
      samples[k].h_body_nT = Eigen::Vector3d(rep.reference_magnitude_nT, 0.0, 0.0);
      samples[k].has_reference_direction = false;
    }
  } else {
    rep.reference = "igrf";
    if (!rec.has_position_columns)
      return fail(
          "no reference field: the file has neither all of the sample CSV's reference columns "
          "(t_s, bx_nT, by_nT, bz_nT, hx_nT, hy_nT, hz_nT: the reference field in the body "
          "frame) nor position columns (latitude, longitude, altitude: an IGRF reference); add "
          "them, or give a constant reference magnitude (--reference-magnitude auto|VALUE_nT)");
    ReferenceField field;
    series.t_s.reserve(rec.rows.size());
    series.value_nT.reserve(rec.rows.size());
    for (std::size_t k = 0; k < rec.rows.size(); ++k) {
      const FieldRecordingRow& row = rec.rows[k];
      const Eigen::Vector3d r = ecef_from_geodetic(
          {row.latitude_deg * kDegToRad, row.longitude_deg * kDegToRad, row.altitude_km * 1e3});
      const std::optional<Eigen::Vector3d> h = field.field_ecef_nT(row.utime, r);
      if (!h) return fail(fmt::format("row {}: no IGRF field (time outside the model?)", k + 1));
      const double t_s = seconds_from_utime(row.utime);
      if (!series.t_s.empty() && !(t_s > series.t_s.back()))
        return fail(fmt::format("row {}: time tags must increase strictly", k + 1));
      series.t_s.push_back(t_s);
      series.value_nT.push_back(h->norm());
      samples[k].utime = row.utime;
      samples[k].b_sensor_nT = row.b_sensor_nT;
      samples[k].h_body_nT = Eigen::Vector3d(h->norm(), 0.0, 0.0);
      samples[k].has_reference_direction = false;
    }
  }

  BatchCalibrationOptions batch = options.batch;
  batch.alignment = false;  // no reference directions: stage 2 is done below when possible
  batch.sigma_nT = options.sigma_nT.value_or(kFirstPassSigma_nT);
  rep.sigma_estimated = !options.sigma_nT;

  // IGRF reference: fit with the offset ignored, the "before" residual and the sigma for the
  // offset profile.
  if (!constant) {
    const CalibrationResult zero = calibrate_batch(samples, batch);
    rep.residual_rms_zero_offset_nT = zero.residual_rms_nT;
    if (!options.sigma_nT && usable(zero) && zero.residual_rms_nT > 0.0)
      batch.sigma_nT = zero.residual_rms_nT;
  }

  if (!constant && (options.estimate_time_offset || options.time_offset_s)) {
    if (options.estimate_time_offset) {
      TimeOffsetOptions o;
      o.tau_min_s = options.offset_min_s;
      o.tau_max_s = options.offset_max_s;
      o.step_s = options.offset_step_s;
      o.fit = batch;
      rep.offset_estimate = estimate_time_offset(samples, series, o);
      if (!rep.offset_estimate->ok())
        return fail(fmt::format("time offset estimation: {}: {}",
                                to_string(rep.offset_estimate->status),
                                rep.offset_estimate->message));
      rep.time_offset_s = rep.offset_estimate->tau_s;
    } else {
      rep.time_offset_s = *options.time_offset_s;
    }
    SampleSet shifted;
    rep.n_dropped_offset =
        apply_time_offset(samples, series, rep.time_offset_s, Interpolation::kCubic, &shifted);
    rep.time_offset_applied = true;
    samples = std::move(shifted);
  }

  // Final fit. Without a given sigma: fixed point sigma = residual rms (a few passes; the
  // weights 4 sigma^2 |y|^2 + 6 sigma^4 depend on it only mildly).
  if (!options.sigma_nT) batch.sigma_nT = kFirstPassSigma_nT;
  rep.result = calibrate_batch(samples, batch);
  for (int pass = 0; pass < kMaxSigmaPasses && !options.sigma_nT && usable(rep.result); ++pass) {
    const double rms = rep.result.residual_rms_nT;
    if (!(rms > 0.0) || std::abs(rms - batch.sigma_nT) < kSigmaRelTolerance * rms) break;
    batch.sigma_nT = rms;
    rep.result = calibrate_batch(samples, batch);
  }
  rep.sigma_used_nT = batch.sigma_nT;

  if (const std::string e = fit_halves(rec, options, rep); !e.empty()) return fail(e);
  align_recording(rec, options, constant, rep);
  return rep;
}

nlohmann::json recording_fit_to_json(const RecordingFitReport& rep, const FieldRecording& rec) {
  nlohmann::json j = calibration_result_to_json(rep.result);
  j["reference"] = rep.reference;
  j["sigma_nT"] = json_number(rep.sigma_used_nT);
  j["sigma_estimated"] = rep.sigma_estimated;
  j["n_rows"] = rep.n_rows;
  j["n_skipped_first"] = rec.n_skipped_first;
  j["n_rejected_non_finite"] = rec.n_rejected_non_finite;
  j["field_unit"] = rec.field_unit_name;
  if (rep.reference == "constant") {
    j["reference_magnitude_nT"] = json_number(rep.reference_magnitude_nT);
    if (rep.sphere) {
      j["sphere_fit"] = {{"center_nT", vec_json(rep.sphere->center_nT)},
                         {"radius_nT", json_number(rep.sphere->radius_nT)},
                         {"residual_rms_nT", json_number(rep.sphere->residual_rms_nT)}};
    }
  }
  if (rep.reference == "igrf")
    j["residual_rms_zero_offset_nT"] = json_number(rep.residual_rms_zero_offset_nT);
  if (rep.time_offset_applied) {
    j["time_offset_s"] = json_number(rep.time_offset_s);
    j["n_dropped_time_offset"] = rep.n_dropped_offset;
    if (rep.offset_estimate) {
      const TimeOffsetResult& o = *rep.offset_estimate;
      j["time_offset_sigma_s"] = json_number(o.sigma_tau_s);
      j["time_offset_sigma_white_s"] = json_number(o.sigma_tau_white_s);
      j["time_offset_status"] = to_string(o.status);
      j["time_offset_range_s"] = nlohmann::json::array(
          {json_number(o.profile_tau_s.empty() ? 0.0 : o.profile_tau_s.front()),
           json_number(o.profile_tau_s.empty() ? 0.0 : o.profile_tau_s.back())});
      j["time_offset_n_fits"] = o.n_fits;
    }
  }
  if (rep.first_half && rep.second_half) {
    nlohmann::json halves = nlohmann::json::array();
    for (const RecordingFitReport* hr : {rep.first_half.get(), rep.second_half.get()}) {
      const CalibrationResult* h = &hr->result;
      const Eigen::Matrix3d& D = h->parameters.D;
      halves.push_back(
          {{"bias_nT", vec_json(h->parameters.bias_nT)},
           {"bias_sigma_nT", vec_json(h->bias_sigma_nT())},
           {"D_diag", vec_json(D.diagonal())},
           {"D_diag_sigma",
            vec_json(h->covariance.diagonal().segment<3>(3).cwiseMax(0.0).cwiseSqrt())},
           {"residual_rms_nT", json_number(h->residual_rms_nT)},
           {"n_samples", h->n_samples},
           {"time_offset_s", json_number(hr->time_offset_applied ? hr->time_offset_s : 0.0)},
           {"status", to_string(h->status)}});
    }
    j["halves"] = halves;
  }
  if (rec.has_quaternion_columns) {
    j["n_missing_quaternion"] = rec.n_missing_quaternion;
    if (rep.alignment.estimated) {
      j["field_enu_nT"] = vec_json(rep.alignment.field_enu_nT);
      j["enu_std_nT"] = vec_json(rep.alignment.enu_std_nT);
      j["enu_std_identity_nT"] = vec_json(rep.alignment.enu_std_identity_nT);
      j["alignment_n_samples"] = rep.alignment.n_pairs;
      j["alignment_iterations"] = rep.alignment.joint.iterations;
    } else {
      j["alignment_message"] = rep.alignment.message;
    }
  }
  return j;
}

}  // namespace magcal
