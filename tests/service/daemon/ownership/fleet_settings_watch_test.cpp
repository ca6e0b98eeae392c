// FleetSettingsWatch: a live station whose result-affecting settings differ from this one's is
// warned about once (again when its settings change or it comes back), a match again is said,
// and the gauge counts the differing live stations; gone stations, this station's own row and
// rows without settings are not compared.
#include "service/daemon/ownership/fleet_settings_watch.hpp"

#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include <catch2/catch.hpp>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "service/io/station_settings.hpp"

using magcal::storage::StationRow;

namespace {

constexpr int64_t kNow = 1'767'225'600'000'000;

// Counts the occurrences of `what` in `text`.
int count(const std::string& text, const std::string& what) {
  int n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

}  // namespace

TEST_CASE("the settings watch warns once per differing live station and counts them") {
  std::ostringstream log;
  const auto previous = spdlog::default_logger();
  spdlog::set_default_logger(std::make_shared<spdlog::logger>(
      "capture", std::make_shared<spdlog::sinks::ostream_sink_st>(log)));
  const auto mine = magcal::station_settings({{"refit.every_hours", "0"}, {"ukf.alpha", "1"}});
  const auto six = magcal::station_settings({{"refit.every_hours", "6"}, {"ukf.alpha", "1"}});
  magcal::DaemonCounters counters;
  magcal::FleetSettingsWatch watch("gs-a", mine, counters);
  const auto row = [](std::string station, std::optional<magcal::storage::StationSettings> s,
                      bool live) {
    return StationRow{std::move(station), "i", kNow - 1, live ? kNow + 1 : kNow - 1, std::move(s)};
  };
  const std::string warning =
      "settings differ from station gs-b: refit.every_hours 0 here, 6 there; results of a "
      "spacecraft depend on which station owns it";

  // Own row (even with other settings), a gone one and one without settings: nothing.
  watch.check({row("gs-a", six, true), row("gs-c", six, false), row("gs-d", std::nullopt, true)},
              kNow);
  CHECK(log.str().empty());
  CHECK(counters.fleet_settings_mismatch.load() == 0);
  // gs-b differs: one warning, and not again at the next rounds.
  for (int round = 0; round < 3; ++round) watch.check({row("gs-b", six, true)}, kNow);
  CHECK(count(log.str(), warning) == 1);
  CHECK(counters.fleet_settings_mismatch.load() == 1);
  // gs-b restarted with this station's settings: said once, the gauge back to 0.
  watch.check({row("gs-b", mine, true)}, kNow);
  watch.check({row("gs-b", mine, true)}, kNow);
  CHECK(count(log.str(), "settings of station gs-b now match this station's") == 1);
  CHECK(counters.fleet_settings_mismatch.load() == 0);
  // Other settings again, then gone, then back with them: warned each time it is new.
  watch.check({row("gs-b", six, true)}, kNow);
  watch.check({row("gs-b", six, false)}, kNow);
  CHECK(counters.fleet_settings_mismatch.load() == 0);
  watch.check({row("gs-b", six, true), row("gs-e", six, true)}, kNow);
  CHECK(count(log.str(), warning) == 3);
  CHECK(count(log.str(), "settings differ from station gs-e") == 1);
  CHECK(counters.fleet_settings_mismatch.load() == 2);
  spdlog::set_default_logger(previous);
}
