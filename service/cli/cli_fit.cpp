// `magcal fit --input FILE.csv|FILE.lcm|- [--input ...] --method centered|twostep|ekf|ukf
//  [--sigma-nT S] [--robust] [--sat ID] [--trace FILE.csv] [--json]`
//
// Reads samples (service/io/sample_files.hpp). LCM samples with has_reference use h_body_nT;
// otherwise has_position -> IGRF at r_ecef (service/io/reference_field.hpp), rotated to body when
// has_attitude, else only |h| is used (no alignment from such samples). centered / twostep run
// the batch pipeline (pipeline/batch_calibration.hpp); ekf / ukf run the online filters over the
// samples in time order and report the final snapshot, the convergence time (time after which
// every bias 1-sigma stayed below 10 nT) and, with --trace, t_s + state + 1-sigma per sample.
// A CSV in another layout (docs/input-formats.md, service/io/field_recording.hpp) with a
// body-frame reference, or a position and an attitude to compute one from, is fitted the same
// way; one without goes to the magnitude-only fit (cli_fit_recording.cpp). Several --input
// files (or globs) give one result each; "-" reads a CSV from standard input.
// Output: aligned text, or one JSON object with --json (design.md keys,
// service/io/result_json.hpp; one line per file with several files). Exit: 0 result printed
// (accepted, rejected or not converged); 1 usage; 2 data (unreadable file, too few samples, NaN,
// unusable geometry, failed fit).
#include <glob.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <set>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "pipeline/alignment.hpp"
#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_table.hpp"
#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/roll_pitch_yaw_report.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/temperature_correction.hpp"
#include "pipeline/temperature_model.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/csv_line.hpp"
#include "service/io/field_recording.hpp"
#include "service/io/reference_field.hpp"
#include "service/io/result_json.hpp"
#include "service/io/sample_files.hpp"

namespace magcal::cli {
namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() &&
         s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

struct Loaded {
  SampleSet samples;
  std::string error;
  int exit_code = kExitOk;
  std::string notes;  // for stderr once the fit has a result (an error stays one line)
};

// The one-line note on repeats the readers dropped (sample_files.hpp: one time tag holds one
// sample; counted twice, they would shrink every reported sigma).
void note_duplicates(const std::string& input, int64_t dropped, const char* what, const char* key) {
  if (dropped == 0) return;
  std::cerr << fmt::format(
      "magcal fit: {}: dropped {} exact duplicate {} (same {} and values; one time tag holds "
      "one sample)\n",
      input, dropped, what, key);
}

}  // namespace

void note_recording(const FieldRecording& rec) {
  const auto names = [](const std::vector<std::string>& v) {
    return v.empty() ? std::string("none") : fmt::format("{}", fmt::join(v, ", "));
  };
  std::cerr << fmt::format("magcal fit: {}: columns used: {}; ignored: {}\n", rec.source,
                           names(rec.used_columns), names(rec.ignored_columns));
  if (rec.n_rejected_non_finite > 0)
    std::cerr << fmt::format(
        "magcal fit: {}: dropped {} rows with an empty or non-finite time, field or position\n",
        rec.source, rec.n_rejected_non_finite);
  note_duplicates(rec.source, rec.n_duplicates_dropped, "rows", "time");
  if (rec.n_out_of_order > 0)
    std::cerr << fmt::format("magcal fit: {}: {} rows out of time order, sorted\n", rec.source,
                             rec.n_out_of_order);
  if (rec.n_times_without_zone > 0)
    std::cerr << fmt::format(
        "magcal fit: {}: {} times without a zone (no Z or +hh:mm) taken as UTC\n", rec.source,
        rec.n_times_without_zone);
}

namespace {

// A CSV whose header is the design's sample format: read_sample_csv.
Loaded load_sample_csv(const CsvTable& table) {
  Loaded out;
  CsvReadResult csv = read_sample_csv(table);
  if (!csv.ok()) {
    out.error = csv.error;
    out.exit_code = kExitData;
    return out;
  }
  // The design's columns and its writer's extras are the format; anything else is named.
  std::vector<std::string> ignored;
  for (const std::string& name : table.header) {
    static const std::set<std::string> known = {
        "t_s", "bx_nT", "by_nT", "bz_nT",      "hx_nT",      "hy_nT",      "hz_nT",        "qw",
        "qx",  "qy",    "qz",    "r_ecef_x_m", "r_ecef_y_m", "r_ecef_z_m", "temperature_C"};
    if (!known.count(name)) ignored.push_back(name);
  }
  if (!ignored.empty())
    out.notes += fmt::format("magcal fit: {}: columns ignored: {}\n", table.source,
                             fmt::join(ignored, ", "));
  if (csv.missing_dropped > 0)
    out.notes += fmt::format("magcal fit: {}: dropped {} rows with an empty or non-finite value\n",
                             table.source, csv.missing_dropped);
  note_duplicates(table.source, csv.duplicates_dropped, "rows", "t_s");
  out.samples.reserve(csv.rows.size());
  for (const CsvSampleRow& row : csv.rows) out.samples.push_back(row.sample);
  return out;
}

// An LCM log of mag_sample_t / mag_batch_t.
Loaded load_samples(const FitArgs& args) {
  Loaded out;
  LcmReadOptions opt;
  if (!args.sat.empty()) opt.sat_id = args.sat;
  LcmReadResult lcm = read_sample_lcm_log(args.input, opt);
  if (!lcm.ok()) {
    out.error = lcm.error;
    out.exit_code = kExitData;
    return out;
  }
  if (args.sat.empty() && lcm.sat_ids.size() > 1) {
    out.error = fmt::format("{} holds several spacecraft ({}): choose one with --sat", args.input,
                            fmt::join(lcm.sat_ids, ", "));
    out.exit_code = kExitUsage;
    return out;
  }
  if (!args.sat.empty() && lcm.samples.empty()) {
    out.error = fmt::format("{}: no samples of spacecraft {} (present: {})", args.input, args.sat,
                            fmt::join(lcm.sat_ids, ", "));
    out.exit_code = kExitData;
    return out;
  }
  note_duplicates(args.input, lcm.duplicates_dropped, "samples", "spacecraft, utime");
  if (lcm.undecodable > 0) {
    // What magcald counts as decode_error: the fit goes on without those frames' samples, but
    // the user must know data were lost.
    std::cerr << fmt::format(
        "magcal fit: {}: {} of {} frames on the sample channels could not be decoded (corrupt); "
        "their samples are left out\n",
        args.input, lcm.undecodable, lcm.events);
  }
  std::unique_ptr<ReferenceField> field;
  out.samples.reserve(lcm.samples.size());
  for (std::size_t k = 0; k < lcm.samples.size(); ++k) {
    const mag_sample_t& msg = lcm.samples[k];
    for (int i = 0; i < 6; ++i) {
      const bool is_b = i < 3;
      const double v = is_b ? msg.b_sensor_nT[i] : msg.h_body_nT[i - 3];
      if ((is_b || msg.has_reference) && std::abs(v) > kMaxFieldComponent_nT) {
        out.error = fmt::format(
            "{}: sample {} (seq {}): {}[{}] = {:g} nT is beyond any magnetometer's range "
            "(|value| <= 1e7 nT)",
            args.input, k, msg.seq, is_b ? "b_sensor_nT" : "h_body_nT", i % 3, v);
        out.exit_code = kExitData;
        return out;
      }
    }
    CalibrationSample s = to_calibration_sample(msg);
    if (!msg.has_reference) {
      if (!msg.has_position) {
        out.error =
            fmt::format("{}: sample {} (seq {}) has neither a reference field nor a position",
                        args.input, k, msg.seq);
        out.exit_code = kExitData;
        return out;
      }
      if (!field) field = std::make_unique<ReferenceField>();
      const Eigen::Vector3d r(msg.r_ecef_m[0], msg.r_ecef_m[1], msg.r_ecef_m[2]);
      std::optional<Eigen::Vector3d> h;
      if (msg.has_attitude) {
        const QuaternionWxyz q(msg.q_body_from_eci[0], msg.q_body_from_eci[1],
                               msg.q_body_from_eci[2], msg.q_body_from_eci[3]);
        h = field->field_body_nT(msg.utime, r, q);
        s.has_reference_direction = true;
      } else {
        h = field->field_ecef_nT(msg.utime, r);
        if (h) h = Eigen::Vector3d(h->norm(), 0.0, 0.0);  // only |h| is meaningful
        s.has_reference_direction = false;
      }
      if (!h) {
        out.error = fmt::format(
            "{}: sample {} (seq {}): no IGRF reference (time outside the "
            "model or invalid position)",
            args.input, k, msg.seq);
        out.exit_code = kExitData;
        return out;
      }
      s.h_body_nT = *h;
    }
    out.samples.push_back(s);
  }
  return out;
}

struct FilterRun {
  CalibrationResult result;
  double convergence_time_s = std::numeric_limits<double>::quiet_NaN();
  std::string error;
};

// Runs the filter over the samples in time order; optional trace rows to `trace`.
template <typename Filter>
FilterRun run_filter(Filter& filter, const SampleSet& samples, std::FILE* trace) {
  FilterRun run;
  for (const CalibrationSample& s : samples) {
    filter.update(s.b_sensor_nT, s.h_body_nT.norm(), s.utime);
    if (trace) {
      // Per sample: what a snapshot taken now would say (status and evidence).
      const CalibrationResult snap = filter.snapshot();
      const Vector9d x = snap.parameters.packed();
      const Vector9d sd = snap.covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
      std::fprintf(trace, "%.6f", static_cast<double>(s.utime) * 1e-6);
      for (int i = 0; i < 9; ++i) std::fprintf(trace, ",%.10g", x(i));
      for (int i = 0; i < 9; ++i) std::fprintf(trace, ",%.10g", sd(i));
      std::fprintf(trace, ",%s,%.4g,%.4g,%.4g\n", to_string(snap.status), snap.measurement_noise_nT,
                   snap.residual_autocorrelation, snap.fisher_condition_number);
    }
  }
  run.result = filter.snapshot();
  const FilterState& st = filter.state();
  if (st.converged_since_utime >= 0 && st.has_time) {
    run.convergence_time_s = static_cast<double>(st.converged_since_utime - st.first_utime) * 1e-6;
  }
  return run;
}

void finish_filter_result(CalibrationResult& r, const SampleSet& samples, double sigma_nT,
                          const CalibrationResult& refit, bool estimate_attitude_lag) {
  r.n_samples = static_cast<int>(samples.size());
  r.window_start_utime = samples.front().utime;
  r.window_end_utime = samples.back().utime;
  double sum_sq = 0.0;
  for (const CalibrationSample& s : samples) {
    const double e = r.parameters.apply(s.b_sensor_nT).norm() - s.h_body_nT.norm();
    sum_sq += e * e;
  }
  r.residual_rms_nT = std::sqrt(sum_sq / static_cast<double>(samples.size()));
  r.converged = r.status == CalibrationStatus::kOk;
  estimate_alignment(samples, sigma_nT, BatchCalibrationOptions{}.min_alignment_samples, &r, &refit,
                     estimate_attitude_lag);
  GateInputs in;
  in.min_coverage_eigenvalue = direction_coverage_eigenvalues(samples)(0);
  GateVerdict verdict = evaluate_gates(r, in);
  reject_unless_ok(r, verdict);  // as the daemon's snapshots
  apply_verdict(r, verdict);
}

void print_text(const CalibrationResult& r, const FieldError& raw_error, double compute_ms,
                double convergence_time_s, double gimbal_lock_margin_deg) {
  const Eigen::Vector3d b = r.parameters.bias_nT, s = r.bias_sigma_nT();
  const Eigen::Matrix3d& D = r.parameters.D;
  const Vector9d sd = r.covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  auto line = [](const char* key, const std::string& value) {
    std::cout << fmt::format("{:<18}{}\n", key, value);
  };
  line("method", r.method);
  line("status", to_string(r.status));
  line("verdict", r.accepted ? "accepted" : "rejected");
  for (const std::string& reason : r.rejection_reasons) line("  reason", reason);
  if (!r.message.empty()) line("message", r.message);
  line("n_samples", std::to_string(r.n_samples));
  // What the numbers mean (estimation.md section 1): the equation, the time they refer to, the
  // bias's frame and reference.
  line("equation", r.has_alignment ? "B_cal = R^T ((I + D) B - b): B sensor frame, B_cal body frame"
                                   : "B_cal = (I + D) B - b: sensor frame (no alignment)");
  if (r.has_temperature_model || r.has_bias_rate) {
    line("", fmt::format("b(t, T) = b{}{}", r.has_temperature_model ? " + k_T (T - T0)" : "",
                         r.has_bias_rate ? " + r (t - t_ref)" : ""));
  }
  line("epoch", fmt::format("{} (window {} to {})", history_time(r.utime),
                            history_time(r.window_start_utime), history_time(r.window_end_utime)));
  std::string bias_reference = "sensor frame";
  if (r.has_temperature_model)
    bias_reference += fmt::format(", at T0 = {:.3f} degC", r.reference_temperature_C);
  if (r.has_bias_rate)
    bias_reference += ", at t_ref = " + history_time(r.window_end_utime) + " (the window's end)";
  line("bias", bias_reference);
  line("bias_nT", fmt::format("{:12.3f} {:12.3f} {:12.3f}", b.x(), b.y(), b.z()));
  line("bias_sigma_nT", fmt::format("{:12.3f} {:12.3f} {:12.3f}", s.x(), s.y(), s.z()));
  for (int i = 0; i < 3; ++i) {
    line(i == 0 ? "D" : "", fmt::format("{:12.6f} {:12.6f} {:12.6f}", D(i, 0), D(i, 1), D(i, 2)));
  }
  line("D_sigma",
       fmt::format("D11 {:.2e}  D22 {:.2e}  D33 {:.2e}  D12 {:.2e}  D13 {:.2e}  D23 {:.2e}", sd(3),
                   sd(4), sd(5), sd(6), sd(7), sd(8)));
  if (r.has_temperature_model) {  // bias_nT is then the bias at the reference temperature
    const Eigen::Vector3d k = r.temperature_coefficient_nT_per_C;
    const Eigen::Vector3d ks = r.temperature_coefficient_sigma_nT_per_C();
    line("reference_temp_C", fmt::format("{:.3f}", r.reference_temperature_C));
    line("temp_coeff_nT/C", fmt::format("{:12.4f} {:12.4f} {:12.4f}", k.x(), k.y(), k.z()));
    line("temp_coeff_sigma", fmt::format("{:12.4f} {:12.4f} {:12.4f}", ks.x(), ks.y(), ks.z()));
  }
  if (r.has_bias_rate) {  // bias_nT is then the bias at the window's end
    const Eigen::Vector3d& rate = r.bias_rate_nT_per_h;
    const Eigen::Vector3d rs = r.bias_rate_sigma_nT_per_h();
    line("bias_rate_nT/h", fmt::format("{:12.4f} {:12.4f} {:12.4f}", rate.x(), rate.y(), rate.z()));
    line("bias_rate_sigma", fmt::format("{:12.4f} {:12.4f} {:12.4f}", rs.x(), rs.y(), rs.z()));
  }
  if (r.orbit_swing.periods_tried > 0) {  // no temperature channel: a swing with the orbit?
    const UnresolvedBiasSwing& w = r.orbit_swing;
    line(
        "orbit_swing_nT",
        fmt::format("{:12.4f} {:12.4f} {:12.4f}  (at {:.2f} min, p {:.2f}; {})", w.amplitude_nT.x(),
                    w.amplitude_nT.y(), w.amplitude_nT.z(), w.period_s / 60.0, w.period_probability,
                    w.detected() ? "detected"
                                 : "not detected: the sigma covers what the data cannot exclude"));
    line("orbit_swing_sigma", fmt::format("{:12.4f} {:12.4f} {:12.4f}", w.amplitude_sigma_nT.x(),
                                          w.amplitude_sigma_nT.y(), w.amplitude_sigma_nT.z()));
  }
  if (r.has_alignment) {
    const Eigen::Matrix3d& R = r.alignment.R_sensor_from_body;
    for (int i = 0; i < 3; ++i) {
      line(i == 0 ? "R_sensor_from_body" : "",
           fmt::format("{:12.8f} {:12.8f} {:12.8f}", R(i, 0), R(i, 1), R(i, 2)));
    }
    const QuaternionWxyz q = quaternion_from_dcm(R);
    line("q_sensor_from_body",
         fmt::format("{:12.9f} {:12.9f} {:12.9f} {:12.9f}  (w x y z)", q(0), q(1), q(2), q(3)));
    const Eigen::Matrix3d& C = r.alignment.angle_covariance_rad2;
    const RollPitchYawReport a = roll_pitch_yaw_report(R, C, gimbal_lock_margin_deg * kDegToRad);
    line("alignment_deg",
         fmt::format("roll {:.4f}  pitch {:.4f}  yaw {:.4f}", a.rpy.roll_rad * kRadToDeg,
                     a.rpy.pitch_rad * kRadToDeg, a.rpy.yaw_rad * kRadToDeg));
    // Roll and yaw alone have no sigma at gimbal lock (the gimbal_lock line gives the one that
    // does), nor any angle when the covariance is unknown: "-".
    const auto sigma_text = [](double sigma_rad) {
      return std::isnan(sigma_rad) ? std::string("-")
                                   : fmt::format("{:.2g}", sigma_rad * kRadToDeg);
    };
    line("alignment_sigma",
         fmt::format("roll {}  pitch {}  yaw {}  (deg)", sigma_text(a.sigma_rad(0)),
                     sigma_text(a.sigma_rad(1)), sigma_text(a.sigma_rad(2))));
    if (!std::isnan(r.alignment.attitude_lag_s))
      line("attitude_lag_s",
           fmt::format("{:.3f} +- {:.3f}{}", r.alignment.attitude_lag_s,
                       r.alignment.attitude_lag_sigma_s,
                       r.alignment.attitude_lag_applied ? " (applied)"
                                                        : " (seen by the check, not applied: "
                                                          "--estimate-attitude-lag fits it)"));
    for (int i = 0; i < 3; ++i) {
      const Eigen::Vector3d c = C.row(i).transpose() * (kRadToDeg * kRadToDeg);
      line(i == 0 ? "alignment_cov_deg2" : "",
           fmt::format("{:12.4e} {:12.4e} {:12.4e}", c(0), c(1), c(2)));
    }
    if (a.singular) {
      line("gimbal_lock",
           fmt::format("pitch within {:g} deg of +-90: roll 0 by convention, {} {:.4f} +- {:.2g} "
                       "deg",
                       gimbal_lock_margin_deg, a.combination_name, a.combination_rad * kRadToDeg,
                       a.combination_sigma_rad * kRadToDeg));
      line("", fmt::format("these angles differ from the rotation by {:.2g} deg: use the "
                           "quaternion for the rotation itself",
                           a.canonical_rotation_error_rad * kRadToDeg));
    }
  } else {
    line("alignment", "not estimated (no reference directions)");
  }
  line("residual_rms_nT", fmt::format("{:.3f}", r.residual_rms_nT));
  // The field error the calibration leaves on the window, and the raw field's (before).
  const auto error_text = [](const ErrorFigures& after, const ErrorFigures& before) {
    return fmt::format("rms {:.4g}  worst {:.4g}  (uncalibrated: rms {:.4g}  worst {:.4g})",
                       after.rms, after.worst, before.rms, before.worst);
  };
  if (r.field_error.direction_deg.n > 0)
    line("field_dir_err_deg", error_text(r.field_error.direction_deg, raw_error.direction_deg));
  if (r.field_error.magnitude_nT.n > 0)
    line("field_mag_err_nT", error_text(r.field_error.magnitude_nT, raw_error.magnitude_nT));
  line("fisher_condition", fmt::format("{:.3g}", r.fisher_condition_number));
  line("iterations", std::to_string(r.iterations));
  line("converged", r.converged ? "yes" : "no");
  if (r.n_downweighted > 0) line("n_downweighted", std::to_string(r.n_downweighted));
  if (!std::isnan(convergence_time_s)) {
    line("convergence_s", fmt::format("{:.0f}", convergence_time_s));
  }
  line("compute_ms", fmt::format("{:.3f}", compute_ms));
}

// The options' usage errors, printed: kExitUsage, or kExitOk when there are none.
int fit_options_error(const FitArgs& args, bool batch, bool filter) {
  if (!batch && !filter) {
    std::cerr << "magcal fit: --method must be centered, twostep, ekf or ukf (got '" << args.method
              << "')\n";
    return kExitUsage;
  }
  if (!(args.sigma_nT > 0.0) || !std::isfinite(args.sigma_nT)) {
    std::cerr << "magcal fit: --sigma-nT must be positive\n";
    return kExitUsage;
  }
  if (args.expected_residual_nT &&
      !(*args.expected_residual_nT > 0.0 && std::isfinite(*args.expected_residual_nT))) {
    std::cerr << "magcal fit: --expected-residual-nT must be positive\n";
    return kExitUsage;
  }
  if (!args.trace_file.empty() && !filter) {
    std::cerr << "magcal fit: --trace is only available for --method ekf|ukf\n";
    return kExitUsage;
  }
  if (args.robust && !batch) {
    std::cerr << "magcal fit: --robust applies to centered/twostep only\n";
    return kExitUsage;
  }
  return kExitOk;
}

// The options of the magnitude-only fit of a recording without reference directions
// (real_data_fit.hpp), which mean nothing where the reference is a body-frame field.
constexpr std::array<const char*, 5> kMagnitudeOnlyOptions = {
    "--estimate-time-offset", "--offset-range-s", "--time-offset-s", "--reference-magnitude",
    "--split-halves"};

std::array<bool, 5> magnitude_only_options_given(const FitArgs& args) {
  return {args.estimate_time_offset, !args.offset_range_s.empty(), args.time_offset_s.has_value(),
          !args.reference_magnitude.empty(), args.split_halves};
}

// For a recording with reference directions: kExitUsage when a magnitude-only option is given.
int magnitude_only_options_error(const FitArgs& args) {
  const std::array<bool, 5> given = magnitude_only_options_given(args);
  for (size_t i = 0; i < given.size(); ++i) {
    if (given[i]) {
      std::cerr << "magcal fit: " << kMagnitudeOnlyOptions[i]
                << " applies to recordings without reference directions only; " << args.input
                << " has a body-frame reference (hx/hy/hz, or a position and an attitude)\n";
      return kExitUsage;
    }
  }
  return kExitOk;
}

// The recording options mean nothing for the design's sample files: say so, never ignore.
// kExitUsage when one is given, else kExitOk.
int recording_options_error(const FitArgs& args) {
  const std::array<bool, 5> given = magnitude_only_options_given(args);
  const std::pair<bool, const char*> recording_only[] = {
      {!args.field_unit.empty(), "--field-unit"}, {args.alt_km.has_value(), "--alt-km"},
      {args.skip_first != 0, "--skip-first"},     {given[0], kMagnitudeOnlyOptions[0]},
      {given[1], kMagnitudeOnlyOptions[1]},       {given[2], kMagnitudeOnlyOptions[2]},
      {given[3], kMagnitudeOnlyOptions[3]},       {given[4], kMagnitudeOnlyOptions[4]}};
  for (const auto& [flag_given, flag] : recording_only) {
    if (flag_given) {
      std::cerr << "magcal fit: " << flag << " applies to recordings in foreign CSV layouts only; "
                << args.input << " is a magcal sample file (design.md)\n";
      return kExitUsage;
    }
  }
  return kExitOk;
}

// centered / twostep: the batch pipeline, with a note when a thermal bias stays unmodelled.
CalibrationResult fit_batch(const FitArgs& args, const SampleSet& samples) {
  BatchCalibrationOptions opt;
  parse_batch_method(args.method, &opt.method);
  opt.sigma_nT = args.sigma_nT;
  opt.robust = args.robust;
  opt.gate_options.expected_residual_nT = gate_expected_residual_nT(args);
  opt.estimate_attitude_lag = args.estimate_attitude_lag;
  CalibrationResult r = calibrate_batch(samples, opt);
  // Temperatures that vary but are too few for the model leave a thermal bias unmodelled: say
  // so (the fit itself cannot tell a thermal swing it does not model from noise).
  const TemperatureSpread spread = temperature_spread(samples);
  if (!r.has_temperature_model && spread.n_with_temperature > 0 &&
      spread.std_C >= kMinTemperatureSpread_C) {
    if (const std::string why =
            temperature_model_unusable(spread, static_cast<int>(samples.size()));
        !why.empty()) {
      std::cerr << fmt::format(
          "magcal fit: note: {}: too few for the bias temperature model (at least {:.0f} % and "
          "{} samples); a thermal bias (temperature spread {:.2g} degC) stays unmodelled\n",
          why, 100.0 * kMinTemperatureSampleFraction, kMinTemperatureSamples, spread.std_C);
    }
  }
  return r;
}

// A refused alignment whose reference came from a recording's quaternions: the fit is tried
// with the usual misreadings of a quaternion (scalar last, the conjugate), and one whose
// alignment is then accepted is named among the rejection reasons, with the fix.
void diagnose_quaternion_reading(const FitArgs& args, const FieldRecording& rec,
                                 CalibrationResult& r) {
  if (r.accepted || rec.has_reference_columns || !rec.has_quaternion_columns) return;
  const auto is_alignment_reason = [](const std::string& reason) {
    return reason.rfind("alignment", 0) == 0;
  };
  if (std::none_of(r.rejection_reasons.begin(), r.rejection_reasons.end(), is_alignment_reason))
    return;
  ReferenceField field;
  for (const QuaternionReading reading :
       {QuaternionReading::kScalarLast, QuaternionReading::kConjugate,
        QuaternionReading::kScalarLastConjugate}) {
    std::string error;
    const SampleSet samples = samples_from_recording(rec, field, &error, reading);
    if (samples.empty()) continue;
    const CalibrationResult tried = fit_batch(args, samples);
    if (std::any_of(tried.rejection_reasons.begin(), tried.rejection_reasons.end(),
                    is_alignment_reason) ||
        !tried.has_alignment)
      continue;
    r.rejection_reasons.push_back(fmt::format(
        "attitude_convention: read as {} the quaternions give an accepted alignment; magcal "
        "reads q0..q3 / qw..qz as w, x, y, z, body from ECI (docs/input-formats.md): reorder or "
        "conjugate them in the file",
        describe(reading)));
    return;
  }
}

// Why the filters cannot take these samples (the batch path's input validation), "" when they
// can.
std::string filter_input_problem(const std::string& input, const SampleSet& samples) {
  const BatchCalibrationOptions check;
  if (static_cast<int>(samples.size()) < check.min_samples) {
    return fmt::format("{}: too few samples: {} < {}", input, samples.size(), check.min_samples);
  }
  for (std::size_t k = 0; k < samples.size(); ++k) {
    if (std::string problem = sample_input_problem(samples[k], check.max_field_nT);
        !problem.empty()) {
      return input + ": " + sample_label(k, samples[k].utime) + ": " + problem;
    }
  }
  const double coverage = direction_coverage_eigenvalues(samples)(0);
  if (!(coverage >= check.min_coverage_eigenvalue)) {
    return fmt::format(
        "unusable geometry: the field direction barely changes (smallest direction-scatter "
        "eigenvalue {:.2g})",
        coverage);
  }
  return "";
}

// The --trace file, written under a temporary name and renamed once complete (a failed run
// leaves no partial trace behind).
class TraceFile {
 public:
  explicit TraceFile(const std::string& path) : path_(path), tmp_path_(path + ".tmp") {}
  ~TraceFile() { discard(); }
  TraceFile(const TraceFile&) = delete;
  TraceFile& operator=(const TraceFile&) = delete;

  // Opens it with its header; false when it cannot be written.
  bool open() {
    file_ = std::fopen(tmp_path_.c_str(), "w");
    if (!file_) return false;
    std::fputs(
        "t_s,b1_nT,b2_nT,b3_nT,D11,D22,D33,D12,D13,D23,sigma_b1_nT,sigma_b2_nT,"
        "sigma_b3_nT,sigma_D11,sigma_D22,sigma_D33,sigma_D12,sigma_D13,sigma_D23,status,"
        "noise_nT,innovation_rho,fisher_condition\n",
        file_);
    return true;
  }
  std::FILE* file() const { return file_; }
  // Closes it under its name; false (and nothing left behind) when it could not be written.
  bool commit() {
    const bool ok = std::fclose(file_) == 0;
    file_ = nullptr;
    std::error_code ec;
    if (ok) std::filesystem::rename(tmp_path_, path_, ec);
    if (!ok || ec) {
      std::filesystem::remove(tmp_path_, ec);
      return false;
    }
    return true;
  }

 private:
  void discard() {
    if (!file_) return;
    std::fclose(file_);
    file_ = nullptr;
    std::error_code ec;
    std::filesystem::remove(tmp_path_, ec);
  }

  std::string path_;
  std::string tmp_path_;
  std::FILE* file_ = nullptr;
};

// The twostep refit that measures the filters' model error. The filters' model has 9
// parameters; where the data show more (the batch refit takes the sensor-model extension), they
// converge to the 9-parameter optimum, a distance the batch refit measures
// (CalibrationResult::model_error). It is in their reported covariance, as the daemon's re-anchor
// passes it (MagnetometerUkf::reanchor); the refit's extension is what their alignment removes
// (estimate_alignment).
CalibrationResult model_error_refit(const FitArgs& args, const SampleSet& samples) {
  BatchCalibrationOptions batch;
  batch.sigma_nT = args.sigma_nT;
  batch.alignment = false;
  batch.gates = false;
  return calibrate_batch(samples, batch);
}

// The samples the filter takes. Where the refit took a temperature model, the filter sees the
// samples moved to its T0, as the daemon's UKF does (TemperatureCorrection): a bias swinging with
// the temperature is faster than the filter follows (the shipped tumbling scenario, +-20 nT per
// orbit: `ok` snapshots up to 16.6 sigma off the current bias without it). Its bias is then the
// bias at T0; a sample without a temperature (none within 60 s) is left out, as there.
SampleSet temperature_corrected(const SampleSet& samples, TemperatureCorrection& temperature) {
  SampleSet filtered;
  filtered.reserve(samples.size());
  for (const CalibrationSample& s : samples) {
    CalibrationSample moved = s;
    if (temperature.correct(s, moved.b_sensor_nT)) filtered.push_back(moved);
  }
  return filtered;
}

// ekf / ukf over the samples in time order, anchored as the daemon's filters are on a refit
// that measured the model error. kExitOk with the result, or the exit code of an error printed.
int fit_filter(const FitArgs& args, SampleSet& samples, CalibrationResult& r,
               double& convergence_time_s) {
  if (const std::string problem = filter_input_problem(args.input, samples); !problem.empty()) {
    std::cerr << "magcal fit: " << problem << "\n";
    return kExitData;
  }
  std::stable_sort(
      samples.begin(), samples.end(),
      [](const CalibrationSample& a, const CalibrationSample& b) { return a.utime < b.utime; });
  std::optional<TraceFile> trace;
  if (!args.trace_file.empty() && !trace.emplace(args.trace_file).open()) {
    std::cerr << "magcal fit: cannot write trace " << args.trace_file << "\n";
    return kExitData;
  }
  // A refit that failed measured nothing: the filter is then never `ok`
  // (FilterOptions::ok_needs_model_error).
  const CalibrationResult refit = model_error_refit(args, samples);
  const bool model_error_measured = refit.status == CalibrationStatus::kOk;
  if (!model_error_measured) {  // the snapshot's reason alone reads "waiting for a refit"
    std::cerr << "magcal fit: note: " << args.input
              << ": the twostep refit that measures the model error gave "
              << to_string(refit.status) << ": " << refit.message
              << "; without it the filter is never ok\n";
  }
  const Matrix9d model_error = refit.model_error_covariance();
  TemperatureCorrection temperature;
  if (model_error_measured) temperature.take_from(refit, 0);
  const SampleSet filtered = temperature_corrected(samples, temperature);
  if (!filtered.empty() && filtered.size() < samples.size()) {
    std::cerr << "magcal fit: note: " << args.input << ": " << samples.size() - filtered.size()
              << " of " << samples.size() << " samples without a temperature within "
              << TemperatureCorrection::kTemperatureHoldMax_utime / 1'000'000
              << " s left out of the filter (the refit's temperature model needs one)\n";
  }
  if (filtered.empty()) {  // (the temperature model needs half the samples to carry one)
    trace.reset();
    std::cerr << "magcal fit: " << args.input << ": no sample carries a temperature within "
              << TemperatureCorrection::kTemperatureHoldMax_utime / 1'000'000
              << " s, which the refit's temperature model needs\n";
    return kExitData;
  }
  std::FILE* const trace_file = trace ? trace->file() : nullptr;
  FilterRun run;
  if (args.method == "ekf") {
    MagnetometerEkf::Options o;
    o.sigma_nT = args.sigma_nT;
    MagnetometerEkf f(o);
    if (model_error_measured) f.set_model_error_covariance(model_error);
    run = run_filter(f, filtered, trace_file);
  } else {
    MagnetometerUkf::Options o;
    o.sigma_nT = args.sigma_nT;
    MagnetometerUkf f(o);
    if (model_error_measured) f.set_model_error_covariance(model_error);
    run = run_filter(f, filtered, trace_file);
  }
  if (trace && !trace->commit()) {
    std::cerr << "magcal fit: cannot write trace " << args.trace_file << "\n";
    return kExitData;
  }
  r = run.result;
  convergence_time_s = run.convergence_time_s;
  finish_filter_result(r, filtered, args.sigma_nT, refit, args.estimate_attitude_lag);
  temperature.describe(r);
  r.field_error = table_field_error(r, samples);  // with the temperature term, on the raw samples
  return kExitOk;
}

}  // namespace

// The residual gate judges against what this sensor should leave: the stated
// --expected-residual-nT, else at least the stated noise (a 600 nT-noise sensor cannot leave the
// paper sensor's 7.5 nT).
double gate_expected_residual_nT(const FitArgs& args) {
  return args.expected_residual_nT ? *args.expected_residual_nT
                                   : std::max(GateOptions{}.expected_residual_nT, args.sigma_nT);
}

namespace {

// One input file (args.input) fitted and printed.
int run_fit_file(const FitArgs& args) {
  const bool batch = args.method == "centered" || args.method == "twostep";
  const bool filter = args.method == "ekf" || args.method == "ukf";
  if (const int usage = fit_options_error(args, batch, filter); usage != kExitOk) return usage;
  const bool csv = args.input == "-" || ends_with(args.input, ".csv");
  if (args.input != "-" && !std::filesystem::exists(args.input)) {
    std::cerr << "magcal fit: input " << args.input << " does not exist\n";
    return kExitData;
  }
  if (!csv && !ends_with(args.input, ".lcm")) {
    std::cerr << "magcal fit: --input must be a .csv or .lcm file, or - (a CSV on standard "
                 "input): "
              << args.input << "\n";
    return kExitUsage;
  }
  Loaded loaded;
  std::optional<FieldRecording> recording;  // a CSV in another layout than the design's
  if (csv) {
    CsvTable table;
    if (const std::string e = read_csv_table(args.input, &table); !e.empty()) {
      std::cerr << "magcal fit: " << e << "\n";
      return kExitData;
    }
    if (is_design_sample_csv_header(table.header)) {
      if (const int usage = recording_options_error(args); usage != kExitOk) return usage;
      loaded = load_sample_csv(table);
    } else {
      FieldRecordingOptions ro;
      if (const int usage = recording_read_options(args, &ro); usage != kExitOk) return usage;
      std::string error;
      recording = read_field_recording(table, ro, &error);
      if (!recording) {
        std::cerr << "magcal fit: " << error << "\n";
        return kExitData;
      }
      if (!recording_has_reference_directions(*recording))
        return run_recording_fit(args, *recording);
      if (const int usage = magnitude_only_options_error(args); usage != kExitOk) return usage;
      ReferenceField field;
      loaded.samples = samples_from_recording(*recording, field, &error);
      if (loaded.samples.empty()) {
        loaded.error = error;
        loaded.exit_code = kExitData;
      }
    }
  } else {
    if (const int usage = recording_options_error(args); usage != kExitOk) return usage;
    loaded = load_samples(args);
  }
  if (!loaded.error.empty()) {
    std::cerr << "magcal fit: " << loaded.error << "\n";
    return loaded.exit_code;
  }
  SampleSet& samples = loaded.samples;

  CalibrationResult r;
  double convergence_time_s = std::numeric_limits<double>::quiet_NaN();
  const auto t_start = std::chrono::steady_clock::now();
  if (batch) {
    r = fit_batch(args, samples);
    if (recording) diagnose_quaternion_reading(args, *recording, r);
  } else if (const int code = fit_filter(args, samples, r, convergence_time_s); code != kExitOk) {
    return code;
  }
  const double compute_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_start).count();

  if (r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable) {
    std::cerr << "magcal fit: " << args.input << ": " << to_string(r.status) << ": " << r.message
              << "\n";
    return kExitData;
  }
  std::cerr << loaded.notes;
  if (recording) note_recording(*recording);
  // The raw field against the reference: what the calibration improves on.
  const FieldError raw_error = field_error(calibrated_field(CalibrationTable{}, samples), samples);
  if (args.json) {
    nlohmann::json j = calibration_result_to_json(r, args.gimbal_lock_margin_deg);
    j["uncalibrated_field_direction_error_deg"] = error_figures_json(raw_error.direction_deg);
    j["uncalibrated_field_magnitude_error_nT"] = error_figures_json(raw_error.magnitude_nT);
    j["compute_ms"] = compute_ms;
    j["input"] = args.input;
    if (filter) j["convergence_time_s"] = json_number(convergence_time_s);
    std::cout << (args.json_lines ? j.dump() : j.dump(2)) << "\n";
  } else {
    print_text(r, raw_error, compute_ms, convergence_time_s, args.gimbal_lock_margin_deg);
  }
  return kExitOk;
}

bool is_glob_pattern(const std::string& s) {
  return s.find_first_of("*?[") != std::string::npos;
}

// The --input values with their globs expanded (sorted, as the shell does); "" or the error.
std::string expand_inputs(const std::vector<std::string>& inputs, std::vector<std::string>* files) {
  for (const std::string& input : inputs) {
    if (!is_glob_pattern(input)) {
      files->push_back(input);
      continue;
    }
    glob_t matches{};
    const int rc = ::glob(input.c_str(), 0, nullptr, &matches);
    if (rc == 0)
      for (size_t i = 0; i < matches.gl_pathc; ++i) files->emplace_back(matches.gl_pathv[i]);
    ::globfree(&matches);
    if (rc != 0) return "--input " + input + ": no file matches";
  }
  if (std::count(files->begin(), files->end(), "-") > 1)
    return "--input -: standard input can be read once";
  return "";
}

}  // namespace

int run_fit(const FitArgs& args) {
  std::vector<std::string> files;
  if (args.inputs.empty()) files.push_back(args.input);
  if (const std::string e = expand_inputs(args.inputs, &files); !e.empty()) {
    std::cerr << "magcal fit: " << e << "\n";
    return kExitUsage;
  }
  FitArgs one = args;
  if (files.size() == 1) {
    one.input = files.front();
    return run_fit_file(one);
  }
  if (!args.trace_file.empty()) {
    std::cerr << "magcal fit: --trace takes one input file (got " << files.size() << ")\n";
    return kExitUsage;
  }
  // One result per file: JSON lines with --json, else each text block under its file's name.
  // A file that fails says why on stderr and the others go on; the exit code is the worst.
  one.json_lines = args.json;
  int worst = kExitOk;
  for (const std::string& file : files) {
    one.input = file;
    if (!args.json) std::cout << "== " << file << "\n" << std::flush;
    worst = std::max(worst, run_fit_file(one));
    std::cout << std::flush;
  }
  return worst;
}

}  // namespace magcal::cli
