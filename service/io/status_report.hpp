// Per spacecraft, what operations watch — last sample time, samples in the refit window, the
// last UKF estimate with its 1-sigma, the last refit with its verdict and job outcome, and the
// change of bias since the previous refit: the text and JSON of `magcal status [--json]` and
// of GET /api/v1/spacecraft, built once here so that both answer byte for byte the same.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "service/io/station_settings.hpp"
#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

struct SpacecraftStatus {
  std::string sat_id;
  std::optional<int64_t> last_sample_utime;
  int64_t samples_in_window = 0;  // in (last sample - window, last sample]
  // The same samples by the station that stored them (design.md "Fleet"), sorted by station;
  // "" for samples stored without one.
  std::vector<storage::StationCount> samples_by_station;
  // Its lease (design.md "Fleet": the daemon that runs its UKF and refits), none before any
  // daemon registered it; owner_now: held at the time of the read.
  std::optional<storage::Lease> lease;
  bool owner_now = false;
  std::optional<storage::CalibrationRecord> last_ukf, last_refit, previous_refit;
  std::optional<storage::RefitJob> last_job;
};

// A daemon sharing the database (design.md "Fleet"; one daemon alone is a fleet of one): live
// while its heartbeat has not expired at the time of the read (wall clock).
struct StationStatus {
  storage::StationRow row;
  bool live = false;
  int64_t spacecraft_owned = 0;  // leases it holds at the time of the read
  // A live station whose result-affecting settings (service/io/station_settings.hpp) differ
  // from the fleet's: from the live stations sharing the most common settings, or, when no
  // settings are the most common, from the first other live station (and those sharing its
  // settings). Empty: not marked (it agrees with the majority, is gone, or declares none).
  std::vector<std::string> settings_differ_from;
  std::vector<SettingDifference> settings_differences;  // here: this station's, there: theirs
};

struct FleetStatus {
  std::vector<SpacecraftStatus> spacecraft;  // sorted by sat_id
  std::vector<StationStatus> stations;       // sorted by station id
};

// Every spacecraft with samples or results and every station that ever beat, read in one
// snapshot (a short deferred read transaction) on `db`, which may be read-only. window_utime:
// the refit window the samples are counted in (the daemon's [storage] window_hours). Throws
// StorageError.
FleetStatus read_status(storage::Connection& db, int64_t window_utime);

// `magcal status --json`: {"spacecraft": [{sat_id, last_sample_time, last_sample_utime,
// samples_in_window, samples_by_station ([{station (null: none), samples}]), owner ({station,
// lease_epoch, lease_expires_time, lease_expires_utime}; null: no daemon holds its lease now),
// last_owner (the same for the lease row held or not; null: none), window_hours,
// last_ukf, last_refit (history objects or null), last_refit_job,
// bias_change_since_previous_refit_nT}], "stations": [{station, live, heartbeat_time,
// heartbeat_utime, expires_time, expires_utime (wall clock: live until then; a clean stop ends
// it at once), spacecraft_owned, settings_hash (null: none declared), settings_differ (null, or
// {from: [station], keys: [{key, here, there}]}: StationStatus)}]}.
nlohmann::json status_json(const FleetStatus& fleet, int64_t window_utime);
// The exact stdout of `magcal status --json` (dumped with indent 2 and a final newline).
std::string status_json_text(const FleetStatus& fleet, int64_t window_utime);
// The exact stdout of `magcal status`: each spacecraft, then the stations.
std::string status_text(const FleetStatus& fleet, int64_t window_utime);

}  // namespace magcal
