// Watches the other live stations' result-affecting settings (service/io/station_settings.hpp)
// from the stations table, once per lease round. A station whose settings differ from this
// one's is a warning, not a refusal: a rolling change of the config across a fleet has to pass
// through such a mixed state, and refusing to start would turn it into an outage. So it is made
// loud and visible instead: one warning per station when it is first seen live with other
// settings (or changes them), naming every differing key with both values, and the gauge
// DaemonCounters::fleet_settings_mismatch (/metrics magcal_fleet_settings_mismatch).
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "service/daemon/ops/health.hpp"
#include "storage/lease_store.hpp"

namespace magcal {

class FleetSettingsWatch {
 public:
  FleetSettingsWatch(std::string station, storage::StationSettings mine, DaemonCounters& counters);

  // What this station declares in its heartbeat.
  const storage::StationSettings& mine() const { return mine_; }
  // Every station's row (LeaseStore::stations()) at now: compares the live others with this
  // station, logs what changed since the last round and sets the gauge.
  void check(const std::vector<storage::StationRow>& rows, int64_t now_utime);

 private:
  const std::string station_;
  const storage::StationSettings mine_;
  DaemonCounters& counters_;
  // Live stations at the last round, each with the hash of the settings it declared ("" for
  // none) and whether they differed from this station's.
  struct Seen {
    std::string hash;
    bool differs = false;
  };
  std::map<std::string, Seen> seen_;
};

}  // namespace magcal
