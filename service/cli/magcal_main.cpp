// magcal: the operator's command-line tool. Parses arguments (the only CLI11 translation unit)
// and dispatches to the subcommands in cli_*.cpp. Exit codes: 0 ok, 1 usage, 2 data/database.
#include <charconv>
#include <cmath>
#include <cstdint>
#include <functional>
#include <iostream>
#include <limits>
#include <optional>
#include <sstream>
#include <string>
#include <utility>

#include <CLI/CLI.hpp>

#include "pipeline/scenario.hpp"
#include "service/cli/cli_commands.hpp"
#include "storage/connection.hpp"

namespace {

// Checks of numeric option text, run by CLI11 before it converts: a bad value gets one clear
// sentence ("--limit must be at least 1 (got 0)") instead of CLI11's raw range text or
// "Could not convert", and a negative seed is refused instead of wrapping to 2^64 - 1. What a
// value must be beyond this (a positive duration, a valid angle) is checked by the run_*
// functions, which know why.

// `text` (with an optional leading '+') read as one T, all of it: std::errc() on success,
// invalid_argument when it is no such number, result_out_of_range when it is one beyond T.
template <typename T>
std::errc parse_number_text(const std::string& text, T* value) {
  std::string_view digits(text);
  if (!digits.empty() && digits.front() == '+') digits.remove_prefix(1);
  const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), *value);
  if (digits.empty() || end != digits.data() + digits.size()) return std::errc::invalid_argument;
  return ec;
}

CLI::Validator whole_number(int64_t min, int64_t max) {
  return CLI::Validator(
      [min, max](std::string& text) -> std::string {
        int64_t value = 0;
        const std::errc ec = parse_number_text(text, &value);
        if (ec == std::errc::invalid_argument) return "must be a whole number (got '" + text + "')";
        const bool below_int64 = ec == std::errc::result_out_of_range && text.front() == '-';
        if (below_int64 || (ec == std::errc() && value < min))
          return "must be at least " + std::to_string(min) + " (got " + text + ")";
        if (ec != std::errc() || value > max)
          return "must be at most " + std::to_string(max) + " (got " + text + ")";
        return "";
      },
      "INT");
}

// A seed: any whole number in [0, 2^64 - 1].
CLI::Validator seed_number() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        uint64_t value = 0;
        if (parse_number_text(text, &value) != std::errc())
          return "must be a whole number from 0 to 18446744073709551615 (got '" + text + "')";
        return "";
      },
      "SEED");
}

// --db: an SQLite file or a postgresql:// URI; a mistyped URI scheme is a bad argument (exit 1),
// not a database that cannot be opened (exit 2).
CLI::Option* add_db_option(CLI::App* command, std::string& db, bool required = true) {
  return command->add_option("--db", db, "SQLite database file or postgresql:// URI")
      ->required(required)
      ->check(CLI::Validator(
          [](std::string& text) { return magcal::storage::database_value_error(text); }, "DB"));
}

// A finite decimal number (the run_* functions check its range).
CLI::Validator real_number() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        double value = 0.0;
        if (parse_number_text(text, &value) != std::errc() || !std::isfinite(value))
          return "must be a finite number (got '" + text + "')";
        return "";
      },
      "NUMBER");
}

// A finite decimal number in [min, max].
CLI::Validator real_number_in(double min, double max) {
  return CLI::Validator(
      [min, max](std::string& text) -> std::string {
        double value = 0.0;
        if (parse_number_text(text, &value) != std::errc() || !std::isfinite(value))
          return "must be a finite number (got '" + text + "')";
        if (value < min || value > max)
          return (std::ostringstream()
                  << "must be from " << min << " to " << max << " (got " << text << ")")
              .str();
        return "";
      },
      "NUMBER");
}

constexpr int64_t kIntMax = std::numeric_limits<int>::max();

// "paper, pure, tumbling": every built-in scenario, for the help of --scenario.
std::string preset_list() {
  std::string names;
  for (const auto& name : magcal::scenario_preset_names()) {
    names += (names.empty() ? "" : ", ") + name;
  }
  return names;
}

// A first argument that is neither an option nor a subcommand: CLI11 would only say "A
// subcommand is required". Returns the one line naming it, or "" when there is none.
std::string unknown_subcommand(const CLI::App& app, int argc, char** argv) {
  if (argc < 2 || argv[1][0] == '-') return "";
  const std::string word = argv[1];
  std::string names;
  for (const CLI::App* sub : app.get_subcommands({})) {
    if (sub->get_name() == word) return "";
    names += (names.empty() ? "" : ", ") + sub->get_name();
  }
  return "unknown subcommand '" + word + "' (subcommands: " + names + ")";
}

// `magcal field`: IGRF at a point, given geocentric (--r-km, --colat-deg) or geodetic
// (--lat-deg, --alt-km) coordinates.
CLI::App* add_field_command(CLI::App& app, magcal::cli::FieldArgs& args) {
  CLI::App* const command = app.add_subcommand("field", "IGRF field at a point");
  command->add_option("--time", args.time_iso, "UTC time, ISO 8601")->required();
  auto* r_opt =
      command->add_option("--r-km", args.r_km, "geocentric radius, km")->check(real_number());
  auto* colat_opt = command->add_option("--colat-deg", args.colat_deg, "geocentric colatitude, deg")
                        ->check(real_number());
  auto* lat_opt = command->add_option("--lat-deg", args.lat_deg, "geodetic (WGS-84) latitude, deg")
                      ->check(real_number());
  auto* alt_opt = command->add_option("--alt-km", args.alt_km, "altitude above WGS-84, km")
                      ->check(real_number());
  command->add_option("--lon-deg", args.lon_deg, "longitude, deg east")
      ->required()
      ->check(real_number());
  command->add_option("--coefficients", args.coefficients_file,
                      "IGRF coefficient file (official .txt or .shc); default built-in IGRF-14");
  command->add_flag("--json", args.json, "print JSON");
  r_opt->excludes(lat_opt)->excludes(alt_opt);
  colat_opt->excludes(lat_opt)->excludes(alt_opt);
  return command;
}

// `magcal sim`: a simulated spacecraft magnetometer into a sample file.
CLI::App* add_sim_command(CLI::App& app, magcal::cli::SimArgs& args) {
  CLI::App* const command = app.add_subcommand("sim", "simulate a spacecraft magnetometer");
  command->add_option("--scenario", args.scenario,
                      "preset name (" + preset_list() + ") or scenario FILE.toml");
  command->add_option("--hours", args.hours, "duration, hours (overrides the scenario)")
      ->check(real_number());
  command->add_option("--seed", args.seed, "random seed (overrides the scenario)")
      ->check(seed_number());
  command->add_option("--out", args.out, "output FILE.lcm (LCM log) or FILE.csv")->required();
  command->add_option("--truth", args.truth, "write the true parameters to FILE.json");
  command->add_option("--sat-id", args.sat_id, "spacecraft id (overrides the scenario)");
  command
      ->add_option("--batch", args.batch_size,
                   "LCM output: mag_batch_t packets of N samples on MAGCAL_BATCH")
      ->check(whole_number(0, kIntMax));
  return command;
}

// `magcal fit`: a calibration from a sample file or a recording in a foreign CSV layout.
CLI::App* add_fit_command(CLI::App& app, magcal::cli::FitArgs& args) {
  CLI::App* const command = app.add_subcommand("fit", "calibrate from a file");
  command
      ->add_option("--input", args.inputs,
                   "FILE.csv, FILE.lcm, or - (a CSV on standard input); several files (repeated, "
                   "listed or a glob 'day*.csv'): one result per file (JSON lines with --json)")
      ->required();
  command->add_option("--method", args.method, "centered|twostep|ekf|ukf")
      ->check(CLI::IsMember({"centered", "twostep", "ekf", "ukf"}));
  const CLI::Option* sigma =
      command->add_option("--sigma-nT", args.sigma_nT, "measurement noise, nT per axis (default 3)")
          ->check(real_number());
  command->add_flag("--robust", args.robust,
                    "centered/twostep: find outliers (Huber IRLS, robust scale), fit without them");
  command->add_option("--sat", args.sat, "spacecraft id (required when a log holds several)");
  command->add_option("--trace", args.trace_file,
                      "ekf/ukf: write state and 1-sigma per sample (CSV)");
  command->add_flag("--json", args.json, "print JSON");
  command
      ->add_option("--gimbal-lock-margin-deg", args.gimbal_lock_margin_deg,
                   "roll/yaw reported as a canonical split (roll 0) within this of pitch +-90 deg "
                   "(default 2)")
      ->check(real_number_in(0.0, 45.0));
  command->add_option("--field-unit", args.field_unit, "recording CSV: field unit nT|uT|G|mG");
  command->add_option("--alt-km", args.alt_km, "recording CSV: assumed altitude (km) when absent")
      ->check(real_number());
  command->add_option("--skip-first", args.skip_first, "recording CSV: drop the first N rows")
      ->check(whole_number(0, kIntMax));
  command->add_flag("--estimate-attitude-lag", args.estimate_attitude_lag,
                    "sample files: fit the attitude-magnetometer time lag with the alignment");
  command->add_flag("--estimate-time-offset", args.estimate_time_offset,
                    "recording CSV: estimate the time-tag offset of the position stream");
  command->add_option("--offset-range-s", args.offset_range_s,
                      "MIN:MAX search range of the offset (default -1000:1000)");
  command
      ->add_option("--time-offset-s", args.time_offset_s,
                   "recording CSV: apply this offset (reference at t + tau)")
      ->check(real_number());
  command->add_option("--reference-magnitude", args.reference_magnitude,
                      "recording CSV: constant field magnitude, auto|VALUE_nT");
  command->add_flag("--split-halves", args.split_halves,
                    "recording CSV: also fit the two halves separately");
  command
      ->add_option("--expected-residual-nT", args.expected_residual_nT,
                   "expected residual rms for the acceptance gate (default max(7.5, --sigma-nT))")
      ->check(real_number());
  command->footer(
      "CSV input (docs/input-formats.md): a header row naming the columns (any order; others "
      "are ignored and named on stderr), separated by , ; or tab; quotes and a byte-order mark "
      "are fine. Accepted names (compared in lower case; a unit may follow in parentheses, "
      "\"Bx (uT)\"):\n" +
      magcal::recording_column_table_text() +
      "Field columns need a unit: a suffix _nT _uT _G _mG, a unit in parentheses, or "
      "--field-unit. With hx/hy/hz, or a position and a quaternion, every --method applies and "
      "the alignment is estimated (with a temperature column, the temperature model too); "
      "without, centered|twostep fit |B| only. Rows with an empty or non-finite value are "
      "dropped, rows are sorted by time, exact repeats dropped: counted on stderr.\n");
  command->callback([&args, sigma] { args.sigma_given = sigma->count() > 0; });
  return command;
}

// `magcal evaluate`: the Monte-Carlo evaluation against truth.
CLI::App* add_evaluate_command(CLI::App& app, magcal::cli::EvaluateArgs& args) {
  CLI::App* const command =
      app.add_subcommand("evaluate", "Monte-Carlo evaluation against the paper");
  command->add_option("--scenario", args.scenario,
                      "preset name (" + preset_list() + ") or FILE.toml");
  command->add_option("--runs", args.runs, "Monte-Carlo runs")->check(whole_number(1, kIntMax));
  command->add_option("--seed", args.seed, "first random seed")->check(seed_number());
  command->add_flag("--json", args.json, "print JSON");
  return command;
}

// `magcal refit`, `history`, `status` and `serve` read (refit: and write) a database.
CLI::App* add_refit_command(CLI::App& app, magcal::cli::RefitArgs& args) {
  CLI::App* const command =
      app.add_subcommand("refit", "run an offline refit of a stored window now");
  add_db_option(command, args.db);
  command->add_option("--sat", args.sat, "spacecraft id")->required();
  command->add_option("--config", args.config, "magcald config (gates, sigma, window)");
  command->add_flag("--json", args.json, "print JSON");
  return command;
}

CLI::App* add_history_command(CLI::App& app, magcal::cli::HistoryArgs& args) {
  CLI::App* const command = app.add_subcommand("history", "query stored calibration results");
  add_db_option(command, args.db);
  command->add_option("--sat", args.sat, "spacecraft id")->required();
  command->add_option("--method", args.method, "ukf|ekf|centered|twostep");
  command->add_option("--since", args.since, "ISO 8601 UTC, inclusive");
  command->add_option("--until", args.until, "ISO 8601 UTC, inclusive");
  command->add_option("--limit", args.limit, "only the N newest")->check(whole_number(1, kIntMax));
  command->add_option("--order", args.order, "asc|desc (default asc)")
      ->check(CLI::IsMember({"asc", "desc"}));
  command->add_option("--format", args.format, "table|csv|json")
      ->check(CLI::IsMember({"table", "csv", "json"}));
  return command;
}

// `magcal export` and `compare` name calibrations as a history id, `latest` or a JSON file.
constexpr const char* kCalibrationHelp =
    "history id (--db), 'latest' (--db --sat: newest accepted refit) or FILE.json (fit --json)";

CLI::App* add_export_command(CLI::App& app, magcal::cli::ExportArgs& args) {
  CLI::App* const command = app.add_subcommand(
      "export", "a calibration as an uplink table: B_cal = M B - o (body frame), float32");
  command->add_option("calibration", args.calibration, kCalibrationHelp)->required();
  add_db_option(command, args.db, false);
  command->add_option("--sat", args.sat, "spacecraft id (with latest)");
  command->add_option("--format", args.format, "json|csv (default json)")
      ->check(CLI::IsMember({"json", "csv"}));
  command->add_option("--out", args.out, "write to FILE (default stdout)");
  command
      ->add_option("--rounding-field-nT", args.rounding_field_nT,
                   "|B| the stated float32 rounding error is for (default 70000)")
      ->check(real_number());
  return command;
}

CLI::App* add_compare_command(CLI::App& app, magcal::cli::CompareArgs& args) {
  CLI::App* const command = app.add_subcommand(
      "compare", "two calibrations: their difference and the field error each leaves");
  command->add_option("a", args.a, std::string("A: ") + kCalibrationHelp)->required();
  command->add_option("b", args.b, "B: the candidate, as A")->required();
  add_db_option(command, args.db, false);
  command->add_option("--sat", args.sat, "spacecraft id (latest, stored samples)");
  command->add_option("--samples", args.samples, "the window: a sample FILE.csv");
  command->add_option("--since", args.since,
                      "stored samples from (ISO 8601 UTC; default B's window)");
  command->add_option("--until", args.until, "stored samples to (ISO 8601 UTC, inclusive)");
  command->add_flag("--json", args.json, "print JSON");
  return command;
}

CLI::App* add_status_command(CLI::App& app, magcal::cli::StatusArgs& args) {
  CLI::App* const command = app.add_subcommand("status", "per-spacecraft summary");
  add_db_option(command, args.db);
  command->add_flag("--json", args.json, "print JSON");
  return command;
}

CLI::App* add_serve_command(CLI::App& app, magcal::cli::ServeArgs& args) {
  CLI::App* const command = app.add_subcommand(
      "serve", "HTTP operations server over a database (read-only): API, plots page");
  add_db_option(command, args.db);
  command->add_option("--listen", args.listen,
                      "ADDR:PORT to listen on (default 127.0.0.1:9780; port 0: any free)");
  return command;
}

// Parses the command line into the subcommands' arguments: nullopt to go on, else the exit code
// (help, version, or a usage error printed).
std::optional<int> parse_command_line(CLI::App& app, int argc, char** argv) {
  using magcal::cli::kExitUsage;
  if (const std::string error = unknown_subcommand(app, argc, argv); !error.empty()) {
    std::cerr << "magcal: " << error << "\n";
    return kExitUsage;
  }
  // Named after the subcommand, as every later error is ("magcal history: ...").
  const std::string command = argc >= 2 && argv[1][0] != '-' ? std::string(" ") + argv[1] : "";
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ValidationError& e) {
    // "--limit: must be at least 1 (got 0)" from the checks above: said as one sentence.
    std::string text = e.what();
    if (const auto colon = text.find(": "); colon != std::string::npos) text.erase(colon, 1);
    std::cerr << "magcal" << command << ": " << text << "\n";
    return kExitUsage;
  } catch (const CLI::ParseError& e) {
    std::cerr << "magcal" << command << ": " << e.what() << " (see magcal" << command
              << " --help)\n";
    return kExitUsage;
  }
  return std::nullopt;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace magcal::cli;
  CLI::App app{"magcal - spacecraft magnetometer calibration (version " MAGCAL_VERSION ")"};
  app.require_subcommand(1);
  app.set_version_flag("--version", MAGCAL_VERSION);
  FieldArgs field;
  SimArgs sim;
  FitArgs fit;
  EvaluateArgs evaluate;
  RefitArgs refit;
  HistoryArgs history;
  StatusArgs status;
  ServeArgs serve;
  ExportArgs export_args;
  CompareArgs compare;
  // In the order of --help; the one the command line names runs.
  const std::pair<const CLI::App*, std::function<int()>> subcommands[] = {
      {add_field_command(app, field), [&] { return run_field(field); }},
      {add_sim_command(app, sim), [&] { return run_sim(sim); }},
      {add_fit_command(app, fit), [&] { return run_fit(fit); }},
      {add_evaluate_command(app, evaluate), [&] { return run_evaluate(evaluate); }},
      {add_refit_command(app, refit), [&] { return run_refit(refit); }},
      {add_history_command(app, history), [&] { return run_history(history); }},
      {add_export_command(app, export_args), [&] { return run_export(export_args); }},
      {add_compare_command(app, compare), [&] { return run_compare(compare); }},
      {add_status_command(app, status), [&] { return run_status(status); }},
      {add_serve_command(app, serve), [&] { return run_serve(serve); }}};
  if (const auto exit_code = parse_command_line(app, argc, argv)) return *exit_code;
  for (const auto& [command, run] : subcommands) {
    if (*command) return run();
  }
  return kExitUsage;
}
