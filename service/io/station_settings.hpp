// The settings a station's results depend on (design.md "Fleet"). Leases move spacecraft
// between the daemons sharing a database, and a spacecraft's UKF and refits run under whichever
// owns it: stations whose result-affecting settings differ make results that depend on the
// owner. Each station declares its settings in its heartbeat row (storage::StationSettings);
// the daemons warn about a live station that differs, and `magcal status` marks it.
//
// Canonical text: one "section.key=value" line per setting, sorted by key, values as the daemon
// formats them (DaemonConfig::result_settings()); the hash is FNV-1a 64 of the text, 16 hex
// digits. Two stations have the same settings exactly when their texts are equal.
#pragma once

#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "storage/lease_store.hpp"

namespace magcal {

// "section.key" -> value.
using SettingsMap = std::map<std::string, std::string>;

// The canonical text and its hash. A value's line breaks become spaces (one line per key).
storage::StationSettings station_settings(const SettingsMap& values);
// The text back as a map (lines without '=' are skipped).
SettingsMap parse_station_settings(std::string_view text);

// One key set differently; nullopt: the key is not declared there (another magcal version).
struct SettingDifference {
  std::string key;
  std::optional<std::string> here;
  std::optional<std::string> there;
};
// The keys whose values differ, sorted by key.
std::vector<SettingDifference> settings_differences(const SettingsMap& here,
                                                    const SettingsMap& there);
// "refit.every_hours 6 here, 0 there; ukf.sigma_nT 5 here, (none) there".
std::string describe_differences(const std::vector<SettingDifference>& differences);

}  // namespace magcal
