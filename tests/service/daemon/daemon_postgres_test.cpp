// magcald and magcal on PostgreSQL (design.md "Fleet": the same surface as on SQLite), as real
// processes against a throwaway PostgreSQL server (tests/storage/postgres/pg_test_server.hpp):
// a few hours of the paper scenario replayed into magcald on PostgreSQL and into magcald on an
// SQLite file give the same history (rows, times, sources, numbers); magcal status, refit and
// serve work on the URI and answer as on the file; the URI's password shows in no output.
// Skipped without the PostgreSQL server programs (with CI=true it fails).
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <set>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "tests/service/http_test_support.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace {

using magcal::test::http_get;
using magcal::test::run;
using magcal::test::Run;
using magcal::test::run_magcal;
using magcal::test::ServeProcess;
using magcal::test::slurp;
using magcal::test::TempDir;
using nlohmann::json;

const std::string kBin = MAGCAL_BIN_DIR;
const std::string kSat = "PAPER-1";
const std::string kPassword = "pw-not-for-logs";  // trust auth: accepted and ignored

// Every value of `a` and `b` the same, numbers to within a relative 1e-9 (the two databases
// store IEEE doubles; only the engines differ). Keys listed in `skip` (ids, wall-clock times)
// are not compared. Adds a failure naming the path of each difference.
void check_same(const json& a, const json& b, const std::string& path,
                const std::set<std::string>& skip) {
  INFO(path);
  if (a.is_number() && b.is_number()) {
    const double x = a.get<double>(), y = b.get<double>();
    CHECK(std::abs(x - y) <= 1e-9 * std::max({1.0, std::abs(x), std::abs(y)}));
    return;
  }
  REQUIRE(a.type() == b.type());
  if (a.is_object()) {
    std::set<std::string> keys_a, keys_b;
    for (const auto& [k, v] : a.items()) keys_a.insert(k);
    for (const auto& [k, v] : b.items()) keys_b.insert(k);
    REQUIRE(keys_a == keys_b);
    for (const auto& k : keys_a) {
      if (skip.count(k) == 0) check_same(a[k], b[k], path + "." + k, skip);
    }
  } else if (a.is_array()) {
    REQUIRE(a.size() == b.size());
    for (size_t i = 0; i < a.size(); ++i) {
      check_same(a[i], b[i], path + "[" + std::to_string(i) + "]", skip);
    }
  } else {
    CHECK(a == b);
  }
}

// `magcal ARGS` with exit 0; its stdout.
std::string magcal_ok(const std::string& args, const TempDir& dir) {
  const Run r = run_magcal(args, dir);
  INFO("magcal " << args << "\n" << r.err);
  REQUIRE(r.exit_code == 0);
  CHECK(r.err.find(kPassword) == std::string::npos);
  return r.out;
}

json history(const std::string& db, const TempDir& dir) {
  return json::parse(magcal_ok("history --db '" + db + "' --sat " + kSat + " --format json", dir));
}

size_t count_method(const json& rows, const std::string& method) {
  size_t n = 0;
  for (const auto& r : rows) n += r["method"] == method ? 1 : 0;
  return n;
}

}  // namespace

TEST_CASE("magcald, magcal status, history, refit and serve on PostgreSQL answer as on SQLite",
          "[daemon][postgres][integration]") {
  magcal::test::PgTestServer* server = magcal::test::pg_server_or_skip();
  if (server == nullptr) return;
  TempDir dir("magcald_pg");
  // 6 h at 10 s: the first refit (after [refit] min_samples) and data-clock refits every 2 h.
  const std::string log = dir.file("six_hours.lcm");
  REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "6", "--seed", "1",
               "--out", log, "--batch", "200"},
              dir.file("sim.log")) == 0);
  {
    std::ofstream config(dir.file("d.toml"));
    config << "[refit]\nclock = \"data\"\nevery_hours = 2\nmin_samples = 1000\n";
  }
  // Over TCP with a password in the URI: what a fleet's config holds.
  const std::string socket_uri = server->create_database();  // postgresql://magcal@/NAME?host=..
  const size_t name_at = socket_uri.find("@/") + 2;
  const std::string name = socket_uri.substr(name_at, socket_uri.find('?') - name_at);
  std::string pg = server->tcp_uri(name);
  pg.replace(pg.find("magcal@"), 7, "magcal:" + kPassword + "@");
  const std::string sqlite = dir.file("m.db");

  {
    std::ofstream config(dir.file("d_pg.toml"));
    config << slurp(dir.file("d.toml")) << "[storage]\ndb_path = \"" << pg << "\"\nspill_dir = \""
           << dir.file("") << "\"\n";  // each test's own: ctest runs cases in parallel
  }
  for (const std::string& db : {sqlite, pg}) {
    const std::string daemon_log = dir.file(db == pg ? "magcald_pg.log" : "magcald_sqlite.log");
    // SQLite by --db; PostgreSQL by [storage] db_path, with the operations server too (it opens
    // its own read-only connection).
    const std::vector<std::string> args =
        db == pg ? std::vector<std::string>{"--config", dir.file("d_pg.toml"), "--http-listen",
                                            "127.0.0.1:0"}
                 : std::vector<std::string>{"--config", dir.file("d.toml"), "--db",
                                            db,         "--http-listen",    ""};
    std::vector<std::string> command{kBin + "/magcald", "--lcm-url", "file://" + log + "?speed=0"};
    command.insert(command.end(), args.begin(), args.end());
    const int rc = run(command, daemon_log);
    INFO(slurp(daemon_log));
    REQUIRE(rc == 0);
    CHECK(slurp(daemon_log).find(kPassword) == std::string::npos);
  }
  const std::string pg_log = slurp(dir.file("magcald_pg.log"));
  CHECK(pg_log.find("up: db postgresql://magcal:***@127.0.0.1") != std::string::npos);
  CHECK(pg_log.find("(database postgresql://magcal:***@127.0.0.1") != std::string::npos);

  // The same rows: sources, times, windows, sample counts, numbers. Not compared: ids (the
  // refit thread and the worker insert in either order) and wall-clock times.
  const std::set<std::string> skip{"id",
                                   "calibration_id",
                                   "created_time",
                                   "started_time",
                                   "finished_time",
                                   "lease_expires_time",
                                   "lease_expires_utime",
                                   "heartbeat_time",
                                   "heartbeat_utime",
                                   "expires_time",
                                   "expires_utime"};
  const json rows_sqlite = history(sqlite, dir);
  const json rows_pg = history(pg, dir);
  REQUIRE(count_method(rows_sqlite, "ukf") >= 100);  // one per minute of data, once started
  REQUIRE(count_method(rows_sqlite, "twostep") >= 2);
  check_same(rows_pg, rows_sqlite, "history", skip);

  // status: the same per spacecraft.
  const json status_sqlite = json::parse(magcal_ok("status --json --db '" + sqlite + "'", dir));
  const json status_pg = json::parse(magcal_ok("status --json --db '" + pg + "'", dir));
  REQUIRE(status_pg["spacecraft"].size() == 1);
  CHECK(status_pg["spacecraft"][0]["samples_in_window"] ==
        status_sqlite["spacecraft"][0]["samples_in_window"]);
  check_same(status_pg, status_sqlite, "status", skip);
  const std::string status_text = magcal_ok("status --db '" + pg + "'", dir);
  CHECK(status_text.find(kSat) != std::string::npos);

  // A manual refit stores one more row, the same on both.
  for (const std::string& db : {sqlite, pg}) {
    const json refit = json::parse(magcal_ok("refit --json --db '" + db + "' --sat " + kSat, dir));
    CHECK(refit["sat_id"] == kSat);
  }
  const json after_pg = history(pg, dir);
  CHECK(count_method(after_pg, "twostep") == count_method(rows_pg, "twostep") + 1);
  check_same(after_pg, history(sqlite, dir), "history after refit", skip);

  // magcal serve on the URI: the API answers with the CLI's bytes, /metrics from the database.
  ServeProcess serve(pg, dir);
  const auto api_history = http_get(serve.port(), "/api/v1/history?sat=" + kSat);
  REQUIRE(api_history.status == 200);
  CHECK(api_history.body ==
        magcal_ok("history --db '" + pg + "' --sat " + kSat + " --format json", dir));
  const auto api_status = http_get(serve.port(), "/api/v1/spacecraft");
  REQUIRE(api_status.status == 200);
  check_same(json::parse(api_status.body),
             json::parse(magcal_ok("status --json --db '" + pg + "'", dir)), "api status", skip);
  const auto metrics = http_get(serve.port(), "/metrics");
  REQUIRE(metrics.status == 200);
  const std::string window_line =
      "magcal_window_samples{sat=\"" + kSat + "\"} " +
      std::to_string(status_pg["spacecraft"][0]["samples_in_window"].get<int64_t>());
  CHECK(metrics.body.find(window_line) != std::string::npos);
  CHECK(http_get(serve.port(), "/api/v1/history?sat=NOPE").status == 400);
  CHECK(serve.stop() == 0);
  const std::string serve_log = serve.log();
  CHECK(serve_log.find(kPassword) == std::string::npos);
  CHECK(serve_log.find("postgresql://magcal:***@") != std::string::npos);

  // An unreachable server (nothing listens on port 1): from magcal one line naming the URI
  // without its password, exit 2. magcald starts anyway (an outage from the start,
  // daemon_pg_outage_test): the replay goes to its spill file, the URI named the same way.
  const std::string unreachable = "postgresql://magcal:" + kPassword + "@127.0.0.1:1/magcal";
  const std::string named = "cannot connect to postgresql://magcal:***@127.0.0.1:1/magcal: ";
  const Run status = run_magcal("status --db '" + unreachable + "'", dir);
  CHECK(status.exit_code == 2);
  CHECK(status.out.empty());
  CHECK(std::count(status.err.begin(), status.err.end(), '\n') == 1);
  CHECK(status.err.find(named) != std::string::npos);
  CHECK(status.err.find(kPassword) == std::string::npos);
  {
    std::ofstream config(dir.file("unreachable.toml"));
    config << "[storage]\nspill_dir = \"" << dir.file("") << "\"\n";
  }
  CHECK(run({kBin + "/magcald", "--config", dir.file("unreachable.toml"), "--http-listen", "",
             "--db", unreachable, "--lcm-url", "file://" + log + "?speed=0"},
            dir.file("magcald_unreachable.log")) == 0);
  const std::string unreached = slurp(dir.file("magcald_unreachable.log"));
  INFO(unreached);
  CHECK(unreached.find("database unreachable at start: ") != std::string::npos);
  CHECK(unreached.find(named) != std::string::npos);
  CHECK(unreached.find(kPassword) == std::string::npos);
  CHECK(unreached.find("pending samples spilled") != std::string::npos);
}
