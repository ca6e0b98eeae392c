// magcal: the operator's command-line tool. Parses arguments (the only CLI11 translation unit)
// and dispatches to the subcommands in cli_*.cpp. Exit codes: 0 ok, 1 usage, 2 data/database.
#include <charconv>
#include <cmath>
#include <cstdint>
#include <iostream>
#include <limits>
#include <sstream>
#include <string>

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
CLI::Option* add_db_option(CLI::App* command, std::string& db) {
  return command->add_option("--db", db, "SQLite database file or postgresql:// URI")
      ->required()
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

}  // namespace

int main(int argc, char** argv) {
  using namespace magcal::cli;
  CLI::App app{"magcal - spacecraft magnetometer calibration (version " MAGCAL_VERSION ")"};
  app.require_subcommand(1);
  app.set_version_flag("--version", MAGCAL_VERSION);

  FieldArgs field;
  auto* field_cmd = app.add_subcommand("field", "IGRF field at a point");
  field_cmd->add_option("--time", field.time_iso, "UTC time, ISO 8601")->required();
  auto* r_opt =
      field_cmd->add_option("--r-km", field.r_km, "geocentric radius, km")->check(real_number());
  auto* colat_opt =
      field_cmd->add_option("--colat-deg", field.colat_deg, "geocentric colatitude, deg")
          ->check(real_number());
  auto* lat_opt =
      field_cmd->add_option("--lat-deg", field.lat_deg, "geodetic (WGS-84) latitude, deg")
          ->check(real_number());
  auto* alt_opt = field_cmd->add_option("--alt-km", field.alt_km, "altitude above WGS-84, km")
                      ->check(real_number());
  field_cmd->add_option("--lon-deg", field.lon_deg, "longitude, deg east")
      ->required()
      ->check(real_number());
  field_cmd->add_option("--coefficients", field.coefficients_file,
                        "IGRF coefficient file (official .txt or .shc); default built-in IGRF-14");
  field_cmd->add_flag("--json", field.json, "print JSON");
  r_opt->excludes(lat_opt)->excludes(alt_opt);
  colat_opt->excludes(lat_opt)->excludes(alt_opt);

  SimArgs sim;
  auto* sim_cmd = app.add_subcommand("sim", "simulate a spacecraft magnetometer");
  sim_cmd->add_option("--scenario", sim.scenario,
                      "preset name (" + preset_list() + ") or scenario FILE.toml");
  sim_cmd->add_option("--hours", sim.hours, "duration, hours (overrides the scenario)")
      ->check(real_number());
  sim_cmd->add_option("--seed", sim.seed, "random seed (overrides the scenario)")
      ->check(seed_number());
  sim_cmd->add_option("--out", sim.out, "output FILE.lcm (LCM log) or FILE.csv")->required();
  sim_cmd->add_option("--truth", sim.truth, "write the true parameters to FILE.json");
  sim_cmd->add_option("--sat-id", sim.sat_id, "spacecraft id (overrides the scenario)");
  sim_cmd
      ->add_option("--batch", sim.batch_size,
                   "LCM output: mag_batch_t packets of N samples on MAGCAL_BATCH")
      ->check(whole_number(0, kIntMax));

  FitArgs fit;
  auto* fit_cmd = app.add_subcommand("fit", "calibrate from a file");
  fit_cmd->add_option("--input", fit.input, "FILE.csv or FILE.lcm")->required();
  fit_cmd->add_option("--method", fit.method, "centered|twostep|ekf|ukf")
      ->check(CLI::IsMember({"centered", "twostep", "ekf", "ukf"}));
  fit_cmd->add_option("--sigma-nT", fit.sigma_nT, "measurement noise, nT per axis (default 3)")
      ->check(real_number());
  fit_cmd->add_flag("--robust", fit.robust,
                    "centered/twostep: find outliers (Huber IRLS, robust scale), fit without them");
  fit_cmd->add_option("--sat", fit.sat, "spacecraft id (required when a log holds several)");
  fit_cmd->add_option("--trace", fit.trace_file,
                      "ekf/ukf: write state and 1-sigma per sample (CSV)");
  fit_cmd->add_flag("--json", fit.json, "print JSON");
  fit_cmd
      ->add_option("--gimbal-lock-margin-deg", fit.gimbal_lock_margin_deg,
                   "roll/yaw reported as a canonical split (roll 0) within this of pitch +-90 deg "
                   "(default 2)")
      ->check(real_number_in(0.0, 45.0));
  fit_cmd->add_option("--field-unit", fit.field_unit, "recording CSV: field unit nT|uT|G|mG");
  fit_cmd->add_option("--alt-km", fit.alt_km, "recording CSV: assumed altitude (km) when absent")
      ->check(real_number());
  fit_cmd->add_option("--skip-first", fit.skip_first, "recording CSV: drop the first N rows")
      ->check(whole_number(0, kIntMax));
  fit_cmd->add_flag("--estimate-attitude-lag", fit.estimate_attitude_lag,
                    "sample files: fit the attitude-magnetometer time lag with the alignment");
  fit_cmd->add_flag("--estimate-time-offset", fit.estimate_time_offset,
                    "recording CSV: estimate the time-tag offset of the position stream");
  fit_cmd->add_option("--offset-range-s", fit.offset_range_s,
                      "MIN:MAX search range of the offset (default -1000:1000)");
  fit_cmd
      ->add_option("--time-offset-s", fit.time_offset_s,
                   "recording CSV: apply this offset (reference at t + tau)")
      ->check(real_number());
  fit_cmd->add_option("--reference-magnitude", fit.reference_magnitude,
                      "recording CSV: constant field magnitude, auto|VALUE_nT");
  fit_cmd->add_flag("--split-halves", fit.split_halves,
                    "recording CSV: also fit the two halves separately");
  fit_cmd
      ->add_option("--expected-residual-nT", fit.expected_residual_nT,
                   "expected residual rms for the acceptance gate (default max(7.5, --sigma-nT))")
      ->check(real_number());

  EvaluateArgs evaluate;
  auto* eval_cmd = app.add_subcommand("evaluate", "Monte-Carlo evaluation against the paper");
  eval_cmd->add_option("--scenario", evaluate.scenario,
                       "preset name (" + preset_list() + ") or FILE.toml");
  eval_cmd->add_option("--runs", evaluate.runs, "Monte-Carlo runs")
      ->check(whole_number(1, kIntMax));
  eval_cmd->add_option("--seed", evaluate.seed, "first random seed")->check(seed_number());
  eval_cmd->add_flag("--json", evaluate.json, "print JSON");

  RefitArgs refit;
  auto* refit_cmd = app.add_subcommand("refit", "run an offline refit of a stored window now");
  add_db_option(refit_cmd, refit.db);
  refit_cmd->add_option("--sat", refit.sat, "spacecraft id")->required();
  refit_cmd->add_option("--config", refit.config, "magcald config (gates, sigma, window)");
  refit_cmd->add_flag("--json", refit.json, "print JSON");

  HistoryArgs history;
  auto* hist_cmd = app.add_subcommand("history", "query stored calibration results");
  add_db_option(hist_cmd, history.db);
  hist_cmd->add_option("--sat", history.sat, "spacecraft id")->required();
  hist_cmd->add_option("--method", history.method, "ukf|ekf|centered|twostep");
  hist_cmd->add_option("--since", history.since, "ISO 8601 UTC, inclusive");
  hist_cmd->add_option("--until", history.until, "ISO 8601 UTC, inclusive");
  hist_cmd->add_option("--limit", history.limit, "only the N newest")
      ->check(whole_number(1, kIntMax));
  hist_cmd->add_option("--order", history.order, "asc|desc (default asc)")
      ->check(CLI::IsMember({"asc", "desc"}));
  hist_cmd->add_option("--format", history.format, "table|csv|json")
      ->check(CLI::IsMember({"table", "csv", "json"}));

  StatusArgs status;
  auto* status_cmd = app.add_subcommand("status", "per-spacecraft summary");
  add_db_option(status_cmd, status.db);
  status_cmd->add_flag("--json", status.json, "print JSON");

  ServeArgs serve;
  auto* serve_cmd = app.add_subcommand(
      "serve", "HTTP operations server over a database (read-only): API, plots page");
  add_db_option(serve_cmd, serve.db);
  serve_cmd->add_option("--listen", serve.listen,
                        "ADDR:PORT to listen on (default 127.0.0.1:9780; port 0: any free)");

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

  if (*field_cmd) return run_field(field);
  if (*sim_cmd) return run_sim(sim);
  if (*fit_cmd) {
    fit.sigma_given = fit_cmd->get_option("--sigma-nT")->count() > 0;
    return run_fit(fit);
  }
  if (*eval_cmd) return run_evaluate(evaluate);
  if (*refit_cmd) return run_refit(refit);
  if (*hist_cmd) return run_history(history);
  if (*status_cmd) return run_status(status);
  if (*serve_cmd) return run_serve(serve);
  return kExitUsage;
}
