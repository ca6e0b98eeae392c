// Refit schedule: daily time plus every N hours, wall or data clock.
#include <catch2/catch.hpp>

#include "pipeline/time_utc.hpp"
#include "service/refit_scheduler.hpp"

using namespace magcal;

namespace {
int64_t t(const char* iso) {
  return *parse_iso8601_utc(iso);
}
}  // namespace

TEST_CASE("daily time parsing", "[refit_scheduler]") {
  CHECK(parse_daily_time_utc("02:00") == 120);
  CHECK(parse_daily_time_utc("00:00") == 0);
  CHECK(parse_daily_time_utc("23:59") == 23 * 60 + 59);
  CHECK_FALSE(parse_daily_time_utc("24:00"));
  CHECK_FALSE(parse_daily_time_utc("2:00"));
  CHECK_FALSE(parse_daily_time_utc("02:60"));
  CHECK_FALSE(parse_daily_time_utc("0200"));
  CHECK_FALSE(parse_daily_time_utc(""));
}

TEST_CASE("next scheduled time: daily only", "[refit_scheduler]") {
  const RefitSchedule s{120, 0.0};
  CHECK(next_scheduled_utime(s, t("2020-01-01T00:00:00Z")) == t("2020-01-01T02:00:00Z"));
  // Strictly after: at 02:00 the next one is tomorrow.
  CHECK(next_scheduled_utime(s, t("2020-01-01T02:00:00Z")) == t("2020-01-02T02:00:00Z"));
  CHECK(next_scheduled_utime(s, t("2019-12-31T23:00:00Z")) == t("2020-01-01T02:00:00Z"));
  // Before 1970 (negative utime) the floor division still works.
  CHECK(next_scheduled_utime(s, t("1969-12-31T03:00:00Z")) == t("1970-01-01T02:00:00Z"));
}

TEST_CASE("next scheduled time: daily plus every N hours", "[refit_scheduler]") {
  const RefitSchedule six{120, 6.0};
  CHECK(next_scheduled_utime(six, t("2020-01-01T00:00:00Z")) == t("2020-01-01T02:00:00Z"));
  CHECK(next_scheduled_utime(six, t("2020-01-01T02:00:00Z")) == t("2020-01-01T08:00:00Z"));
  CHECK(next_scheduled_utime(six, t("2020-01-01T20:00:00Z")) == t("2020-01-02T02:00:00Z"));
  // A period that does not divide the day restarts at the daily time.
  const RefitSchedule five{120, 5.0};
  CHECK(next_scheduled_utime(five, t("2020-01-01T22:00:00Z")) == t("2020-01-02T02:00:00Z"));
  CHECK(next_scheduled_utime(five, t("2020-01-01T21:59:00Z")) == t("2020-01-01T22:00:00Z"));
}

TEST_CASE("the scheduler reports each crossed time once", "[refit_scheduler]") {
  RefitScheduler s(RefitSchedule{120, 6.0});
  CHECK_FALSE(s.next_due());
  // The first clock value only sets the clock (nothing before it is due).
  CHECK(s.advance(t("2020-01-01T00:00:00Z")).empty());
  REQUIRE(s.next_due());
  CHECK(*s.next_due() == t("2020-01-01T02:00:00Z"));
  CHECK(s.advance(t("2020-01-01T01:59:59Z")).empty());
  const auto a = s.advance(t("2020-01-01T02:00:00Z"));
  REQUIRE(a.size() == 1);
  CHECK(a[0] == t("2020-01-01T02:00:00Z"));
  CHECK(s.advance(t("2020-01-01T02:00:00Z")).empty());  // not twice
  CHECK(s.advance(t("2020-01-01T01:00:00Z")).empty());  // backwards: ignored
  // A jump over several slots reports all of them, ascending (a replay after a gap).
  const auto b = s.advance(t("2020-01-02T03:00:00Z"));
  REQUIRE(b.size() == 4);
  CHECK(b[0] == t("2020-01-01T08:00:00Z"));
  CHECK(b[3] == t("2020-01-02T02:00:00Z"));
}
