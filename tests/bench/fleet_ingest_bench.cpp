// Fleet ingest throughput (issue 19 "Benchmarks"): real magcald processes replaying LCM logs
// (file://...?speed=0) into one database, in paired rounds of four cases so that load from
// elsewhere on the machine hits them alike:
//   sqlite_1        one daemon, the whole fleet's log, an SQLite file (WAL) in /tmp
//   pg_1            one daemon, the same log, a PostgreSQL database
//   pg_3_disjoint   three daemons (--station A|B|C) on one PostgreSQL database, each replaying
//                   the passes of a third of the spacecraft (sat index mod 3)
//   pg_3_overlap    three daemons, each spacecraft's passes dealt round-robin to the stations
//                   (pass p of spacecraft s to station (s + p) mod 3), each pass also carrying
//                   the previous pass's last kOverlapSamples samples, which the previous station
//                   delivered too: those copies are duplicates (stored once, counted). The
//                   three replays (speed=0) drift apart in data time by more than
//                   [fleet] reorder_delay_s, so an owner's filter passes samples another station
//                   stores late (counted in missing_by_seq): fewer UKF snapshots than pg_1 (live
//                   stations receive in step); pg_3_disjoint stores as many as pg_1.
// The fleet: <spacecraft> spacecraft (default 1 000, the design's nightly-refit fleet), one
// sample per 10 s each, passes of 10 minutes (60 samples, one mag_batch_t frame with the
// reference field in it), <samples per spacecraft> each (default 720: 2 h, so that most samples
// meet a running UKF, which starts after ~30 min of data here), frames ordered by time across
// the fleet. Refits are off ([refit] min_samples above any spacecraft's count; they are
// measured by refit_fleet_bench); UKF snapshots are stored as by default (one per 60 s of data).
//
// samples/s = sample rows in the database after the case (counted through the storage API: the
// union, each sample once) / wall time from the first daemon's start to the last daemon's exit
// (open, migrations and the final drain included). Per daemon: received / stored / duplicates from
// its "final status:" log line (-1 when a later daemon words it differently: the rows still count).
// Any daemon exiting non-zero, or rows != the fleet's distinct samples, is an error. Also the
// UKF snapshot rows the daemons stored, the rest of what ingest writes, and on PostgreSQL the
// server's own count of commits, rows written and read, deadlocks (pg_stat_database).
// CPU: user+sys seconds of the daemons (wait4) and of the PostgreSQL server (the postmaster,
// its reaped backends and its live children, from /proc), the machine's busy CPU seconds
// (/proc/stat) and what of it was neither (other processes), against nproc x wall; and stored
// samples per CPU second of daemons + server, which says what a case costs whether or not the
// cores were saturated.
//
// The PostgreSQL server is a throwaway one (tests/storage/postgres/pg_test_server.hpp:
// synchronous_commit off, the like-for-like setting to SQLite's WAL + synchronous=NORMAL, and
// fsync off, which spares PostgreSQL the checkpoints' fsyncs that SQLite still pays), on the
// same machine as the daemons: they share its cores.
//   build/bin/fleet_ingest_bench --benchmark_format=json
//   BM_FleetIngest/<spacecraft>/<samples per spacecraft>/<rounds>; medians over the rounds.
// Needs the PostgreSQL server programs (postgresql-15); without them the benchmark reports an
// error naming what is missing.
#include <benchmark/benchmark.h>

#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "schemas/magcal_messages.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/postgres/pg_database.hpp"
#include "storage/sample_window_store.hpp"
#include "tests/process_support.hpp"
#include "tests/service/daemon_test_support.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace {

using magcal::test::slurp;
using magcal::test::spawn;
namespace storage = magcal::storage;

const std::string kBin = MAGCAL_BIN_DIR;
constexpr int64_t kT0_utime = 1704067200000000;  // 2024-01-01
constexpr int64_t kStep_utime = 10'000'000;      // 10 s per sample
constexpr int kPassSamples = 60;                 // a 10-minute pass
constexpr int kOverlapSamples = 12;              // 2 minutes seen by both neighbours
constexpr int kStations = 3;
constexpr double kDaemonTimeout_s = 900;

std::string sat_name(int s) {
  return "FLEET-" + std::to_string(s);
}

// Sample k of spacecraft s: the field in the body frame turning through all directions (the
// orbit and a slow tumble: a turn in ~20 min about one axis, ~50 min about another), each
// spacecraft at its own phase, seen with a constant bias and 3 nT noise. The UKFs start after
// about half an hour of data (measured: ~170 samples), so most of a 2 h run is the steady
// state: every sample updates a running filter, and snapshots are stored.
magcal::mag_sample_t make_sample(int s, int k, std::mt19937& rng) {
  std::normal_distribution<double> noise(0.0, 3.0);
  magcal::mag_sample_t out{};
  out.utime = kT0_utime + k * kStep_utime;
  out.sat_id = sat_name(s);
  out.seq = k;
  const double u = 0.05 * k + s, v = 0.02 * k + 0.5 * s;
  const double h[3] = {30000.0 * std::cos(u) * std::cos(v), 30000.0 * std::sin(u) * std::cos(v),
                       30000.0 * std::sin(v)};
  for (int i = 0; i < 3; ++i) {
    out.h_body_nT[i] = h[i];
    out.b_sensor_nT[i] = h[i] + 1000.0 * (i + 1) + noise(rng);
  }
  out.has_reference = true;
  out.temperature_C = std::nanf("");
  return out;
}

// The fleet's logs: the merged one (every sample once) and each station's, for both splits.
struct FleetLogs {
  std::string merged;
  std::array<std::string, kStations> disjoint, overlap;
  int64_t distinct = 0;         // samples of the fleet (= rows after any case)
  int64_t overlap_offered = 0;  // samples in the three overlap logs together
};

FleetLogs write_logs(const std::string& dir, int n_sats, int samples_per_sat) {
  FleetLogs logs;
  logs.merged = dir + "/merged.lcm";
  lcm::LogFile merged(logs.merged, "w");
  std::vector<std::unique_ptr<lcm::LogFile>> disjoint, overlap;
  for (int st = 0; st < kStations; ++st) {
    logs.disjoint[st] = dir + "/disjoint_" + std::to_string(st) + ".lcm";
    logs.overlap[st] = dir + "/overlap_" + std::to_string(st) + ".lcm";
    disjoint.push_back(std::make_unique<lcm::LogFile>(logs.disjoint[st], "w"));
    overlap.push_back(std::make_unique<lcm::LogFile>(logs.overlap[st], "w"));
  }
  std::map<lcm::LogFile*, int64_t> events;
  auto write = [&events](lcm::LogFile& out, const magcal::mag_batch_t& b) {
    int64_t& n = events[&out];
    magcal::test::write_log_event(out, n, kT0_utime + n * 1000, "MAGCAL_BATCH", b);
    ++n;
  };
  std::mt19937 rng(7);
  const int passes = std::max(1, samples_per_sat / kPassSamples);
  std::vector<magcal::mag_sample_t> previous_tail(static_cast<size_t>(n_sats) * kOverlapSamples);
  for (int p = 0; p < passes; ++p) {
    for (int s = 0; s < n_sats; ++s) {
      magcal::mag_batch_t pass, with_overlap;
      pass.sat_id = with_overlap.sat_id = sat_name(s);
      auto* tail = &previous_tail[static_cast<size_t>(s) * kOverlapSamples];
      if (p > 0) with_overlap.samples.assign(tail, tail + kOverlapSamples);
      for (int i = 0; i < kPassSamples; ++i) {
        pass.samples.push_back(make_sample(s, p * kPassSamples + i, rng));
      }
      with_overlap.samples.insert(with_overlap.samples.end(), pass.samples.begin(),
                                  pass.samples.end());
      std::copy(pass.samples.end() - kOverlapSamples, pass.samples.end(), tail);
      pass.n = static_cast<int32_t>(pass.samples.size());
      with_overlap.n = static_cast<int32_t>(with_overlap.samples.size());
      write(merged, pass);
      write(*disjoint[static_cast<size_t>(s % kStations)], pass);
      write(*overlap[static_cast<size_t>((s + p) % kStations)], with_overlap);
      logs.distinct += pass.n;
      logs.overlap_offered += with_overlap.n;
    }
  }
  return logs;
}

// CPU seconds (user + sys) from /proc: a process with its reaped children, and the machine.
double clock_ticks_s(int64_t ticks) {
  return static_cast<double>(ticks) / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

// Fields 14-17 of /proc/PID/stat (utime stime cutime cstime) and field 4 (ppid); false when gone.
bool read_stat(const std::string& pid, int64_t& ppid, std::array<int64_t, 4>& times) {
  std::ifstream in("/proc/" + pid + "/stat");
  std::string text;
  if (!std::getline(in, text)) return false;
  const size_t close = text.rfind(')');  // the command name may hold spaces
  if (close == std::string::npos) return false;
  std::istringstream fields(text.substr(close + 2));
  std::string skip;
  fields >> skip >> ppid;  // state, ppid
  for (int i = 0; i < 9; ++i) fields >> skip;
  for (auto& t : times) fields >> t;
  return static_cast<bool>(fields);
}

// The PostgreSQL server's CPU seconds so far: the postmaster, the backends it reaped, and the
// processes alive under it now.
double postgres_cpu_s(const magcal::test::PgTestServer& server) {
  std::ifstream pidfile(server.dir() + "/data/postmaster.pid");
  std::string postmaster;
  if (!std::getline(pidfile, postmaster)) return 0.0;
  int64_t ppid = 0;
  std::array<int64_t, 4> t{};
  if (!read_stat(postmaster, ppid, t)) return 0.0;
  int64_t ticks = t[0] + t[1] + t[2] + t[3];
  for (const auto& entry : std::filesystem::directory_iterator("/proc")) {
    const std::string pid = entry.path().filename().string();
    if (pid.empty() || !std::all_of(pid.begin(), pid.end(), ::isdigit)) continue;
    if (read_stat(pid, ppid, t) && std::to_string(ppid) == postmaster) ticks += t[0] + t[1];
  }
  return clock_ticks_s(ticks);
}

// Busy CPU seconds of the whole machine so far (all but idle and iowait).
double machine_busy_cpu_s() {
  std::ifstream in("/proc/stat");
  std::string cpu;
  in >> cpu;
  int64_t v = 0, busy = 0;
  for (int i = 0; i < 8 && in >> v; ++i) busy += (i == 3 || i == 4) ? 0 : v;
  return clock_ticks_s(busy);
}

// What the PostgreSQL server did for one database (pg_stat_database, flushed by each backend
// at its exit, so complete once the daemons have exited): commits, rows written and read (an
// index scan's rows are "fetched", a sequential scan's "returned"), deadlocks.
struct PgActivity {
  int64_t commits = 0, rows_inserted = 0, rows_updated = 0, rows_deleted = 0, rows_fetched = 0,
          rows_returned = 0, deadlocks = 0;
  int64_t calibration_rows_inserted = 0;
};

PgActivity pg_activity(const std::string& uri) {
  storage::OpenOptions no_schema;
  no_schema.migrate_to = 0;  // only reads the statistics
  storage::PgDatabase db(uri, no_schema);
  const storage::PgResult r = db.execute(
      "SELECT xact_commit, tup_inserted, tup_updated, tup_deleted, tup_fetched, tup_returned, "
      "deadlocks, (SELECT n_tup_ins FROM pg_stat_user_tables WHERE relname = 'calibrations') "
      "FROM pg_stat_database WHERE datname = current_database()");
  PgActivity a;
  if (r.rows() != 1) return a;
  for (auto [column, field] : {std::pair{0, &a.commits},
                               {1, &a.rows_inserted},
                               {2, &a.rows_updated},
                               {3, &a.rows_deleted},
                               {4, &a.rows_fetched},
                               {5, &a.rows_returned},
                               {6, &a.deadlocks},
                               {7, &a.calibration_rows_inserted}}) {
    *field = r.get_int64(0, column);
  }
  return a;
}

struct DaemonRun {
  int exit_code = 0;
  double cpu_s = 0.0;
  int64_t received = -1, stored = -1, duplicates = -1;
  std::string log;
};

struct CaseRun {
  double wall_s = 0.0;
  int64_t rows = 0, ukf_rows = 0;
  PgActivity pg;
  double daemons_cpu_s = 0.0, postgres_cpu_s = 0.0, machine_busy_s = 0.0;
  std::vector<DaemonRun> daemons;
  std::string error;
};

// "final status: received=R stored=S rejected=X (duplicate=D ...)" of a daemon's log.
void parse_final_status(DaemonRun& d) {
  std::smatch m;
  if (std::regex_search(d.log, m, std::regex(R"(final status: received=(\d+) stored=(\d+))"))) {
    d.received = std::stoll(m[1].str());
    d.stored = std::stoll(m[2].str());
    d.duplicates = 0;
  }
  if (std::regex_search(d.log, m, std::regex(R"(final status: [^\n]*[ (]duplicate=(\d+))"))) {
    d.duplicates = std::stoll(m[1].str());
  }
}

// The sample rows of `db` and its calibration rows (UKF snapshots: refits are off), the other
// rows ingest writes. On PostgreSQL the server's count of inserted calibration rows: reading
// them back costs a round trip for each row with rejection reasons (PgCalibrationHistory).
std::pair<int64_t, int64_t> rows_in(const std::string& db, int n_sats) {
  storage::OpenOptions read_only;
  read_only.read_only = true;
  const auto connection = storage::open_database(db, read_only);
  const auto samples = connection->make_sample_window_store();
  const auto history = connection->make_calibration_history();
  const bool postgres = storage::is_postgres_uri(db);
  int64_t rows = 0, calibrations = 0;
  for (int s = 0; s < n_sats; ++s) {
    rows += samples->count(sat_name(s));
    storage::HistoryQuery q;
    q.sat_id = sat_name(s);
    if (!postgres) calibrations += static_cast<int64_t>(history->query(q).size());
  }
  if (postgres) calibrations = pg_activity(db).calibration_rows_inserted;
  return {rows, calibrations};
}

// The daemons replaying `logs` (one each, station i = "station-" + letter) into `db`, at once.
CaseRun run_case(const std::vector<std::string>& logs, const std::string& db,
                 const std::string& config, const std::string& dir, const std::string& name,
                 int n_sats, const magcal::test::PgTestServer* server) {
  CaseRun out;
  const double pg_before = server ? postgres_cpu_s(*server) : 0.0;
  const double busy_before = machine_busy_cpu_s();
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<pid_t> pids;
  for (size_t i = 0; i < logs.size(); ++i) {
    const std::string log = dir + "/" + name + "_" + std::to_string(i) + ".log";
    std::filesystem::remove(log);
    out.daemons.push_back({});
    out.daemons.back().log = log;
    pids.push_back(spawn({kBin + "/magcald", "--config", config, "--db", db, "--station",
                          std::string("station-") + static_cast<char>('A' + i), "--http-listen", "",
                          "--lcm-url", "file://" + logs[i] + "?speed=0"},
                         log));
  }
  const auto deadline = t0 + std::chrono::duration<double>(kDaemonTimeout_s);
  for (size_t i = 0; i < pids.size(); ++i) {
    DaemonRun& d = out.daemons[i];
    if (pids[i] < 0) {
      d.exit_code = -3;
      continue;
    }
    int status = 0;
    rusage usage{};
    while (::wait4(pids[i], &status, WNOHANG, &usage) == 0) {
      if (std::chrono::steady_clock::now() > deadline) {
        ::kill(pids[i], SIGKILL);
        ::wait4(pids[i], &status, 0, &usage);
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    d.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -2;
    d.cpu_s = static_cast<double>(usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) +
              1e-6 * static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
  }
  out.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  out.machine_busy_s = machine_busy_cpu_s() - busy_before;
  out.postgres_cpu_s = server ? postgres_cpu_s(*server) - pg_before : 0.0;
  for (DaemonRun& d : out.daemons) {
    const std::string path = d.log;
    d.log = slurp(path);
    parse_final_status(d);
    out.daemons_cpu_s += d.cpu_s;
    if (d.exit_code != 0 && out.error.empty()) {
      out.error = name + ": magcald exit code " + std::to_string(d.exit_code) + ", log " + path;
    }
  }
  if (out.error.empty()) {
    try {
      if (server) out.pg = pg_activity(db);  // before the counting below reads rows
      std::tie(out.rows, out.ukf_rows) = rows_in(db, n_sats);
    } catch (const std::exception& e) {
      out.error = name + ": counting rows: " + e.what();
    }
  }
  return out;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

struct CaseSummary {
  std::vector<double> samples_per_s, received_per_s, samples_per_cpu_s, wall_s, daemons_cpu_s,
      postgres_cpu_s, others_cpu_s;
  int64_t offered = 0, stored = 0, duplicates = 0;  // daemons' own counts, last round
  int64_t ukf_rows = 0;                             // last round
  PgActivity pg;                                    // last round
  bool counts_known = true;
};

void add(CaseSummary& s, const CaseRun& run) {
  s.samples_per_s.push_back(static_cast<double>(run.rows) / run.wall_s);
  s.samples_per_cpu_s.push_back(static_cast<double>(run.rows) /
                                (run.daemons_cpu_s + run.postgres_cpu_s));
  s.wall_s.push_back(run.wall_s);
  s.daemons_cpu_s.push_back(run.daemons_cpu_s);
  s.postgres_cpu_s.push_back(run.postgres_cpu_s);
  s.others_cpu_s.push_back(
      std::max(0.0, run.machine_busy_s - run.daemons_cpu_s - run.postgres_cpu_s));
  s.offered = s.stored = s.duplicates = 0;
  s.ukf_rows = run.ukf_rows;
  s.pg = run.pg;
  for (const DaemonRun& d : run.daemons) {
    s.counts_known = s.counts_known && d.received >= 0;
    s.offered += d.received;
    s.stored += d.stored;
    s.duplicates += d.duplicates;
  }
  s.received_per_s.push_back(static_cast<double>(s.offered) / run.wall_s);
}

void BM_FleetIngest(benchmark::State& state) {
  const int n_sats = static_cast<int>(state.range(0));
  const int samples_per_sat = static_cast<int>(state.range(1));
  const int rounds = static_cast<int>(state.range(2));
  magcal::test::PgTestServer server;
  if (!server.unavailable_reason().empty() || !server.error().empty()) {
    const std::string why = "PostgreSQL: " + server.unavailable_reason() + server.error();
    state.SkipWithError(why.c_str());
    return;
  }
  const std::string dir = server.dir() + "/bench";  // removed with the server
  std::filesystem::create_directories(dir);
  const FleetLogs logs = write_logs(dir, n_sats, samples_per_sat);
  const std::string config = dir + "/magcald.toml";
  {
    std::ofstream out(config);
    // No refit: min_samples beyond any spacecraft's count. The spill files in the bench's own
    // folder: a daemon refuses to start beside another run's spill file (which an interrupted
    // run would leave in the working directory).
    out << "[refit]\nclock = \"data\"\nmin_samples = " << samples_per_sat + 1 << "\n"
        << "[storage]\nspill_dir = \"" << dir << "\"\n";
  }
  const std::vector<std::string> merged{logs.merged};
  const std::vector<std::string> disjoint(logs.disjoint.begin(), logs.disjoint.end());
  const std::vector<std::string> overlap(logs.overlap.begin(), logs.overlap.end());
  const std::array<std::string, 4> names{"sqlite_1", "pg_1", "pg_3_disjoint", "pg_3_overlap"};
  std::array<CaseSummary, 4> summary;
  for (auto _ : state) {
    for (int r = 0; r < rounds; ++r) {
      for (size_t c = 0; c < names.size(); ++c) {
        const bool sqlite = c == 0;
        const std::string db =
            sqlite ? dir + "/round" + std::to_string(r) + ".db" : server.create_database();
        const CaseRun run = run_case(c == 0 || c == 1 ? merged
                                     : c == 2         ? disjoint
                                                      : overlap,
                                     db, config, dir, names[c], n_sats, sqlite ? nullptr : &server);
        std::string error = run.error;
        if (error.empty() && run.rows != logs.distinct) {
          error = names[c] + ": " + std::to_string(run.rows) + " rows, the fleet has " +
                  std::to_string(logs.distinct) + " samples";
        }
        if (!error.empty()) {
          state.SkipWithError(error.c_str());
          return;
        }
        add(summary[c], run);
        if (sqlite) {
          for (const char* suffix : {"", "-wal", "-shm"}) std::filesystem::remove(db + suffix);
        }
      }
    }
  }
  state.counters["nproc"] = static_cast<double>(std::thread::hardware_concurrency());
  state.counters["spacecraft"] = n_sats;
  state.counters["distinct_samples"] = static_cast<double>(logs.distinct);
  state.counters["overlap_offered_samples"] = static_cast<double>(logs.overlap_offered);
  for (size_t c = 0; c < names.size(); ++c) {
    const CaseSummary& s = summary[c];
    state.counters[names[c] + "_samples_per_s"] = median(s.samples_per_s);
    state.counters[names[c] + "_samples_per_s_min"] =
        *std::min_element(s.samples_per_s.begin(), s.samples_per_s.end());
    state.counters[names[c] + "_samples_per_s_max"] =
        *std::max_element(s.samples_per_s.begin(), s.samples_per_s.end());
    // Samples received (duplicates included) per second: what the stations took in.
    if (s.counts_known) state.counters[names[c] + "_received_per_s"] = median(s.received_per_s);
    // Stored samples per CPU second of the daemons and the server together: nproc times this is
    // the rate the case would reach with every core to itself.
    state.counters[names[c] + "_samples_per_cpu_s"] = median(s.samples_per_cpu_s);
    state.counters[names[c] + "_wall_s"] = median(s.wall_s);
    state.counters[names[c] + "_daemons_cpu_s"] = median(s.daemons_cpu_s);
    state.counters[names[c] + "_postgres_cpu_s"] = median(s.postgres_cpu_s);
    state.counters[names[c] + "_other_processes_cpu_s"] = median(s.others_cpu_s);
    // Of the machine's nproc x wall CPU seconds, the share the daemons and the server used.
    state.counters[names[c] + "_cpu_utilisation"] =
        (median(s.daemons_cpu_s) + median(s.postgres_cpu_s)) /
        (median(s.wall_s) * std::thread::hardware_concurrency());
    state.counters[names[c] + "_ukf_snapshot_rows"] = static_cast<double>(s.ukf_rows);
    if (c > 0) {
      const std::string pg = names[c] + "_pg_";
      state.counters[pg + "commits"] = static_cast<double>(s.pg.commits);
      state.counters[pg + "rows_inserted"] = static_cast<double>(s.pg.rows_inserted);
      state.counters[pg + "rows_updated"] = static_cast<double>(s.pg.rows_updated);
      state.counters[pg + "rows_deleted"] = static_cast<double>(s.pg.rows_deleted);
      state.counters[pg + "rows_fetched"] = static_cast<double>(s.pg.rows_fetched);
      state.counters[pg + "rows_returned"] = static_cast<double>(s.pg.rows_returned);
      state.counters[pg + "deadlocks"] = static_cast<double>(s.pg.deadlocks);
    }
    state.counters[names[c] + "_daemons_received"] =
        static_cast<double>(s.counts_known ? s.offered : -1);
    state.counters[names[c] + "_daemons_stored"] =
        static_cast<double>(s.counts_known ? s.stored : -1);
    state.counters[names[c] + "_daemons_duplicates"] =
        static_cast<double>(s.counts_known ? s.duplicates : -1);
  }
  const double sqlite_1 = median(summary[0].samples_per_s), pg_1 = median(summary[1].samples_per_s);
  state.counters["pg_1_over_sqlite_1"] = pg_1 / sqlite_1;  // target >= 0.5
  state.counters["pg_3_disjoint_over_pg_1"] = median(summary[2].samples_per_s) / pg_1;  // >= 1.5
  state.counters["pg_3_overlap_over_pg_1"] = median(summary[3].samples_per_s) / pg_1;
  // What three daemons could reach if they had every core of the machine, at the CPU cost per
  // sample they measured, against one daemon's rate: the ceiling of pg_3_disjoint_over_pg_1 here.
  state.counters["pg_3_disjoint_cpu_ceiling_over_pg_1"] =
      std::thread::hardware_concurrency() * median(summary[2].samples_per_cpu_s) / pg_1;
  state.SetItemsProcessed(static_cast<int64_t>(logs.distinct) * rounds *
                          static_cast<int64_t>(names.size()));
}
BENCHMARK(BM_FleetIngest)
    ->Args({1000, 720, 3})
    ->Iterations(1)
    ->Unit(benchmark::kSecond)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
