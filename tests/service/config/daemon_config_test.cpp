// magcald configuration: defaults, the example file, and clear errors for unknown keys and bad
// values (design.md "The daemon's command line and config").
#include <catch2/catch.hpp>

#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <set>
#include <string>

#include "service/config/daemon_config.hpp"
#include "storage/connection.hpp"

using magcal::DaemonConfig;
using magcal::parse_daemon_config;

TEST_CASE("defaults are valid and match design.md", "[daemon_config]") {
  const auto load = parse_daemon_config("", "empty");
  REQUIRE(load.ok());
  const auto& c = load.config;
  CHECK(c.storage.db_path == "magcal.db");
  CHECK(c.storage.window_hours == 12.0);
  CHECK(c.storage.retention_margin_hours == 1.0);
  CHECK(c.refit.daily_at_utc == "02:00");
  CHECK(c.refit.every_hours == 0.0);
  CHECK(c.refit.clock == "wall");
  CHECK(c.refit.min_samples == 1000);
  CHECK(c.refit.early_growth == Approx(std::sqrt(2.0)));
  CHECK(c.ukf.filter.sigma_nT == 3.0);
  CHECK(c.ukf.snapshot_every_s == 60.0);
  CHECK(c.sensor.range_nT == 100000.0);
  CHECK(c.igrf.coefficients_file.empty());
  CHECK(c.log.level == "info");
  CHECK(c.lcm.samples_channel == "MAGCAL_SAMPLES");
  CHECK(c.lcm.batch_channel == "MAGCAL_BATCH");
  CHECK(c.lcm.calibration_channel == "MAGCAL_CALIBRATION");
  CHECK(c.lcm.status_channel == "MAGCAL_STATUS");
  CHECK(c.service.whitelist.empty());
  CHECK(c.ingest.max_time_jump_s == 3600.0);
  CHECK(c.ingest.max_future_s == 300.0);
  CHECK(c.storage.max_failure_s == 60.0);
  CHECK(c.storage.max_pending_samples == 200000);
  CHECK(c.storage.pg_max_failure_s == 3600.0);
  CHECK(c.storage.spill_dir.empty());
  CHECK(c.storage.spill_max_bytes == int64_t{1} << 30);
  CHECK(c.storage.stop_max_failure_s == 30.0);
  CHECK(c.storage.busy_timeout_ms == 5000);
  CHECK(c.http.listen == "127.0.0.1:9780");  // design.md: loopback by default
  char host[256] = {};
  REQUIRE(::gethostname(host, sizeof host - 1) == 0);
  CHECK(c.station.id == host);  // design.md "Fleet": the host name by default
}

TEST_CASE("the example config lists every key with exactly the defaults", "[daemon_config]") {
  const auto load = magcal::load_daemon_config(MAGCAL_SOURCE_DIR "/deploy/magcald.example.toml");
  REQUIRE(load.error == "");
  const magcal::DaemonConfig d;
  const auto& c = load.config;
  CHECK(c.lcm.url == d.lcm.url);
  CHECK(c.lcm.publish_url == d.lcm.publish_url);
  CHECK(c.storage.commit_every_samples == d.storage.commit_every_samples);
  CHECK(c.storage.commit_every_ms == d.storage.commit_every_ms);
  CHECK(c.storage.busy_timeout_ms == d.storage.busy_timeout_ms);
  CHECK(c.storage.max_failure_s == d.storage.max_failure_s);
  CHECK(c.storage.max_pending_samples == d.storage.max_pending_samples);
  CHECK(c.storage.pg_max_failure_s == d.storage.pg_max_failure_s);
  CHECK(c.storage.spill_dir == d.storage.spill_dir);
  CHECK(c.storage.spill_max_bytes == d.storage.spill_max_bytes);
  CHECK(c.storage.stop_max_failure_s == d.storage.stop_max_failure_s);
  CHECK(c.storage.pg_reply_timeout_s == d.storage.pg_reply_timeout_s);
  CHECK(c.refit.robust == d.refit.robust);
  CHECK(c.refit.early_growth == d.refit.early_growth);
  CHECK(c.ukf.filter.process_noise_per_sqrt_hour == d.ukf.filter.process_noise_per_sqrt_hour);
  CHECK(c.ukf.filter.alpha == d.ukf.filter.alpha);
  CHECK(c.ukf.filter.beta == d.ukf.filter.beta);
  CHECK(c.ukf.filter.kappa == d.ukf.filter.kappa);
  CHECK(c.ukf.filter.initial_bias_sigma_nT == d.ukf.filter.initial_bias_sigma_nT);
  CHECK(c.ukf.filter.initial_D_sigma == d.ukf.filter.initial_D_sigma);
  CHECK(c.ukf.filter.gate_nis == Approx(d.ukf.filter.gate_nis));
  CHECK(c.ukf.filter.nis_window == d.ukf.filter.nis_window);
  CHECK(c.ukf.filter.nis_inconsistent_mean == d.ukf.filter.nis_inconsistent_mean);
  CHECK(c.ukf.filter.inflation_factor == d.ukf.filter.inflation_factor);
  CHECK(c.ukf.filter.converged_bias_sigma_nT == d.ukf.filter.converged_bias_sigma_nT);
  CHECK(c.ukf.filter.cold_start == d.ukf.filter.cold_start);
  CHECK(c.ukf.filter.consistency_action == d.ukf.filter.consistency_action);
  const auto& g = c.gates;
  const auto& dg = d.gates;
  CHECK(g.expected_residual_nT == dg.expected_residual_nT);
  CHECK(g.residual_test == dg.residual_test);
  CHECK(g.residual_factor == dg.residual_factor);
  CHECK(g.residual_tail_probability == dg.residual_tail_probability);
  CHECK(g.max_fisher_condition == dg.max_fisher_condition);
  CHECK(g.min_fisher_eigenvalue == dg.min_fisher_eigenvalue);
  CHECK(g.min_coverage_eigenvalue == dg.min_coverage_eigenvalue);
  CHECK(g.max_bias_nT == dg.max_bias_nT);
  CHECK(g.max_scale == dg.max_scale);
  CHECK(g.max_nonorthogonality == dg.max_nonorthogonality);
  CHECK(g.change_tail_probability == dg.change_tail_probability);
  CHECK(g.bias_change_floor_nT == dg.bias_change_floor_nT);
  CHECK(g.D_change_floor == dg.D_change_floor);
  CHECK(c.service.queue_capacity_samples == d.service.queue_capacity_samples);
  CHECK(c.service.status_every_s == d.service.status_every_s);
  CHECK(c.service.min_position_km == d.service.min_position_km);
  CHECK(c.service.max_position_km == d.service.max_position_km);
  CHECK(c.log.status_every_s == d.log.status_every_s);
  CHECK(c.ingest.max_time_jump_s == d.ingest.max_time_jump_s);
  CHECK(c.ingest.max_future_s == d.ingest.max_future_s);
  CHECK(c.http.listen == d.http.listen);
}

namespace {

// A seconds setting of deploy/magcald.service ("WatchdogSec=60s", "TimeoutStopSec=90"); 0 when
// absent.
double unit_seconds(const std::string& key) {
  std::ifstream unit(MAGCAL_SOURCE_DIR "/deploy/magcald.service");
  REQUIRE(unit.good());
  for (std::string line; std::getline(unit, line);) {
    if (line.starts_with(key + "=")) return std::stod(line.substr(key.size() + 1));
  }
  return 0;
}

}  // namespace

TEST_CASE("a stop gives up on failing storage well before the unit's TimeoutStopSec kills it",
          "[daemon_config]") {
  // The bound plus one PostgreSQL attempt in flight when it passes (30 s on a dead link) and
  // the rest of the drain must end before systemd's SIGKILL drops the held samples unlogged.
  const double timeout_stop_s = unit_seconds("TimeoutStopSec");
  REQUIRE(timeout_stop_s > 0);
  CHECK(magcal::DaemonConfig{}.storage.stop_max_failure_s + 40.0 <= timeout_stop_s);
}

TEST_CASE("a PostgreSQL statement waits for its reply well inside the unit's WatchdogSec",
          "[daemon_config]") {
  // A commit attempt on a server that answers nothing may wait for a reply, a reconnect
  // (connect_timeout, 10 s) and a reply again: the worker loop must still ping the watchdog.
  const double watchdog_s = unit_seconds("WatchdogSec");
  REQUIRE(watchdog_s > 0);
  const magcal::DaemonConfig d;
  CHECK(2 * d.storage.pg_reply_timeout_s + 10.0 < watchdog_s);
  CHECK(d.database_options().reply_timeout_ms == 10000);
  CHECK(d.storage.pg_reply_timeout_s * 1000.0 > d.storage.busy_timeout_ms);
  // SQLite has no reply deadline: a long busy timeout there is no conflict.
  CHECK(parse_daemon_config("[storage]\nbusy_timeout_ms = 15000\n", "sqlite").error.empty());
}

TEST_CASE("values are read, integers accepted for floats", "[daemon_config]") {
  const auto load = parse_daemon_config(R"(
[lcm]
url = "file:///tmp/x.lcm?speed=0"
[storage]
window_hours = 6
[refit]
clock = "data"
every_hours = 6
daily_at_utc = "23:59"
[ukf]
sigma_nT = 7.5
process_noise = [0.1, 0.1, 0.1, 0, 0, 0, 0, 0, 0]
consistency_action = "reseed"
[gates]
residual_test = "chi_square"
[service]
whitelist = ["SAT-B", "SAT-A"]
[http]
listen = "[::1]:0"
)",
                                        "t.toml");
  REQUIRE(load.error == "");
  CHECK(load.config.storage.window_hours == 6.0);
  CHECK(load.config.window_utime() == 6LL * 3600 * 1000000);
  CHECK(load.config.data_clock());
  CHECK(load.config.ukf.filter.sigma_nT == 7.5);
  CHECK(load.config.ukf.filter.process_noise_per_sqrt_hour(0) == 0.1);
  CHECK(load.config.gates.residual_test == magcal::GateOptions::ResidualTest::kChiSquare);
  CHECK(load.config.service.whitelist.size() == 2);
  CHECK(load.config.http.listen == "[::1]:0");
  CHECK(parse_daemon_config("[http]\nlisten = \"\"\n", "off.toml").config.http.listen.empty());
}

TEST_CASE("unknown keys, bad types and bad values name the key", "[daemon_config]") {
  struct Case {
    const char* toml;
    const char* expect;  // substring of the error
  };
  const Case cases[] = {
      {"[storage]\nwindow_hour = 12\n", "unknown key [storage] window_hour"},
      {"[stroage]\ndb_path = \"x\"\n", "unknown section [stroage]"},
      {"[storage]\nwindow_hours = \"12\"\n", "[storage] window_hours: expected a number"},
      {"[storage]\nwindow_hours = -1\n", "[storage] window_hours: must be > 0"},
      {"[refit]\nclock = \"sundial\"\n", "[refit] clock"},
      {"[refit]\ndaily_at_utc = \"2:00\"\n", "[refit] daily_at_utc"},
      {"[refit]\ndaily_at_utc = \"24:00\"\n", "[refit] daily_at_utc"},
      {"[refit]\nmin_samples = 1.5\n", "[refit] min_samples: expected an integer"},
      {"[refit]\nearly_growth = 1.05\n", "[refit] early_growth: must be 0"},
      {"[refit]\nearly_growth = -2\n", "[refit] early_growth: must be 0"},
      {"[ukf]\nsigma_nT = 0\n", "[ukf]"},
      {"[ukf]\nprocess_noise = [1, 2]\n", "[ukf] process_noise"},
      {"[ukf]\ncold_start = \"warm\"\n", "[ukf] cold_start: expected one of"},
      {"[log]\nlevel = \"loud\"\n", "[log] level"},
      {"[lcm]\nstatus_channel = \"\"\n", "[lcm] status_channel"},
      {"[service]\nwhitelist = \"SAT\"\n", "[service] whitelist"},
      {"[sensor]\nrange_nT = nan\n", "[sensor] range_nT"},
      {"[ingest]\nmax_time_jump_s = 0\n", "[ingest] max_time_jump_s"},
      {"[ingest]\nmax_future_s = -1\n", "[ingest] max_future_s"},
      {"[ingest]\nmax_future_s = inf\n", "[ingest] max_future_s"},
      {"[storage]\nmax_failure_s = 0\n", "[storage] max_failure_s: must be > 0"},
      {"[storage]\npg_max_failure_s = -5\n", "[storage] pg_max_failure_s: must be > 0"},
      {"[storage]\npg_max_failure_s = \"1h\"\n", "[storage] pg_max_failure_s: expected a number"},
      {"[storage]\nspill_max_bytes = -1\n", "[storage] spill_max_bytes: must be >= 0"},
      {"[storage]\nspill_max_bytes = 1.5e9\n", "[storage] spill_max_bytes: expected an integer"},
      {"[storage]\nspill_dir = 7\n", "[storage] spill_dir: expected a string"},
      {"[storage]\nstop_max_failure_s = 0\n", "[storage] stop_max_failure_s: must be > 0"},
      {"[storage]\ndb_path = \"postgresql://h/db\"\npg_reply_timeout_s = 5\n",
       "[storage] pg_reply_timeout_s (5 s) must be above busy_timeout_ms (5000 ms)"},
      {"[storage]\npg_reply_timeout_s = 7200\n",
       "[storage] pg_reply_timeout_s: must be > 0 and at most 3600"},
      {"[storage]\npg_reply_timeout_s = 0\n",
       "[storage] pg_reply_timeout_s: must be > 0 and at most 3600"},
      {"[storage]\nbusy_timeout_ms = -1\n", "[storage] busy_timeout_ms: must be >= 0"},
      {"[storage]\nmax_pending_samples = 100\n",
       "[storage] max_pending_samples: must be >= commit_every_samples"},
      {"[http]\nlisten = \"9780\"\n", "[http] listen: expected \"ADDR:PORT\""},
      {"[http]\nlisten = \"localhost:\"\n", "[http] listen"},
      {"[http]\nlisten = \":9780\"\n", "[http] listen"},
      {"[http]\nlisten = \"127.0.0.1:65536\"\n", "[http] listen"},
      {"[http]\nlisten = \"127.0.0.1:-1\"\n", "[http] listen"},
      {"[http]\nlisten = 9780\n", "[http] listen: expected a string"},
      {"[station]\nid = \"\"\n", "[station] id: must be 1-64 printable ASCII characters"},
      {"[station]\nid = \"ground station 2\"\n", "got \"ground station 2\""},
      {"[station]\nid = \"gs\\u0007\"\n", "got \"gs?\""},
      {"[station]\nid = \"gs-\\u00e9\"\n", "[station] id"},  // not ASCII
      {"[station]\nid = 2\n", "[station] id: expected a string"},
      {"lcm = 3\n", "[lcm] must be a table"},
      {"[storage\n", "t.toml:1"},
  };
  for (const auto& c : cases) {
    const auto load = parse_daemon_config(c.toml, "t.toml");
    INFO(c.toml);
    CHECK_FALSE(load.ok());
    CHECK_THAT(load.error, Catch::Contains(c.expect));
  }
}

TEST_CASE("a station id is read from [station] id, up to 64 characters", "[daemon_config]") {
  auto load = parse_daemon_config("[station]\nid = \"Svalbard-2\"\n", "t.toml");
  REQUIRE(load.ok());
  CHECK(load.config.station.id == "Svalbard-2");
  load = parse_daemon_config("[station]\nid = \"" + std::string(64, 's') + "\"\n", "t.toml");
  CHECK(load.ok());
  load = parse_daemon_config("[station]\nid = \"" + std::string(65, 's') + "\"\n", "t.toml");
  CHECK_THAT(load.error, Catch::Contains("[station] id") && Catch::Contains("(65 characters)"));
}

TEST_CASE("PostgreSQL has its own storage failure limit and a spill file per station",
          "[daemon_config]") {
  auto load = parse_daemon_config(
      "[storage]\nmax_failure_s = 30\npg_max_failure_s = 900\n[station]\nid = \"gs/2\"\n",
      "t.toml");
  REQUIRE(load.ok());
  DaemonConfig c = load.config;
  // SQLite: max_failure_s, no spill.
  CHECK(c.storage_max_failure_s() == 30.0);
  CHECK(std::string(c.storage_max_failure_key()) == "max_failure_s");
  CHECK(c.spill_path().empty());
  c.storage.db_path = "postgresql://magcal@db.example/fleet";
  CHECK(c.storage_max_failure_s() == 900.0);
  CHECK(std::string(c.storage_max_failure_key()) == "pg_max_failure_s");
  // The station id names the file ('/' made harmless); spill_dir, else $STATE_DIRECTORY, else
  // the working directory.
  c.storage.spill_dir = "/var/spool/magcal";
  CHECK(c.spill_path() == "/var/spool/magcal/magcal-spill-gs_2.spill");
  c.storage.spill_dir.clear();
  const char* state = std::getenv("STATE_DIRECTORY");
  const std::string saved = state ? state : "";
  ::setenv("STATE_DIRECTORY", "/var/lib/magcal:/var/lib/other", 1);
  CHECK(c.spill_path() == "/var/lib/magcal/magcal-spill-gs_2.spill");
  ::unsetenv("STATE_DIRECTORY");
  CHECK(c.spill_path() == "./magcal-spill-gs_2.spill");
  if (state) ::setenv("STATE_DIRECTORY", saved.c_str(), 1);
  c.storage.spill_max_bytes = 0;  // no spill
  CHECK(c.spill_path().empty());
}

TEST_CASE("a missing config file is an error", "[daemon_config]") {
  const auto load = magcal::load_daemon_config("/nonexistent/magcald.toml");
  CHECK_FALSE(load.ok());
  CHECK_THAT(load.error, Catch::Contains("/nonexistent/magcald.toml"));
}

// deploy/fleet (docs/fleet.md): three stations' configs for one PostgreSQL database. They must
// keep parsing, and agree on what makes a fleet: one database, distinct stations, one refit
// schedule (a scheduled refit is claimed once, at whichever station's schedule reaches it).
TEST_CASE("the fleet example configs parse, share one database and differ in the station",
          "[daemon_config]") {
  std::vector<magcal::DaemonConfig> stations;
  for (const char* file : {"station-a.toml", "station-b.toml", "station-c.toml"}) {
    const auto load =
        magcal::load_daemon_config(MAGCAL_SOURCE_DIR "/deploy/fleet/" + std::string(file));
    INFO(file);
    REQUIRE(load.error == "");
    CHECK(magcal::storage::is_postgres_uri(load.config.storage.db_path));
    stations.push_back(load.config);
  }
  std::set<std::string> ids;
  for (const auto& c : stations) {
    ids.insert(c.station.id);
    const auto& a = stations.front();
    CHECK(c.storage.db_path == a.storage.db_path);
    CHECK(c.storage.window_hours == a.storage.window_hours);
    CHECK(c.storage.retention_margin_hours == a.storage.retention_margin_hours);
    CHECK(c.refit.daily_at_utc == a.refit.daily_at_utc);
    CHECK(c.refit.every_hours == a.refit.every_hours);
    CHECK(c.refit.clock == a.refit.clock);
    CHECK(c.refit.min_samples == a.refit.min_samples);
    CHECK(c.refit.early_growth == a.refit.early_growth);
    CHECK(c.refit.robust == a.refit.robust);
    CHECK(c.result_settings() == a.result_settings());  // so their results do not depend on
                                                        // which station owns a spacecraft
  }
  CHECK(ids.size() == stations.size());
}

TEST_CASE("the settings results depend on: every key but the operational ones, as text",
          "[daemon_config]") {
  const auto settings = [](const std::string& toml) {
    const auto load = parse_daemon_config(toml, "test");
    REQUIRE(load.error == "");
    return load.config.result_settings();
  };
  const auto d = settings("");
  CHECK(d.at("refit.every_hours") == "0");
  CHECK(d.at("refit.clock") == "wall");
  CHECK(d.at("refit.robust") == "false");
  CHECK(d.at("storage.window_hours") == "12");
  CHECK(d.at("fleet.lease_s") == "30");
  CHECK(d.at("fleet.reorder_delay_s") == "60");
  CHECK(d.at("ukf.cold_start") == "data");
  CHECK(d.at("ukf.sigma_nT") == "3");
  CHECK(d.at("sensor.range_nT") == "100000");
  CHECK(d.at("igrf.coefficients_file") == "built-in IGRF-14");
  CHECK(d.at("service.whitelist") == "[]");
  CHECK(d.count("ukf.process_noise") == 1);
  CHECK(d.count("gates.max_bias_nT") == 1);
  CHECK(d.count("ingest.max_future_s") == 1);
  // Where data comes from and goes, commit cadence, failure limits, logging: not results.
  for (const char* key :
       {"station.id", "lcm.url", "lcm.samples_channel", "http.listen", "log.level",
        "storage.db_path", "storage.spill_dir", "storage.commit_every_ms",
        "storage.pg_max_failure_s", "service.queue_capacity_samples"}) {
    INFO(key);
    CHECK(d.count(key) == 0);
  }
  // Operational keys changed: the same settings.
  CHECK(settings("[station]\nid = \"gs-x\"\n[log]\nlevel = \"debug\"\n[http]\nlisten = \"\"\n"
                 "[storage]\nspill_dir = \"/tmp\"\ncommit_every_ms = 100\n") == d);
  // One result-affecting key changed: that key alone differs.
  auto six = settings("[refit]\nevery_hours = 6\n");
  CHECK(six.at("refit.every_hours") == "6");
  six["refit.every_hours"] = "0";
  CHECK(six == d);
  CHECK(settings("[ukf]\nsigma_nT = 2.5\n").at("ukf.sigma_nT") == "2.5");
  CHECK(settings("[ukf]\ncold_start = \"zero\"\n").at("ukf.cold_start") == "zero");
  // A whitelist is a set: its order in the file does not matter.
  CHECK(settings("[service]\nwhitelist = [\"B\", \"A\"]\n").at("service.whitelist") == "[A,B]");
  CHECK(settings("[service]\nwhitelist = [\"A\", \"B\", \"A\"]\n").at("service.whitelist") ==
        "[A,B]");
  // The IGRF file by its content, not its path.
  const std::string dir = std::filesystem::temp_directory_path() /
                          ("magcal_igrf_identity_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  for (const char* name : {"a.txt", "b.txt"}) std::ofstream(dir + "/" + name) << "g 1 0 -29404.8\n";
  const auto igrf = [&](const std::string& name) {
    return settings("[igrf]\ncoefficients_file = \"" + dir + "/" + name + "\"\n")
        .at("igrf.coefficients_file");
  };
  const std::string a = igrf("a.txt");
  CHECK(a.rfind("file fnv1a ", 0) == 0);
  CHECK(igrf("b.txt") == a);
  std::ofstream(dir + "/b.txt") << "g 1 0 -29404.9\n";
  CHECK(igrf("b.txt") != a);
  std::filesystem::remove_all(dir);
}

TEST_CASE("daily time parsing", "[daemon_config]") {
  CHECK(magcal::parse_daily_time_utc("02:00") == 120);
  CHECK(magcal::parse_daily_time_utc("00:00") == 0);
  CHECK(magcal::parse_daily_time_utc("23:59") == 23 * 60 + 59);
  CHECK_FALSE(magcal::parse_daily_time_utc("24:00"));
  CHECK_FALSE(magcal::parse_daily_time_utc("2:00"));
  CHECK_FALSE(magcal::parse_daily_time_utc("02:60"));
  CHECK_FALSE(magcal::parse_daily_time_utc("0200"));
  CHECK_FALSE(magcal::parse_daily_time_utc(""));
}
