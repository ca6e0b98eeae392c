// `magcal serve`: the operations server (service/http/operations_server.hpp) over a database
// file, read-only, until SIGINT or SIGTERM. /metrics: what the database alone knows
// (service/http/metrics.hpp, database_metrics_text: the same names as magcald's), read on its own
// read-only connection per scrape; /-/healthy and /-/ready answer 200 while the server runs (the
// database is open).
#include <pthread.h>
#include <signal.h>

#include <cstdio>
#include <iostream>

#include "service/cli/cli_commands.hpp"
#include "service/config/daemon_config.hpp"
#include "service/http/metrics.hpp"
#include "service/http/operations_server.hpp"
#include "service/io/read_only_database.hpp"

namespace magcal::cli {

int run_serve(const ServeArgs& args) {
  // Block the stop signals in every thread (the server's inherit this mask) and wait for them
  // here: no async-signal handler, and the server threads are never interrupted.
  sigset_t stop_signals;
  sigemptyset(&stop_signals);
  sigaddset(&stop_signals, SIGINT);
  sigaddset(&stop_signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &stop_signals, nullptr);

  http::ServerHooks hooks;
  // The same window as `magcal status` (the daemon's default [storage] window_hours).
  hooks.status_window_utime = DaemonConfig{}.window_utime();
  hooks.metrics_text = [db_path = args.db, window_utime = hooks.status_window_utime] {
    return read_consistently(db_path, [window_utime](storage::Connection& db) {
      return http::database_metrics_text(db, MAGCAL_VERSION, window_utime);
    });
  };
  std::string error;
  auto server = http::OperationsServer::start(args.listen, args.db, std::move(hooks), &error);
  if (!server) {
    std::cerr << "magcal serve: " << error << "\n";
    return kExitData;
  }
  // The bound port (also when --listen asked for port 0), for scripts and tests.
  std::printf("magcal serve: %s (database %s, read-only; Ctrl-C stops)\n", server->url().c_str(),
              storage::database_name(args.db).c_str());
  std::fflush(stdout);
  int signal_number = 0;
  sigwait(&stop_signals, &signal_number);
  server->stop();
  return kExitOk;
}

}  // namespace magcal::cli
