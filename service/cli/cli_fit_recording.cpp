// `magcal fit` on a real recording in a foreign CSV layout: reads the recording,
// runs service/analysis/real_data_fit.hpp and prints its report as text or JSON.
#include <filesystem>
#include <iostream>

#include <fmt/format.h>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/analysis/real_data_fit.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/result_json.hpp"

namespace magcal::cli {
namespace {

void print_text(const RecordingFitReport& rep, const FieldRecording& rec) {
  const CalibrationResult& r = rep.result;
  auto line = [](const char* key, const std::string& value) {
    std::cout << fmt::format("{:<22}{}\n", key, value);
  };
  auto v3 = [](const Eigen::Vector3d& v, const char* f = "{:12.3f}") {
    return fmt::format(fmt::runtime(std::string(f) + " " + f + " " + f), v(0), v(1), v(2));
  };
  line("method", r.method);
  line("status", to_string(r.status));
  line("verdict", r.accepted ? "accepted" : "rejected");
  for (const std::string& reason : r.rejection_reasons) line("  reason", reason);
  line("reference", rep.reference);
  if (rep.sphere)
    line("sphere_fit",
         fmt::format("radius {:.1f} nT, centre {}, rms {:.1f} nT", rep.sphere->radius_nT,
                     v3(rep.sphere->center_nT, "{:.1f}"), rep.sphere->residual_rms_nT));
  if (rep.reference == "constant")
    line("reference_nT", fmt::format("{:.1f}", rep.reference_magnitude_nT));
  line("n_samples", std::to_string(r.n_samples));
  line("sigma_nT", fmt::format("{:.1f}{}", rep.sigma_used_nT,
                               rep.sigma_estimated ? " (estimated from the residual)" : ""));
  if (rep.time_offset_applied) {
    if (rep.offset_estimate)
      line("time_offset_s",
           fmt::format("{:.2f} +- {:.2f} (searched {:.0f}..{:.0f} s)", rep.time_offset_s,
                       rep.offset_estimate->sigma_tau_s, rep.offset_estimate->profile_tau_s.front(),
                       rep.offset_estimate->profile_tau_s.back()));
    else
      line("time_offset_s", fmt::format("{:.2f} (given)", rep.time_offset_s));
  }
  line("bias_nT", v3(r.parameters.bias_nT));
  line("bias_sigma_nT", v3(r.bias_sigma_nT()));
  for (int i = 0; i < 3; ++i)
    line(i == 0 ? "D" : "", v3(r.parameters.D.row(i).transpose(), "{:12.6f}"));
  line("residual_rms_nT", fmt::format("{:.1f}", r.residual_rms_nT));
  if (rep.time_offset_applied)
    line("rms_offset_ignored_nT", fmt::format("{:.1f}", rep.residual_rms_zero_offset_nT));
  if (rep.first_half && rep.second_half) {
    int i = 1;
    for (const RecordingFitReport* hr : {rep.first_half.get(), rep.second_half.get()}) {
      const CalibrationResult* h = &hr->result;
      line(
          i++ == 1 ? "half_1" : "half_2",
          fmt::format("b {}  diag(D) {}  rms {:.1f}  tau {:.1f} s",
                      v3(h->parameters.bias_nT, "{:.0f}"), v3(h->parameters.D.diagonal(), "{:.4f}"),
                      h->residual_rms_nT, hr->time_offset_applied ? hr->time_offset_s : 0.0));
    }
  }
  if (rec.has_quaternion_columns) {
    line("missing_quaternions", std::to_string(rec.n_missing_quaternion));
    if (rep.alignment.estimated) {
      const RollPitchYaw& a = rep.alignment.rpy;
      line("alignment_deg",
           fmt::format("roll {:.3f}  pitch {:.3f}  yaw {:.3f}", a.roll_rad * kRadToDeg,
                       a.pitch_rad * kRadToDeg, a.yaw_rad * kRadToDeg));
      line("alignment_iter", std::to_string(rep.alignment.joint.iterations));
      line("field_enu_nT", v3(rep.alignment.field_enu_nT, "{:.1f}"));
      line("enu_std_nT", v3(rep.alignment.enu_std_nT, "{:.1f}"));
      line("enu_std_identity_nT", v3(rep.alignment.enu_std_identity_nT, "{:.1f}"));
    } else {
      line("alignment", rep.alignment.message);
    }
  }
}

}  // namespace

int recording_read_options(const FitArgs& args, FieldRecordingOptions* ro) {
  if (!args.field_unit.empty()) {
    ro->field_unit = parse_field_unit(args.field_unit);
    if (!ro->field_unit) {
      std::cerr << "magcal fit: --field-unit must be nT, uT, G or mG\n";
      return kExitUsage;
    }
  }
  if (args.skip_first < 0) {
    std::cerr << "magcal fit: --skip-first must be >= 0\n";
    return kExitUsage;
  }
  ro->skip_first = args.skip_first;
  ro->altitude_km = args.alt_km;
  return kExitOk;
}

int run_recording_fit(const FitArgs& args, const FieldRecording& recording) {
  const FieldRecording* const rec = &recording;
  if (args.method != "centered" && args.method != "twostep") {
    std::cerr << "magcal fit: " << rec->source
              << ": a recording without reference directions (no hx/hy/hz, nor a position with "
                 "an attitude quaternion) is fitted with --method centered|twostep\n";
    return kExitUsage;
  }
  if (args.estimate_attitude_lag) {
    std::cerr << "magcal fit: --estimate-attitude-lag needs reference directions (hx/hy/hz, or "
                 "a position with an attitude quaternion); this recording's alignment is checked "
                 "for quaternion conventions instead\n";
    return kExitUsage;
  }

  RecordingFitOptions fo;
  parse_batch_method(args.method, &fo.batch.method);
  fo.batch.robust = args.robust;
  if (args.sigma_given) fo.sigma_nT = args.sigma_nT;
  fo.batch.gate_options.expected_residual_nT = gate_expected_residual_nT(args);
  fo.estimate_time_offset = args.estimate_time_offset;
  fo.time_offset_s = args.time_offset_s;
  fo.split_halves = args.split_halves;
  if (!args.offset_range_s.empty()) {
    const auto colon = args.offset_range_s.find(':');
    try {
      if (colon == std::string::npos) throw std::invalid_argument("no colon");
      std::size_t n1 = 0, n2 = 0;
      const std::string a = args.offset_range_s.substr(0, colon);
      const std::string b = args.offset_range_s.substr(colon + 1);
      fo.offset_min_s = std::stod(a, &n1);
      fo.offset_max_s = std::stod(b, &n2);
      if (n1 != a.size() || n2 != b.size()) throw std::invalid_argument("trailing");
    } catch (const std::exception&) {
      std::cerr << "magcal fit: --offset-range-s must be MIN:MAX in seconds (got '"
                << args.offset_range_s << "')\n";
      return kExitUsage;
    }
  }
  if (!args.reference_magnitude.empty()) {
    if (args.reference_magnitude == "auto") {
      fo.reference_magnitude_auto = true;
    } else {
      try {
        std::size_t n = 0;
        fo.reference_magnitude_nT = std::stod(args.reference_magnitude, &n);
        if (n != args.reference_magnitude.size()) throw std::invalid_argument("trailing");
      } catch (const std::exception&) {
        std::cerr << "magcal fit: --reference-magnitude must be auto or a value in nT\n";
        return kExitUsage;
      }
    }
  }
  if (const std::string e = fo.validate(); !e.empty()) {
    std::cerr << "magcal fit: " << e << "\n";
    return kExitUsage;
  }
  std::string error;
  const std::optional<RecordingFitReport> rep = fit_recording(*rec, fo, &error);
  if (!rep) {
    std::cerr << "magcal fit: " << args.input << ": " << error << "\n";
    return kExitData;
  }
  const CalibrationResult& r = rep->result;
  if (r.status == CalibrationStatus::kFailed || r.status == CalibrationStatus::kUnobservable) {
    std::cerr << "magcal fit: " << args.input << ": " << to_string(r.status) << ": " << r.message
              << "\n";
    return kExitData;
  }
  note_recording(*rec);
  if (rec->has_temperature_column) {
    std::cerr << "magcal fit: " << rec->source
              << ": the temperature is not modelled in a fit against |H| alone (no hx/hy/hz, nor "
                 "a position with an attitude quaternion): the bias is the window's mean\n";
  }
  if (args.json) {
    nlohmann::json j = recording_fit_to_json(*rep, *rec);
    j["input"] = args.input;
    std::cout << (args.json_lines ? j.dump() : j.dump(2)) << "\n";
  } else {
    print_text(*rep, *rec);
  }
  return kExitOk;
}

}  // namespace magcal::cli
