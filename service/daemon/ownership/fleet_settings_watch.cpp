#include "service/daemon/ownership/fleet_settings_watch.hpp"

#include <spdlog/spdlog.h>

#include "service/io/station_settings.hpp"

namespace magcal {

FleetSettingsWatch::FleetSettingsWatch(std::string station, storage::StationSettings mine,
                                       DaemonCounters& counters)
    : station_(std::move(station)), mine_(std::move(mine)), counters_(counters) {}

void FleetSettingsWatch::check(const std::vector<storage::StationRow>& rows, int64_t now_utime) {
  std::map<std::string, Seen> live;
  int32_t differing = 0;
  for (const auto& row : rows) {
    if (row.station == station_ || !row.live_at(now_utime)) continue;
    // A station that declares no settings (a row from before schema version 9) is not compared.
    const std::string hash = row.settings ? row.settings->hash : "";
    const bool differs = row.settings && row.settings->text != mine_.text;
    differing += differs;
    live[row.station] = Seen{hash, differs};
    const auto before = seen_.find(row.station);
    if (before != seen_.end() && before->second.hash == hash) continue;  // nothing new
    if (differs) {
      spdlog::warn(
          "settings differ from station {}: {}; results of a spacecraft depend on which station "
          "owns it",
          row.station,
          describe_differences(settings_differences(parse_station_settings(mine_.text),
                                                    parse_station_settings(row.settings->text))));
    } else if (before != seen_.end() && before->second.differs) {
      spdlog::info("settings of station {} now match this station's", row.station);
    }
  }
  seen_ = std::move(live);
  counters_.fleet_settings_mismatch.store(differing, std::memory_order_relaxed);
}

}  // namespace magcal
