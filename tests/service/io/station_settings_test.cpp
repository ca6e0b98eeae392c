// A station's result-affecting settings as canonical text (service/io/station_settings.hpp):
// sorted lines, a hash that follows the text, and the differing keys named both ways.
#include "service/io/station_settings.hpp"

#include <catch2/catch.hpp>

TEST_CASE("station settings: canonical text, hash, and the keys that differ") {
  const auto a = magcal::station_settings({{"b.x", "2"}, {"a.y", "line\nbreak"}});
  CHECK(a.text == "a.y=line break\nb.x=2\n");  // sorted by key, one line each
  CHECK(a.hash.size() == 16);
  CHECK(magcal::station_settings({{"a.y", "line break"}, {"b.x", "2"}}).hash == a.hash);
  CHECK(magcal::station_settings({{"a.y", "line break"}, {"b.x", "3"}}).hash != a.hash);
  CHECK(magcal::parse_station_settings(a.text) ==
        magcal::SettingsMap{{"a.y", "line break"}, {"b.x", "2"}});
  const auto d = magcal::settings_differences({{"a.k", "1"}, {"b.k", "x"}, {"c.k", "same"}},
                                              {{"b.k", "y"}, {"c.k", "same"}, {"d.k", "new"}});
  CHECK(magcal::describe_differences(d) ==
        "a.k 1 here, (none) there; b.k x here, y there; d.k (none) here, new there");
}
