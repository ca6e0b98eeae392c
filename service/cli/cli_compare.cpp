// `magcal compare A B [--db DB] [--sat ID] [--samples FILE.csv | --since ISO --until ISO]
//  [--json]`: two calibrations (each a history id, `latest` or a JSON file, as `magcal export`
// takes them) against each other and against a window's reference field (docs/export.md):
// - the difference B - A per parameter in units of its sigma, and its chi-square
//   (pipeline/calibration_difference.hpp);
// - the field error each leaves on the window (pipeline/field_error.hpp: direction in degrees,
//   magnitude in nT, rms and worst), the raw field's, and B's calibrated field against A's;
// - one line of advice: "within the noise: keep A" when the difference is not significant
//   (and both have the same terms), else by the direction and magnitude errors (the magnitude
//   error alone on a window without reference directions): "worth uploading" or "keep A".
// The window: a sample FILE.csv (the format of `magcal sim`), or the samples stored for the
// spacecraft (--db) from --since to --until, by default B's window. Exit: 0 printed; 1 usage;
// 2 data (no such calibration, no samples).
#include <cmath>
#include <iostream>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include <fmt/format.h>

#include "pipeline/calibration_difference.hpp"
#include "pipeline/calibration_table.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/read_only_database.hpp"
#include "service/io/result_json.hpp"
#include "service/io/sample_files.hpp"

namespace magcal::cli {
namespace {

constexpr const char* kParameterNames[9] = {"b1_nT", "b2_nT", "b3_nT", "D11", "D22",
                                            "D33",   "D12",   "D13",   "D23"};

struct Window {
  SampleSet samples;
  std::string name;
};

// The window's samples, or nullopt with the error printed and *exit_code set.
std::optional<Window> load_window(const CompareArgs& args, const CalibrationResult& b,
                                  const CalibrationOrigin& a_origin,
                                  const CalibrationOrigin& b_origin, int* exit_code) {
  const auto fail = [&](int code, const std::string& message) {
    std::cerr << "magcal compare: " << message << "\n";
    *exit_code = code;
    return std::nullopt;
  };
  Window w;
  if (!args.samples.empty()) {
    if (!args.since.empty() || !args.until.empty())
      return fail(kExitUsage, "--since/--until select stored samples (--db), not --samples");
    CsvReadResult csv = read_sample_csv(args.samples);
    if (!csv.ok()) return fail(kExitData, csv.error);
    for (const CsvSampleRow& row : csv.rows) w.samples.push_back(row.sample);
    w.name = args.samples;
  } else if (!args.db.empty()) {
    const std::string sat = !args.sat.empty()          ? args.sat
                            : !b_origin.sat_id.empty() ? b_origin.sat_id
                                                       : a_origin.sat_id;
    if (sat.empty()) return fail(kExitUsage, "whose stored samples? give --sat");
    int64_t t0 = b.window_start_utime, t1 = b.window_end_utime;
    for (auto [text, out, name] :
         {std::tuple{&args.since, &t0, "--since"}, std::tuple{&args.until, &t1, "--until"}}) {
      if (text->empty()) continue;
      const std::optional<int64_t> t = parse_iso8601_utc(*text);
      if (!t) {
        return fail(kExitUsage, std::string(name) + " '" + *text +
                                    "' is not an ISO 8601 UTC time (e.g. 2026-01-01T12:00:00Z)");
      }
      *out = *t;
    }
    std::vector<storage::StoredSample> stored;
    try {
      stored = read_consistently(args.db, [&](storage::Connection& c) {
        std::vector<storage::StoredSample> rows;
        c.make_sample_window_store()->read_window(sat, t0, t1 + 1, rows);
        return rows;
      });
    } catch (const storage::StorageError& e) {
      return fail(kExitData, e.what());
    }
    for (const storage::StoredSample& s : stored)
      w.samples.push_back(calibration_sample_from_stored(s));
    w.name = "stored samples of " + sat + " from " + history_time(t0) + " to " + history_time(t1);
  } else {
    return fail(kExitUsage, "give the window: --samples FILE.csv, or --db (stored samples)");
  }
  if (w.samples.empty()) return fail(kExitData, w.name + ": no samples");
  return w;
}

struct Figures {
  FieldError a, b, between, raw;
};

// The advice line; *upload: whether it says to upload B. Within the noise (same terms, chi2
// not significant): keep A. Otherwise by the field errors on the window: B when it lowers both
// rms errors, A when it lowers neither; when it lowers one and raises the other, B when the
// factor it gains exceeds the factor it loses. Without reference directions: the magnitude
// error alone.
std::string advice(const CalibrationDifference& d, const Figures& f, bool* upload) {
  *upload = false;
  const bool known = !std::isnan(d.chi2);
  if (known && !d.significant && d.same_model) return "within the noise: keep A";
  const std::string caveat = known ? "" : " (the difference's uncertainty is unknown)";
  const auto deg = [](double v) { return fmt::format("{:.3g}°", v); };
  const auto nT = [](double v) { return fmt::format("{:.3g} nT", v); };
  const ErrorFigures &ma = f.a.magnitude_nT, &mb = f.b.magnitude_nT;
  const bool direction = f.a.direction_deg.n > 0 && f.b.direction_deg.n > 0;
  if (!direction) {
    *upload = mb.rms < ma.rms;
    return *upload ? fmt::format("B improves the magnitude error from {} to {}: worth uploading{}",
                                 nT(ma.rms), nT(mb.rms), caveat)
                   : fmt::format(
                         "B does not improve the magnitude error ({} against {} with A): "
                         "keep A{}",
                         nT(mb.rms), nT(ma.rms), caveat);
  }
  const ErrorFigures &da = f.a.direction_deg, &db = f.b.direction_deg;
  const bool direction_better = db.rms < da.rms, magnitude_better = mb.rms < ma.rms;
  if (direction_better && magnitude_better) {
    *upload = true;
    return fmt::format(
        "B improves the direction error from {} to {} and the magnitude error from {} to {}: "
        "worth uploading{}",
        deg(da.rms), deg(db.rms), nT(ma.rms), nT(mb.rms), caveat);
  }
  if (!direction_better && !magnitude_better) {
    return fmt::format(
        "B does not improve the direction error ({} against {} with A) nor the magnitude error "
        "({} against {}): keep A{}",
        deg(db.rms), deg(da.rms), nT(mb.rms), nT(ma.rms), caveat);
  }
  // One better, one worse: the larger factor decides.
  const double direction_factor = da.rms / db.rms, magnitude_factor = ma.rms / mb.rms;
  *upload = direction_factor * magnitude_factor > 1.0;
  const std::string gained =
      direction_better ? fmt::format("the direction error from {} to {}", deg(da.rms), deg(db.rms))
                       : fmt::format("the magnitude error from {} to {}", nT(ma.rms), nT(mb.rms));
  const std::string lost =
      direction_better ? fmt::format("the magnitude error from {} to {}", nT(ma.rms), nT(mb.rms))
                       : fmt::format("the direction error from {} to {}", deg(da.rms), deg(db.rms));
  return fmt::format("B improves {} but raises {}: {}{}", gained, lost,
                     *upload ? "worth uploading" : "keep A", caveat);
}

nlohmann::json figures_json(const FieldError& e) {
  return {{"direction_deg", error_figures_json(e.direction_deg)},
          {"magnitude_nT", error_figures_json(e.magnitude_nT)}};
}

nlohmann::json side_json(const CalibrationResult& r, const CalibrationOrigin& o) {
  nlohmann::json j = calibration_result_to_json(r);
  j["source"] = o.source;
  if (!o.sat_id.empty()) j["sat_id"] = o.sat_id;
  if (o.id > 0) j["id"] = o.id;
  return j;
}

void print_text(const Window& w, const CalibrationResult& a, const CalibrationOrigin& ao,
                const CalibrationResult& b, const CalibrationOrigin& bo,
                const CalibrationDifference& d, const Figures& f, const std::string& advice_line) {
  auto line = [](const std::string& key, const std::string& value) {
    std::cout << fmt::format("{:<22}{}\n", key, value);
  };
  int n_direction = 0;
  for (const CalibrationSample& s : w.samples) n_direction += s.has_reference_direction ? 1 : 0;
  line("window", fmt::format("{}: {} samples ({} with a reference direction)", w.name,
                             w.samples.size(), n_direction));
  for (const auto& [name, r, o] : {std::tuple{"A", &a, &ao}, std::tuple{"B", &b, &bo}}) {
    line(name, fmt::format("{}: {}, epoch {}, {}{}", o->source, r->method, history_time(r->utime),
                           r->accepted ? "accepted" : "rejected",
                           r->has_alignment ? "" : ", no alignment (R = I)"));
  }
  std::cout << fmt::format("{:<22}{:>16} {:>16} {:>14} {:>8}\n", "parameter", "A", "B", "B - A",
                           "sigmas");
  const Vector9d pa = a.parameters.packed(), pb = b.parameters.packed();
  for (int i = 0; i < 9; ++i) {
    if (i < 3) {
      std::cout << fmt::format("{:<22}{:16.3f} {:16.3f} {:14.3f} {:8.2f}\n", kParameterNames[i],
                               pa(i), pb(i), d.dp(i), d.z(i));
    } else {
      std::cout << fmt::format("{:<22}{:16.8f} {:16.8f} {:14.3e} {:8.2f}\n", kParameterNames[i],
                               pa(i), pb(i), d.dp(i), d.z(i));
    }
  }
  if (d.has_alignment) {
    line("alignment B from A", fmt::format("{:.4f} deg (chi2 {:.3g} of 3)",
                                           d.dtheta_rad.norm() * kRadToDeg, d.alignment_chi2));
  }
  line("difference", fmt::format("chi2 {:.3g} of 9 (99 % limit {:.3g}): {}", d.chi2,
                                 CalibrationDifference::kChi2Quantile99_9dof,
                                 std::isnan(d.chi2) ? "uncertainty unknown"
                                 : d.significant    ? "significant"
                                 : d.same_model     ? "within the noise"
                                                    : "within the noise on the terms both have"));
  std::cout << fmt::format("{:<22}{:>12} {:>12}\n", "field error", "rms", "worst");
  const auto row = [](const std::string& name, const ErrorFigures& e) {
    if (e.n == 0) return;
    std::cout << fmt::format("{:<22}{:12.4g} {:12.4g}\n", name, e.rms, e.worst);
  };
  row("  direction A (deg)", f.a.direction_deg);
  row("  direction B (deg)", f.b.direction_deg);
  row("  direction raw (deg)", f.raw.direction_deg);
  row("  magnitude A (nT)", f.a.magnitude_nT);
  row("  magnitude B (nT)", f.b.magnitude_nT);
  row("  magnitude raw (nT)", f.raw.magnitude_nT);
  row("  B vs A dir. (deg)", f.between.direction_deg);
  row("  B vs A mag. (nT)", f.between.magnitude_nT);
  line("advice", advice_line);
}

}  // namespace

int run_compare(const CompareArgs& args) {
  int code = kExitOk;
  const auto a = load_named_calibration(args.a, args.db, args.sat, "compare", &code);
  if (!a) return code;
  const auto b = load_named_calibration(args.b, args.db, args.sat, "compare", &code);
  if (!b) return code;
  const std::optional<Window> w = load_window(args, b->first, a->second, b->second, &code);
  if (!w) return code;

  const std::vector<Eigen::Vector3d> field_a =
      calibrated_field(calibration_table(a->first), w->samples);
  const std::vector<Eigen::Vector3d> field_b =
      calibrated_field(calibration_table(b->first), w->samples);
  Figures f;
  f.a = field_error(field_a, w->samples);
  f.b = field_error(field_b, w->samples);
  f.between = field_difference(field_a, field_b);
  f.raw = field_error(calibrated_field(CalibrationTable{}, w->samples), w->samples);
  const CalibrationDifference d = calibration_difference(a->first, b->first);
  bool upload = false;
  const std::string advice_line = advice(d, f, &upload);

  if (!args.json) {
    print_text(*w, a->first, a->second, b->first, b->second, d, f, advice_line);
    return kExitOk;
  }
  nlohmann::json j;
  j["window"] = {{"name", w->name}, {"n_samples", w->samples.size()}};
  j["a"] = side_json(a->first, a->second);
  j["b"] = side_json(b->first, b->second);
  nlohmann::json diff;
  for (const auto& [key, v] :
       {std::pair{"dp", &d.dp}, std::pair{"sigma", &d.sigma}, std::pair{"z", &d.z}}) {
    nlohmann::json values = nlohmann::json::array();
    for (int i = 0; i < 9; ++i) values.push_back(json_number((*v)(i)));
    diff[key] = values;
  }
  diff["chi2"] = json_number(d.chi2);
  diff["dof"] = 9;
  diff["significant"] = d.significant;
  diff["same_model"] = d.same_model;
  if (d.has_alignment) {
    diff["alignment_deg"] = json_number(d.dtheta_rad.norm() * kRadToDeg);
    diff["alignment_chi2"] = json_number(d.alignment_chi2);
  }
  j["difference"] = diff;
  j["field_error"] = {{"a", figures_json(f.a)},
                      {"b", figures_json(f.b)},
                      {"raw", figures_json(f.raw)},
                      {"b_against_a", figures_json(f.between)}};
  j["advice"] = advice_line;
  j["upload_b"] = upload;
  std::cout << j.dump(2) << "\n";
  return kExitOk;
}

}  // namespace magcal::cli
