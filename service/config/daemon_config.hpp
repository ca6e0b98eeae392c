// magcald's configuration (design.md "The daemon's command line and config"): built-in
// defaults, overridden by a TOML file, overridden by command-line flags. Every key has a default,
// so no file is needed. An unknown key or a bad value is an error naming the key; the daemon
// refuses to start. deploy/magcald.example.toml lists every key with its default.
#pragma once

#include <cmath>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "service/config/refit_schedule.hpp"
#include "storage/connection.hpp"

namespace magcal {

// The host name, the default [station] id ("" when the system has none).
std::string default_station_id();

struct DaemonConfig {
  struct Lcm {
    std::string url;  // "" = LCM's default ($LCM_DEFAULT_URL, else udpm://239.255.76.67:7667)
    // Where results and status go. "" = the input URL, except that a file:// input (replay)
    // publishes nothing unless this is set (e.g. "file:///tmp/out.lcm?mode=w" or a udpm URL).
    std::string publish_url;
    std::string samples_channel = "MAGCAL_SAMPLES";
    std::string batch_channel = "MAGCAL_BATCH";
    std::string calibration_channel = "MAGCAL_CALIBRATION";
    std::string status_channel = "MAGCAL_STATUS";
  } lcm;
  struct Storage {
    std::string db_path = "magcal.db";  // an SQLite file, or a postgresql:// URI (a fleet's)
    double window_hours = 12.0;
    double retention_margin_hours = 1.0;
    int commit_every_samples = 4000;  // one transaction per this many samples...
    int commit_every_ms = 250;        // ...or this much wall time, whichever first
    // How long one statement waits on another connection's lock before it fails (SQLite's busy
    // timeout, PostgreSQL's lock_timeout; the daemon retries it with backoff).
    int busy_timeout_ms = 5000;
    // Storage failing continuously for this long (each failed commit retried with backoff)
    // stops the daemon with exit code 3 so systemd restarts it and an operator is alerted.
    // 60 s rides out what heals by itself (a `magcal refit`, backup or VACUUM holding the write
    // lock; a checkpoint stalled by a slow disk), and is short enough to page someone within a
    // minute of a full disk or a deleted file.
    double max_failure_s = 60.0;
    // Received samples held in memory while commits fail (about 200 bytes each: 40 MB). At the
    // bound the worker stops taking frames: a live feed then overflows the receive queue
    // (counted), a replay waits.
    int64_t max_pending_samples = 200000;
    // The same limit when db_path is a PostgreSQL URI, used instead of max_failure_s. A fleet's
    // server is reached over a network and fails in ways that heal without this host: a restart
    // (seconds), a failover to its standby (repmgr/Patroni: about a minute), a WAN link down or
    // maintenance (minutes to an hour). Meanwhile a station keeps receiving (its samples held
    // in memory, then spilled) and a restart of magcald would not help; past an hour a person
    // has to look, and exit 3 makes systemd log it and restart (the spill is kept).
    double pg_max_failure_s = 3600.0;
    // PostgreSQL: during an outage the pending samples go, each commit interval, to a
    // spill file (service/daemon/intake/sample_spill.hpp) instead of stopping intake, and are
    // committed when the database returns (or at the next start). The file is
    // <spill_dir>/magcal-spill-<station id>.spill; spill_dir "" = $STATE_DIRECTORY (systemd's
    // StateDirectory, /var/lib/magcal) when set, else the working directory: local to this
    // daemon, never shared. Past spill_max_bytes the worker stops taking frames (as without a
    // spill: a live feed overflows its receive queue, counted); 0 = no spill. 1 GiB holds about
    // 6.5 million samples (~160 bytes each): hours of a busy station.
    std::string spill_dir;
    int64_t spill_max_bytes = int64_t{1} << 30;
    // At a stop (SIGTERM/SIGINT), storage that still fails is given up this long after the stop
    // (whatever max_failure_s / pg_max_failure_s allow): exit 3, and the samples neither
    // committed nor spilled are counted and logged as not committed (storage_error). Without it,
    // a stop during a PostgreSQL outage with no spill file to take the held samples (spill off,
    // or full) would retry for pg_max_failure_s, until systemd's SIGKILL at TimeoutStopSec
    // (90 s in deploy/magcald.service) dropped them without a word. 30 s, plus one attempt in
    // flight at that moment (a statement on a dead link fails after 30 s: tcp_user_timeout,
    // storage/postgres/pg_database.cpp), stays well under 90 s; keep it below TimeoutStopSec
    // minus 40 s.
    double stop_max_failure_s = 30.0;
    // PostgreSQL: a statement without the server's reply for this long fails as an outage
    // (storage::OpenOptions::reply_timeout_ms): a server that accepts connections but does not
    // answer (frozen, overloaded, or holding every commit for a synchronous standby that is
    // down) is then ridden out as one that is down, its samples held and spilled, a stop bounded
    // by stop_max_failure_s. Keep twice it plus 10 s under the unit's WatchdogSec (60 s in
    // deploy/magcald.service): a commit attempt may wait for a reply, a reconnect (10 s) and a
    // reply again. The longest statement of a healthy server is a refit's window read (~0.1 s).
    double pg_reply_timeout_s = 10.0;
  } storage;
  struct Refit {
    std::string daily_at_utc = "02:00";
    double every_hours = 0.0;    // 0 = off
    std::string clock = "wall";  // "wall" or "data"
    int min_samples = 1000;
    // A new spacecraft's early refits (EarlyRefitPlan): one each time its stored samples grow by
    // this factor, from min_samples until its data span window_hours; 0 = only the first.
    // sqrt(2) puts one near 8 h at 10 s sampling (2 829 samples): on the paper scenario the
    // bias sigma of a window reaches the UKF's 10 nT `ok` bound at about 8 h, and doubling
    // would wait until 11 h.
    double early_growth = 1.4142135623730951;
    bool robust = false;  // outlier-resistant weighting in the batch fit
  } refit;
  struct Ukf {
    // sigma_nT, process_noise, tuning, consistency monitor; `ok` only after a refit measured the
    // model error (FilterOptions::ok_needs_model_error).
    MagnetometerUkf::Options filter;
    double snapshot_every_s = 60.0;  // of data time
  } ukf;
  GateOptions gates;
  struct Sensor {
    double range_nT = 100000.0;
  } sensor;
  struct Igrf {
    std::string coefficients_file;  // "" = built-in IGRF-14
  } igrf;
  struct Log {
    std::string level = "info";    // trace, debug, info, warn, error, critical, off
    double status_every_s = 60.0;  // counters in the log (the status message is more frequent)
  } log;
  // Time plausibility of incoming samples (spacecraft_tracker.hpp has the rules).
  struct Ingest {
    // A sample more than this past its spacecraft's newest accepted sample is held until
    // later samples corroborate the new time (a data gap, a recorder dump) or the stream
    // contradicts it (time_jump).
    double max_time_jump_s = 3600.0;
    // A sample more than this past the wall clock at receipt is rejected (future_time).
    double max_future_s = 300.0;
  } ingest;
  struct Service {
    std::vector<std::string> whitelist;  // empty = accept every spacecraft
    int64_t queue_capacity_samples = 262144;
    double status_every_s = 2.0;      // daemon_status_t on the status channel
    double min_position_km = 6400.0;  // |r_ecef| outside [min, max] is an absurd position
    double max_position_km = 8000.0;
  } service;

  // This daemon's ground station in a fleet (design.md "Fleet"): the station recorded with the
  // samples it stores first, and the owner name of the spacecraft leases it holds. 1-64
  // printable ASCII characters without spaces; unique per daemon sharing a database.
  struct Station {
    std::string id = default_station_id();  // the host name
  } station;

  // Ownership of spacecraft among the daemons sharing a database (design.md "Fleet"). One
  // daemon alone owns every spacecraft; several share them evenly.
  struct Fleet {
    // A spacecraft's owner renews its lease every lease_s / 3; when the owner dies another
    // daemon takes the spacecraft over within about lease_s * 4/3 (the lease runs out, then
    // the next renewal round of a live daemon takes it). 30 s: a takeover within a
    // minute, and a database hiccup of up to 20 s costs no handover.
    double lease_s = 30.0;
    // The owner's UKF takes the union of all stations' stored samples in time order, up to
    // this much data time behind the newest stored one (or all of them once no new sample
    // came for this long in wall time): a sample another station stores later than that, with
    // an older time, is stored and used by refits, not by the online filter. 60 s covers the
    // delivery delays of live stations; a replay of several stations' logs needs the skew of
    // their replays.
    double reorder_delay_s = 60.0;
  } fleet;

  // The operations server (design.md "Operations surface"): /metrics, /-/healthy, /-/ready, the
  // history API and the page, read-only, on its own thread and database connection.
  struct Http {
    // "ADDR:PORT" ([ADDR]:PORT for IPv6; port 0 = any free port, logged), "" = off. Loopback
    // by default: binding elsewhere is an explicit choice. A port that cannot be bound stops
    // magcald at start (exit 2): monitoring that silently is not there is worse.
    std::string listen = "127.0.0.1:9780";
  } http;

  // Empty when every value is valid; else one line naming the key.
  std::string validate() const;
  // The settings results depend on, "section.key" -> value, for the station's settings text
  // (service/io/station_settings.hpp): every key but the operational ones (the LCM channels,
  // commit cadence, failure limits, spill, log, http, station id); the IGRF file by its content.
  std::map<std::string, std::string> result_settings() const;

  bool data_clock() const { return refit.clock == "data"; }
  // db_path is a PostgreSQL URI (a fleet's database).
  bool postgres() const;
  // What the database's engine means for the daemon's commits, health and spill file
  // (storage::Capabilities): the daemon asks these, never which engine it is.
  storage::Capabilities storage_capabilities() const {
    return storage::capabilities_of(storage.db_path);
  }
  // How long storage may fail before the daemon stops (exit 3): [storage] pg_max_failure_s on
  // PostgreSQL, max_failure_s otherwise; and that key, for messages.
  double storage_max_failure_s() const {
    return postgres() ? storage.pg_max_failure_s : storage.max_failure_s;
  }
  const char* storage_max_failure_key() const {
    return postgres() ? "pg_max_failure_s" : "max_failure_s";
  }
  // How magcald opens the database: [storage] busy_timeout_ms and pg_reply_timeout_s, and a
  // PostgreSQL server unreachable now is an outage, not an error (OpenOptions::connect_later).
  storage::OpenOptions database_options() const {
    return {.busy_timeout_ms = storage.busy_timeout_ms,
            .connect_later = true,
            .reply_timeout_ms = static_cast<int>(std::lround(storage.pg_reply_timeout_s * 1000.0))};
  }
  // The spill file ("" = none: SQLite, or spill_max_bytes = 0). See Storage::spill_dir.
  std::string spill_path() const;
  EarlyRefitPlan early_refits() const { return {refit.min_samples, refit.early_growth}; }
  int64_t window_utime() const { return static_cast<int64_t>(storage.window_hours * 3.6e9); }
  int64_t max_time_jump_utime() const { return static_cast<int64_t>(ingest.max_time_jump_s * 1e6); }
  int64_t max_future_utime() const { return static_cast<int64_t>(ingest.max_future_s * 1e6); }
  int64_t lease_utime() const { return static_cast<int64_t>(fleet.lease_s * 1e6); }
  int64_t reorder_delay_utime() const { return static_cast<int64_t>(fleet.reorder_delay_s * 1e6); }
};

// [refit] daily_at_utc "HH:MM" (00:00-23:59) -> minutes after midnight; nullopt if malformed.
std::optional<int> parse_daily_time_utc(const std::string& text);

struct ConfigLoad {
  DaemonConfig config;
  std::string error;  // empty = ok; names the file and key
  bool ok() const { return error.empty(); }
};

// Defaults overridden by the TOML file at `path` (empty path: defaults only), then validated.
ConfigLoad load_daemon_config(const std::string& path);
// Same from TOML text (tests); `origin` names it in errors.
ConfigLoad parse_daemon_config(const std::string& toml_text, const std::string& origin);

}  // namespace magcal
