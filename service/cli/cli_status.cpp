// `magcal status`: per spacecraft, what operations watch (service/io/status_report.hpp, shared
// with GET /api/v1/spacecraft). Read-only, one consistent snapshot.
#include <iostream>
#include <string>

#include "service/cli/cli_commands.hpp"
#include "service/config/daemon_config.hpp"
#include "service/io/read_only_database.hpp"
#include "service/io/status_report.hpp"

namespace magcal::cli {

int run_status(const StatusArgs& args) {
  // The daemon's default window (design.md [storage] window_hours); status takes no config.
  const int64_t window_utime = DaemonConfig{}.window_utime();
  FleetStatus all;
  try {
    all = read_consistently(args.db,
                            [&](storage::Connection& db) { return read_status(db, window_utime); });
  } catch (const storage::StorageError& e) {
    std::cerr << "magcal status: " << e.what() << "\n";
    return kExitData;
  }
  if (args.json) {
    std::cout << status_json_text(all, window_utime);
  } else if (all.spacecraft.empty()) {
    std::cerr << "magcal status: no spacecraft in " << storage::database_name(args.db) << "\n";
  } else {
    std::cout << status_text(all, window_utime);
  }
  return kExitOk;
}

}  // namespace magcal::cli
