// Refit schedule: daily time plus every N hours, wall or data clock.
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>

#include "pipeline/time_utc.hpp"
#include "service/refit/refit_scheduler.hpp"

using namespace magcal;

namespace {
int64_t t(const char* iso) {
  return *parse_iso8601_utc(iso);
}
}  // namespace

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
  // A jump over several slots within a day reports all of them, ascending.
  const auto b = s.advance(t("2020-01-02T01:59:59Z"));
  REQUIRE(b.size() == 3);
  CHECK(b[0] == t("2020-01-01T08:00:00Z"));
  CHECK(b[2] == t("2020-01-01T20:00:00Z"));
  CHECK(s.skipped() == 0);
}

namespace {
// Due times in (from, to], one by one (the reference for the scheduler's arithmetic count).
int64_t brute_force_count(const RefitSchedule& schedule, int64_t from, int64_t to) {
  int64_t n = 0;
  for (int64_t u = next_scheduled_utime(schedule, from); u <= to;
       u = next_scheduled_utime(schedule, u)) {
    ++n;
  }
  return n;
}
}  // namespace

TEST_CASE("a clock jump of more than a day runs only the latest refit", "[refit_scheduler]") {
  for (const RefitSchedule schedule : {RefitSchedule{120, 6.0}, RefitSchedule{120, 5.0},
                                       RefitSchedule{0, 0.0}, RefitSchedule{1439, 0.25}}) {
    DYNAMIC_SECTION("daily minute " << schedule.daily_minute_utc << ", every "
                                    << schedule.every_hours << " h") {
      RefitScheduler s(schedule);
      const int64_t from = t("2020-01-02T01:59:59Z");
      const int64_t to = t("2020-01-05T03:00:00Z");
      s.advance(from);
      const auto due = s.advance(to);
      REQUIRE(due.size() == 1);
      // The latest due time: the next one after it is past the clock.
      CHECK(due[0] <= to);
      CHECK(next_scheduled_utime(schedule, due[0]) > to);
      CHECK(s.skipped() == brute_force_count(schedule, from, to) - 1);
    }
  }
  SECTION("a first clock value at utime 0 (a corrupt tag) queues one refit, not thousands") {
    const RefitSchedule schedule{120, 6.0};
    RefitScheduler s(schedule);
    CHECK(s.advance(0).empty());
    const auto due = s.advance(t("2024-01-01T00:00:00Z"));
    REQUIRE(due.size() == 1);
    CHECK(due[0] == t("2023-12-31T20:00:00Z"));
    // The clock is clamped to the plausible range (1990-2100).
    CHECK(s.skipped() ==
          brute_force_count(schedule, t("1990-01-01T00:00:00Z"), t("2024-01-01T00:00:00Z")) - 1);
    CHECK(s.advance(std::numeric_limits<int64_t>::max()).size() == 1);
    CHECK(s.advance(std::numeric_limits<int64_t>::min()).empty());
  }
}

TEST_CASE("early refits: min_samples, then each time the stored samples grow by the factor",
          "[refit_scheduler]") {
  const EarlyRefitPlan doubling{1000, 2.0};
  CHECK(doubling.next_after(0) == 1000);
  CHECK(doubling.next_after(999) == 1000);
  CHECK(doubling.next_after(1000) == 2000);
  CHECK(doubling.next_after(1500) == 2000);  // after a scheduled refit of 1 500 samples
  CHECK(doubling.next_after(2000) == 4000);
  CHECK(doubling.latest_within(999) == 0);
  CHECK(doubling.latest_within(1000) == 1000);
  CHECK(doubling.latest_within(3999) == 2000);
  CHECK(doubling.latest_within(9000) == 8000);  // several due at once: only the latest
  // Both walk the same sequence: every count next_after names is one latest_within finds.
  const EarlyRefitPlan root2{1000, std::sqrt(2.0)};
  for (int64_t n = root2.next_after(0); n < 100000; n = root2.next_after(n)) {
    INFO(n);
    CHECK(root2.latest_within(n) == n);
    CHECK(root2.latest_within(n - 1) < n);
    CHECK(root2.next_after(n) > n);
  }
  const EarlyRefitPlan first_only{1000, 0.0};
  CHECK(first_only.next_after(0) == 1000);
  CHECK(first_only.next_after(1000) == 0);
  CHECK(first_only.latest_within(5000) == 1000);
}
