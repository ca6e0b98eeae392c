#include "service/io/station_settings.hpp"

#include <fmt/format.h>

#include "service/io/fnv1a.hpp"

namespace magcal {

storage::StationSettings station_settings(const SettingsMap& values) {
  storage::StationSettings out;
  for (const auto& [key, value] : values) {
    std::string line = key + "=" + value;
    for (char& c : line)
      if (c == '\n' || c == '\r') c = ' ';
    out.text += line + "\n";
  }
  out.hash = fmt::format("{:016x}", fnv1a_64(out.text));
  return out;
}

SettingsMap parse_station_settings(std::string_view text) {
  SettingsMap out;
  while (!text.empty()) {
    const size_t end = std::min(text.find('\n'), text.size());
    const std::string_view line = text.substr(0, end);
    text.remove_prefix(std::min(end + 1, text.size()));
    const size_t eq = line.find('=');
    if (eq != std::string_view::npos) out[std::string(line.substr(0, eq))] = line.substr(eq + 1);
  }
  return out;
}

std::vector<SettingDifference> settings_differences(const SettingsMap& here,
                                                    const SettingsMap& there) {
  std::vector<SettingDifference> out;
  auto h = here.begin();
  auto t = there.begin();
  // Both sorted by key: one merge.
  while (h != here.end() || t != there.end()) {
    if (t == there.end() || (h != here.end() && h->first < t->first)) {
      out.push_back({h->first, h->second, std::nullopt});
      ++h;
    } else if (h == here.end() || t->first < h->first) {
      out.push_back({t->first, std::nullopt, t->second});
      ++t;
    } else {
      if (h->second != t->second) out.push_back({h->first, h->second, t->second});
      ++h;
      ++t;
    }
  }
  return out;
}

std::string describe_differences(const std::vector<SettingDifference>& differences) {
  std::string out;
  for (const auto& d : differences) {
    if (!out.empty()) out += "; ";
    out += fmt::format("{} {} here, {} there", d.key, d.here.value_or("(none)"),
                       d.there.value_or("(none)"));
  }
  return out;
}

}  // namespace magcal
