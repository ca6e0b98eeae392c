// `magcal export CALIBRATION [--db DB] [--sat ID] [--format json|csv] [--out FILE]
//  [--rounding-field-nT F]`: a calibration as an uplink table (service/io/calibration_export.hpp,
// docs/export.md). CALIBRATION is a history id, `latest` (the spacecraft's newest accepted
// refit) or a JSON file of `magcal fit --json` / `magcal history --format json`. Exit: 0 table
// written; 1 usage; 2 data (no such calibration, unreadable file or database).
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "service/cli/cli_commands.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/read_only_database.hpp"
#include "storage/calibration_history.hpp"

namespace magcal::cli {
namespace {

bool is_id(const std::string& s) {
  return !s.empty() && s.size() < 19 && s.find_first_not_of("0123456789") == std::string::npos &&
         s != "0";
}

}  // namespace

std::optional<std::pair<CalibrationResult, CalibrationOrigin>> load_named_calibration(
    const std::string& spec, const std::string& db, const std::string& sat, const char* command,
    int* exit_code) {
  const auto fail = [&](int code, const std::string& message) {
    std::cerr << "magcal " << command << ": " << message << "\n";
    *exit_code = code;
    return std::nullopt;
  };
  CalibrationOrigin origin;
  if (is_id(spec) || spec == "latest") {
    if (db.empty()) return fail(kExitUsage, "'" + spec + "' names a stored calibration: give --db");
    if (spec == "latest" && sat.empty())
      return fail(kExitUsage, "'latest' is the newest accepted refit of a spacecraft: give --sat");
    std::optional<storage::CalibrationRecord> rec;
    try {
      rec = read_consistently(db, [&](storage::Connection& c) {
        auto history = c.make_calibration_history();
        return spec == "latest" ? history->latest_accepted_refit(sat)
                                : history->get(std::stoll(spec));
      });
    } catch (const storage::StorageError& e) {
      return fail(kExitData, e.what());
    }
    if (!rec) {
      return fail(kExitData,
                  spec == "latest"
                      ? "no accepted refit of '" + sat + "' in " + storage::database_name(db)
                      : "no calibration with id " + spec + " in " + storage::database_name(db));
    }
    origin.sat_id = rec->sat_id;
    origin.id = rec->id;
    origin.source = "history id " + std::to_string(rec->id) + " of " + storage::database_name(db);
    return std::pair{result_from_record(*rec), origin};
  }
  if (!std::filesystem::exists(spec)) {
    return fail(kExitData,
                "'" + spec + "' is neither a history id, 'latest', nor an existing JSON file");
  }
  std::ifstream in(spec);
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, false);
  if (j.is_discarded()) return fail(kExitData, spec + ": not valid JSON");
  std::string error;
  std::optional<CalibrationResult> r = calibration_from_json(j, &origin, &error);
  if (!r) return fail(kExitData, spec + ": " + error);
  origin.source = spec;
  return std::pair{std::move(*r), origin};
}

int run_export(const ExportArgs& args) {
  if (!(args.rounding_field_nT > 0.0) || !std::isfinite(args.rounding_field_nT)) {
    std::cerr << "magcal export: --rounding-field-nT must be positive\n";
    return kExitUsage;
  }
  int code = kExitOk;
  const auto named = load_named_calibration(args.calibration, args.db, args.sat, "export", &code);
  if (!named) return code;
  const auto& [result, origin] = *named;
  if (!result.accepted) {
    std::cerr << "magcal export: note: " << origin.source
              << " was rejected by the acceptance gates; exported as asked\n";
  }
  const std::string text =
      args.format == "csv"
          ? export_table_csv(result, origin, args.rounding_field_nT)
          : export_table_json(result, origin, args.rounding_field_nT).dump(2) + "\n";
  if (args.out.empty()) {
    std::cout << text;
    return kExitOk;
  }
  std::ofstream out(args.out, std::ios::binary | std::ios::trunc);
  if (!(out << text) || !out.flush()) {
    std::cerr << "magcal export: cannot write " << args.out << "\n";
    return kExitData;
  }
  return kExitOk;
}

}  // namespace magcal::cli
