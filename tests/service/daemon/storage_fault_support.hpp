// What the storage fault tests of magcald share (daemon_fault_injection_test.cpp on SQLite,
// daemon_pg_fault_injection_test.cpp on PostgreSQL): the replay log and config, what the
// samples table holds, and what a daemon that rode out or stopped on a fault published.
#pragma once

#include <signal.h>
#include <sys/mount.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "service/daemon/intake/sample_spill.hpp"
#include "storage/postgres/pg_database.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

namespace magcal::test::storage_faults {

namespace fs = std::filesystem;

inline const std::string kBin = MAGCAL_BIN_DIR;
inline const std::string kSat = "FAULT-1";
constexpr int64_t kT0_utime = 1704081600000000;  // 2024-01-01T04:00:00Z: no data-clock refit
constexpr int64_t kStep_utime = 10'000'000;      // 10 s between samples
constexpr int kBatch = kLogBatch;                // samples per mag_batch_t frame

inline void write_log(const std::string& path, int n, int64_t frame_spacing_us) {
  write_batch_log(path, kSat, kT0_utime, n, frame_spacing_us);
}

// Data-clock refits (none in these logs: no scheduled time, and the first refit, which a replay
// waits for, needs more samples than they hold), a status message every 0.1 s, and `storage`
// keys.
inline std::string write_config(const TempDir& tmp, const std::string& name,
                                const std::string& out_lcm, const std::string& storage) {
  const std::string path = tmp.file(name);
  std::ofstream cfg(path);
  cfg << "[lcm]\npublish_url = \"file://" << out_lcm << "?mode=w\"\n"
      << "[refit]\nclock = \"data\"\nmin_samples = 1000000\n"
      << "[service]\nstatus_every_s = 0.1\n"
      << "[storage]\n"
      << storage;
  return path;
}

// magcald replaying `log_lcm` into `db` at `speed` (1: the recorded pace, 0: at once).
inline std::vector<std::string> daemon_args(const std::string& config, const std::string& db,
                                            const std::string& log_lcm, const std::string& speed) {
  return {kBin + "/magcald",
          "--http-listen",
          "",
          "--config",
          config,
          "--db",
          db,
          "--lcm-url",
          "file://" + log_lcm + "?speed=" + speed};
}

inline pid_t start_daemon(const std::string& config, const std::string& db,
                          const std::string& log_lcm, const std::string& speed,
                          const std::string& out_log) {
  return spawn(daemon_args(config, db, log_lcm, speed), out_log);
}

// The same at once, to its end: its exit code.
inline int run_daemon(const std::string& config, const std::string& db, const std::string& log_lcm,
                      const std::string& out_log) {
  return run(daemon_args(config, db, log_lcm, "0"), out_log);
}

// What the samples table holds, read back with SQLite (read-only; -1 counts: no database).
struct Stored {
  int64_t count = -1;
  int64_t distinct = -1;
  int64_t min_utime = 0;
  int64_t max_utime = 0;
  std::string integrity;
  // The stored samples are exactly the first `count` of the log (what a replay commits in
  // order): only a tail, never committed, can be missing.
  bool is_prefix() const {
    return count == 0 || (count == distinct && min_utime == kT0_utime &&
                          max_utime == kT0_utime + (count - 1) * kStep_utime);
  }
};
inline Stored read_stored_or_throw(const std::string& db) {
  Stored s;
  magcal::storage::OpenOptions ro;
  ro.read_only = true;
  magcal::storage::Database d(db, ro);
  s.integrity = d.integrity_check();
  magcal::storage::Statement q(
      d,
      "SELECT count(*), count(DISTINCT utime), min(utime), max(utime) FROM samples "
      "WHERE sat_id = ?1");
  q.bind(1, kSat);
  REQUIRE(q.step());
  s.count = q.column_int64(0);
  s.distinct = q.column_int64(1);
  s.min_utime = q.is_null(2) ? 0 : q.column_int64(2);
  s.max_utime = q.is_null(3) ? 0 : q.column_int64(3);
  return s;
}

// The same from a PostgreSQL database (no integrity_check there: `integrity` stays empty).
inline Stored read_stored_pg_or_throw(const std::string& uri) {
  Stored s;
  magcal::storage::OpenOptions ro;
  ro.read_only = true;
  magcal::storage::PgDatabase d(uri, ro);
  const auto r = d.execute(
      "SELECT count(*), count(DISTINCT utime), coalesce(min(utime), 0), coalesce(max(utime), 0) "
      "FROM samples WHERE sat_id = $1",
      magcal::storage::PgParams().add(kSat));
  s.count = r.get_int64(0, 0);
  s.distinct = r.get_int64(0, 1);
  s.min_utime = r.get_int64(0, 2);
  s.max_utime = r.get_int64(0, 3);
  return s;
}

inline Stored read_stored(const std::string& db) {
  Stored s;
  const bool postgres = magcal::storage::is_postgres_uri(db);
  if (!postgres && !fs::exists(db)) return s;
  try {
    return postgres ? read_stored_pg_or_throw(db) : read_stored_or_throw(db);
  } catch (const magcal::storage::StorageError& e) {
    s.integrity = e.what();  // not created yet, or not readable
    return s;
  }
}

// magcald replaying `log_lcm` at the recorded pace into `db` (config d.toml in tmp with
// `storage` keys, publishing to out.lcm, its log magcald.log), once it has stored `min_stored`
// samples: its pid.
inline pid_t start_daemon_until_stored(const TempDir& tmp, const std::string& db,
                                       const std::string& log_lcm, const std::string& storage,
                                       int64_t min_stored) {
  const auto cfg = write_config(tmp, "d.toml", tmp.file("out.lcm"), storage);
  const pid_t d = start_daemon(cfg, db, log_lcm, "1", tmp.file("magcald.log"));
  REQUIRE(d > 0);
  REQUIRE(wait_until([&] { return read_stored(db).count >= min_stored; }, 20));
  return d;
}

// A restart once the fault is gone: the same replay of the n samples in `log_lcm` at once
// (config rerun.toml in tmp with `storage` keys, publishing to rerun.lcm, its log rerun.log)
// stores the rest and counts the `already_stored` ones as duplicates; then `db` holds every
// sample once (on SQLite, a sound file). Returns the replay's last status message.
inline magcal::daemon_status_t expect_rerun_fills(const TempDir& tmp, const std::string& storage,
                                                  const std::string& db, const std::string& log_lcm,
                                                  int64_t already_stored, int64_t n) {
  const auto cfg = write_config(tmp, "rerun.toml", tmp.file("rerun.lcm"), storage);
  const int rc = run_daemon(cfg, db, log_lcm, tmp.file("rerun.log"));
  INFO(slurp(tmp.file("rerun.log")));
  REQUIRE(rc == 0);
  const auto pub = read_published(tmp.file("rerun.lcm"));
  REQUIRE_FALSE(pub.statuses.empty());
  const auto& s = pub.statuses.back();
  CHECK(s.received == n);
  CHECK(rejected(s, "duplicate") == already_stored);
  CHECK(s.rejected == already_stored);
  CHECK(s.stored == n - already_stored);
  const auto st = read_stored(db);
  if (!magcal::storage::is_postgres_uri(db)) CHECK(st.integrity == "ok");
  CHECK(st.count == n);
  CHECK(st.distinct == n);
  return s;
}

// magcald replaying `log_lcm` into `db` at the recorded pace (config `config`, its log kill.log in
// tmp), killed with SIGKILL `delay_ms` after `ready` holds (or ended by then): what the kill left
// in `db`. `ready` is a condition on the replay's progress, so the deadline is generous.
inline Stored kill_replay_after(const TempDir& tmp, const std::string& config,
                                const std::string& db, const std::string& log_lcm,
                                const std::function<bool()>& ready, int delay_ms) {
  const pid_t d = start_daemon(config, db, log_lcm, "1", tmp.file("kill.log"));
  REQUIRE(d > 0);
  REQUIRE(wait_until(ready, 60));
  std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
  ::kill(d, SIGKILL);
  const int killed_rc = wait_exit(d, 10);
  REQUIRE((killed_rc == -2 || killed_rc == 0));  // killed, or the replay had ended
  return read_stored(db);
}

// The kill -9 tests' record of the n-sample replays they killed: each kill's stored count, checked
// against what the daemon had published (nothing it reported stored is lost; its last status
// messages may be lost with it: the output log is buffered).
struct KillTally {
  explicit KillTally(int64_t samples) : n(samples) {}
  int64_t n;
  int mid_stream = 0;       // kills that left part of the replay stored
  int64_t max_missing = 0;  // the most samples a kill left to the re-replay
  std::string kept;         // samples stored at each kill
  void add(int64_t stored, const std::string& out_lcm) {
    const auto pub = read_published(out_lcm);
    if (!pub.statuses.empty()) CHECK(stored >= pub.statuses.back().stored);
    if (stored > 0 && stored < n) ++mid_stream;
    kept += std::to_string(stored) + " ";
    max_missing = std::max(max_missing, n - stored);
  }
  std::string summary(int kills) const {
    return std::to_string(kills) + " kills, " + std::to_string(mid_stream) +
           " mid-stream, at most " + std::to_string(max_missing) + " of " + std::to_string(n) +
           " samples missing before the re-replay; stored at each kill: " + kept;
  }
};

// A tmpfs of `size` mounted by the test (needs root or CAP_SYS_ADMIN; CI runs as root).
struct TmpfsMount {
  std::string dir;
  bool mounted = false;
  TmpfsMount(const std::string& path, const std::string& size) : dir(path) {
    fs::create_directories(dir);
    mounted = ::mount("tmpfs", dir.c_str(), "tmpfs", 0, ("size=" + size).c_str()) == 0;
  }
  ~TmpfsMount() {
    if (mounted) ::umount2(dir.c_str(), MNT_DETACH);
  }
};

inline pid_t hold_write_lock(const TempDir& tmp, const std::string& db, int hold_s) {
  return magcal::test::hold_write_lock(tmp.file("lock.sql"), tmp.file("lock.log"), db, hold_s);
}

// A replay that rode out a lock held past the storage timeout, from its status messages
// (`out_lcm`): health said so while the lock was held (status every 0.1 s, lock 2 s), and at the
// end every one of the n samples is stored, nothing pending, the failures counted and retried.
struct LockRiddenOut {
  magcal::daemon_status_t last;
  int unhealthy = 0;  // status messages that said storage was failing
};
inline LockRiddenOut expect_lock_ridden_out(const std::string& out_lcm, int64_t n) {
  const auto pub = read_published(out_lcm);
  REQUIRE_FALSE(pub.statuses.empty());
  LockRiddenOut r{pub.statuses.back(), 0};
  for (const auto& s : pub.statuses) r.unhealthy += s.storage_healthy ? 0 : 1;
  CHECK(r.unhealthy >= 5);
  CHECK(r.last.storage_healthy);
  CHECK(r.last.received == n);
  CHECK(r.last.stored == n);
  CHECK(r.last.rejected == 0);
  CHECK(r.last.queue_overflow == 0);
  CHECK(r.last.storage_pending == 0);
  CHECK(r.last.storage_failures >= 1);
  CHECK(r.last.storage_retries >= 1);
  return r;
}

// A magcald that must stop because storage stays broken: exit 3, the reason in its log, and
// books that balance: every received sample stored, counted as not committed (storage_error,
// also the frame a blocked replay push was handing over at the stop), or (PostgreSQL) held by
// the spill file `spill_file` for the next start. A replay's queue blocks: nothing overflows.
struct StorageStop {
  int rc = 0;
  double seconds = 0.0;  // from the call to the exit
  magcal::daemon_status_t last{};
  int64_t not_committed = 0;
  int64_t spilled = 0;
};
inline StorageStop expect_storage_stop(pid_t d, const std::string& log_file,
                                       const std::string& out_lcm, const std::string& reason,
                                       const std::string& spill_file = "") {
  StorageStop r;
  const auto t0 = Clock::now();
  r.rc = wait_exit(d, 60);
  r.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  const std::string daemon_log = slurp(log_file);
  INFO(daemon_log);
  CHECK(r.rc == 3);
  CHECK_THAT(daemon_log, Catch::Contains(reason));
  const auto pub = read_published(out_lcm);
  REQUIRE_FALSE(pub.statuses.empty());
  r.last = pub.statuses.back();
  r.not_committed = rejected(r.last, "storage_error");
  if (!spill_file.empty() && fs::exists(spill_file)) {
    r.spilled = magcal::SampleSpill(spill_file, "", int64_t{1} << 30).held_samples();
    CHECK_THAT(daemon_log, Catch::Contains("pending samples spilled: committed at the next start"));
  }
  if (r.not_committed > 0) {
    CHECK_THAT(daemon_log, Catch::Contains("received samples were not committed"));
  }
  CHECK(r.not_committed + r.spilled > 0);
  CHECK(r.last.rejected == r.not_committed + rejected(r.last, "duplicate"));
  CHECK(r.last.received == r.last.stored + r.last.rejected + r.last.queue_overflow + r.spilled);
  CHECK(r.last.queue_overflow == 0);
  CHECK_FALSE(r.last.storage_healthy);
  CHECK(r.last.storage_failures >= 1);
  return r;
}

// A temporary folder with a replay log of n samples (write_log) and a database path.
struct Scenario {
  TempDir tmp;
  std::string log;
  std::string db;
  Scenario(const std::string& name, int n, int64_t frame_spacing_us)
      : tmp(name), log(tmp.file("day.lcm")), db(tmp.file("m.db")) {
    write_log(log, n, frame_spacing_us);
  }
};

}  // namespace magcal::test::storage_faults
