// The `magcal` subcommands. magcal_main.cpp parses the command line (CLI11 stays in that one
// translation unit) into these argument structs and calls run_*; each run_* lives in its own
// cli_<command>.cpp. Every run_* returns an exit code (below) and, on error, has printed one
// clear line on stderr and written nothing half.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "pipeline/calibration_result.hpp"
#include "pipeline/roll_pitch_yaw_report.hpp"
#include "service/io/calibration_export.hpp"
#include "service/io/exit_codes.hpp"
#include "service/io/field_recording.hpp"

namespace magcal::cli {

using magcal::kExitData;  // data, file or database error
using magcal::kExitOk;
using magcal::kExitUsage;  // bad arguments

struct FieldArgs {
  std::string time_iso;
  // Geocentric input...
  std::optional<double> r_km, colat_deg;
  // ...or geodetic input (WGS-84); lon_deg is shared.
  std::optional<double> lat_deg, alt_km;
  std::optional<double> lon_deg;
  std::string coefficients_file;  // empty: built-in IGRF-14
  bool json = false;
};
int run_field(const FieldArgs& args);

struct SimArgs {
  std::string scenario = "paper";  // preset name or FILE.toml
  std::optional<double> hours;
  std::optional<uint64_t> seed;
  std::string out;                    // FILE.lcm or FILE.csv
  std::string truth;                  // FILE.json, optional
  std::optional<std::string> sat_id;  // overrides the scenario's (given empty: refused)
  int batch_size = 0;  // > 0: mag_batch_t packets of this many samples on MAGCAL_BATCH
};
int run_sim(const SimArgs& args);

struct FitArgs {
  // --input, as given: files, globs, "-" (a CSV on standard input); one result per file.
  std::vector<std::string> inputs;
  std::string input;        // the file being fitted: FILE.csv, FILE.lcm or "-"
  bool json_lines = false;  // with several files: each JSON result on one line
  std::string method = "twostep";
  double sigma_nT = 3.0;
  bool robust = false;
  std::string sat;
  bool json = false;
  std::string trace_file;  // ekf/ukf: state and 1-sigma after every sample
  // Real recordings in foreign CSV layouts (service/analysis/real_data_fit.hpp).
  bool sigma_given = false;      // --sigma-nT given explicitly (else estimated)
  std::string field_unit;        // nT|uT|G|mG; empty: from the column name
  std::optional<double> alt_km;  // assumed altitude when the file has none
  int skip_first = 0;            // start-up rows dropped
  bool estimate_time_offset = false;
  std::string offset_range_s;  // "MIN:MAX" (default -1000:1000)
  std::optional<double> time_offset_s;
  std::string reference_magnitude;  // "auto" | value in nT (constant field); empty: IGRF
  bool split_halves = false;
  std::optional<double> expected_residual_nT;  // residual gate's expected rms
  bool estimate_attitude_lag = false;          // fit the attitude lag with the rotation
  // Roll/pitch/yaw within this of pitch +-90 deg are reported singular (roll_pitch_yaw_report).
  double gimbal_lock_margin_deg = kDefaultGimbalLockMargin_deg;
};
int run_fit(const FitArgs& args);
// The residual gate's expected rms: --expected-residual-nT, else at least the stated noise.
double gate_expected_residual_nT(const FitArgs& args);
// The recording reader's options from the command line: kExitOk, or kExitUsage (printed).
int recording_read_options(const FitArgs& args, FieldRecordingOptions* options);
// What fit read from a CSV recording, on stderr once the fit has a result (an error stays one
// line): the columns used and ignored, the rows the row rules dropped or sorted, the times
// taken as UTC without a zone.
void note_recording(const FieldRecording& rec);
// Dispatched from run_fit for a CSV recording without reference directions (magnitude only,
// service/analysis/real_data_fit.hpp).
int run_recording_fit(const FitArgs& args, const FieldRecording& recording);

struct EvaluateArgs {
  std::string scenario = "paper";
  int runs = 10;
  uint64_t seed = 1;
  bool json = false;
};
int run_evaluate(const EvaluateArgs& args);

struct RefitArgs {
  std::string db;
  std::string sat;
  std::string config;  // optional magcald config (gates, sigma, window)
  bool json = false;
};
int run_refit(const RefitArgs& args);

struct HistoryArgs {
  std::string db;
  std::string sat;
  std::string method;
  std::string since, until;  // ISO 8601
  std::optional<int> limit;
  std::string order = "asc";
  std::string format = "table";
};
int run_history(const HistoryArgs& args);

struct StatusArgs {
  std::string db;
  bool json = false;
};
int run_status(const StatusArgs& args);

// A calibration named on the command line (export, compare): a history id (with --db), "latest"
// (with --db and --sat: the newest accepted refit), or a JSON file (`magcal fit --json`, one
// object of `magcal history --format json`).
struct ExportArgs {
  std::string calibration;  // ID | latest | FILE.json
  std::string db;
  std::string sat;
  std::string format = "json";  // json | csv
  std::string out;              // empty: stdout
  double rounding_field_nT = kDefaultRoundingField_nT;
};
int run_export(const ExportArgs& args);

struct CompareArgs {
  std::string a, b;  // each ID | latest | FILE.json
  std::string db;
  std::string sat;
  std::string samples;       // the window: a sample FILE.csv...
  std::string since, until;  // ...or the stored samples (--db) in this range (default B's window)
  bool json = false;
};
int run_compare(const CompareArgs& args);

// The calibration `spec` names (see ExportArgs), or nullopt with one line printed as
// "magcal <command>: ..." and *exit_code set.
std::optional<std::pair<CalibrationResult, CalibrationOrigin>> load_named_calibration(
    const std::string& spec, const std::string& db, const std::string& sat, const char* command,
    int* exit_code);

struct ServeArgs {
  std::string db;
  std::string listen = "127.0.0.1:9780";  // ADDR:PORT; port 0 = any free port
};
int run_serve(const ServeArgs& args);

}  // namespace magcal::cli
