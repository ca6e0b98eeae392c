// magcald: the calibration daemon's composition root (design.md "The daemon's command line and
// config"). Flags override the config file, which overrides the built-in defaults.
//   magcald [--config FILE.toml] [--db FILE] [--lcm-url URL] [--log-level LEVEL]
//           [--http-listen ADDR:PORT] [--station ID]
// Exit codes: 0 ok (stopped by SIGINT/SIGTERM or end of a replayed log), 1 usage or bad
// config, 2 database / LCM / data error at start, 3 storage failed for [storage] max_failure_s
// while running, 4 a worker or refit thread died (service/daemon/daemon.hpp).
#include <atomic>
#include <csignal>
#include <iostream>
#include <string>
#include <utility>
#include <vector>

#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "service/config/daemon_config.hpp"
#include "service/daemon/daemon.hpp"

namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_signal(int) {
  g_stop.store(true);
}

// `error` with the config key it starts with (or quotes first, e.g. "[lcm] url") replaced by
// the flag that set it, when one did: "--log-level: expected ..., got "loud"".
std::string blame_flag(std::string error,
                       const std::vector<std::pair<std::string, std::string>>& flags_given) {
  size_t first = std::string::npos;
  const std::pair<std::string, std::string>* blamed = nullptr;
  for (const auto& given : flags_given) {
    const size_t at = error.find(given.second);
    if (at < first) {
      first = at;
      blamed = &given;
    }
  }
  if (blamed) error.replace(first, blamed->second.size(), blamed->first);
  return error;
}

}  // namespace

int main(int argc, char** argv) {
  using magcal::kExitData;
  using magcal::kExitUsage;
  // Installed first: a SIGTERM during start-up (systemd stop, a test) is a clean stop, never 143.
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  CLI::App app{"magcald: magnetometer calibration daemon (LCM in, SQLite or PostgreSQL + LCM out)"};
  std::string config_path, db_path, lcm_url, log_level, http_listen, station;
  app.add_option("--config", config_path, "TOML config (deploy/magcald.example.toml lists keys)");
  app.add_option("--db", db_path,
                 "SQLite database file or postgresql:// URI (overrides [storage] db_path)");
  app.add_option("--lcm-url", lcm_url,
                 "LCM URL (overrides [lcm] url); file://LOG?speed=0 replays a log and exits");
  app.add_option("--log-level", log_level, "trace|debug|info|warn|error|critical|off");
  app.add_option(
      "--http-listen", http_listen,
      "operations server ADDR:PORT (overrides [http] listen; default 127.0.0.1:9780, port 0 = any "
      "free port, \"\" = off): /metrics, /-/healthy, /-/ready, /api/v1/, /");
  app.add_option("--station", station,
                 "this daemon's ground station id (overrides [station] id; default: the host "
                 "name): recorded with the samples it stores first");
  app.set_version_flag("--version", MAGCAL_VERSION);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == 0) return app.exit(e);
    std::cerr << "magcald: " << e.what() << " (see magcald --help)\n";
    return kExitUsage;
  }

  auto load = magcal::load_daemon_config(config_path);
  if (!load.ok()) {
    std::cerr << "magcald: " << load.error << "\n";
    return kExitUsage;
  }
  magcal::DaemonConfig config = std::move(load.config);
  if (!db_path.empty()) config.storage.db_path = db_path;
  if (!lcm_url.empty()) config.lcm.url = lcm_url;
  if (!log_level.empty()) config.log.level = log_level;
  // "" is a value for these: --http-listen "" is off, --station "" is refused by validate().
  if (app.get_option("--http-listen")->count() > 0) config.http.listen = http_listen;
  if (app.get_option("--station")->count() > 0) config.station.id = station;
  // The flags given, with the config key each overrides: an error about that key blames the
  // flag (the file's value was checked when it was loaded).
  std::vector<std::pair<std::string, std::string>> flags_given;
  for (const auto& [flag, key] :
       {std::pair{"--db", "[storage] db_path"}, std::pair{"--lcm-url", "[lcm] url"},
        std::pair{"--log-level", "[log] level"}, std::pair{"--http-listen", "[http] listen"},
        std::pair{"--station", "[station] id"}}) {
    if (app.get_option(flag)->count() > 0) flags_given.emplace_back(flag, key);
  }
  if (const auto error = config.validate(); !error.empty()) {
    std::cerr << "magcald: " << blame_flag(error, flags_given) << "\n";
    return kExitUsage;
  }
  spdlog::set_level(spdlog::level::from_str(config.log.level));

  magcal::Daemon daemon(std::move(config));
  if (const auto error = daemon.open(); !error.empty()) {
    std::cerr << "magcald: " << blame_flag(error, flags_given) << "\n";
    return kExitData;
  }
  return daemon.run(g_stop);
}
