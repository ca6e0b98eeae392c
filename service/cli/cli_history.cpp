// `magcal history`: stored calibration results of one spacecraft as an aligned table, CSV or a
// JSON array (design.md; the text is service/io/history_report.hpp's, shared with GET
// /api/v1/history). Reads the database read-only (never creates or upgrades a file) and works
// while the daemon writes (WAL snapshot).
#include <iostream>
#include <string>
#include <vector>

#include "service/cli/cli_commands.hpp"
#include "service/io/history_report.hpp"
#include "service/io/read_only_database.hpp"

namespace magcal::cli {

int run_history(const HistoryArgs& args) {
  HistoryRequest request;
  request.sat = args.sat;
  request.method = args.method;
  request.since = args.since;
  request.until = args.until;
  request.limit = args.limit;
  request.order = args.order;
  request.format = args.format;
  std::string error;
  const auto query = parse_history_request(request, "--", &error);
  if (!query) {
    std::cerr << "magcal history: " << error << "\n";
    return kExitUsage;
  }

  std::vector<storage::CalibrationRecord> rows;
  try {
    bool known = true;
    rows = read_consistently(args.db, [&](storage::Connection& db) {
      auto found = read_history(db, *query);
      known = !found.empty() || spacecraft_known(db, args.sat);
      return found;
    });
    // Unknown spacecraft (nothing stored at all): a data error (exit 2), as the API's 400 — a
    // script must not take an empty answer for success. A known one with no rows in the asked
    // range is a valid, empty answer.
    if (!known) {
      std::cerr << "magcal history: no data for spacecraft '" << args.sat << "' in "
                << storage::database_name(args.db) << "\n";
      return kExitData;
    }
  } catch (const storage::StorageError& e) {
    std::cerr << "magcal history: " << e.what() << "\n";
    return kExitData;
  }

  if (args.format == "json") {
    std::cout << history_json_text(rows);
  } else if (args.format == "csv") {
    std::cout << history_csv_text(rows);
  } else if (rows.empty()) {
    std::cerr << "magcal history: no results for '" << args.sat << "' with these filters\n";
  } else {
    std::cout << history_table_text(rows);
  }
  return kExitOk;
}

}  // namespace magcal::cli
