// UTC time scales: calendar <-> utime, decimal year, Julian date, ISO 8601.
// References: published epoch values (J2000.0, 1900-01-01) and ERFA's eraCal2jd (IAU SOFA).
#include "pipeline/time_utc.hpp"

#include <cmath>
#include <random>

#include <erfa.h>
#include <catch2/catch.hpp>

using namespace magcal;

namespace {
constexpr int64_t kUs = kMicrosPerSecond;
constexpr double kJdTolerance_days = 1e-9;  // ~86 us: double precision of a JD ~ 2.45e6
constexpr double kYearTolerance = 1e-12;
}  // namespace

TEST_CASE("calendar <-> utime at published epochs", "[time]") {
  // Unix epoch, J2000.0 (2000-01-01T12:00:00 = 946 728 000 s), 1900-01-01 (-2 208 988 800 s).
  CHECK(utime_from_calendar({1970, 1, 1, 0, 0, 0.0}) == 0);
  CHECK(utime_from_calendar({2000, 1, 1, 12, 0, 0.0}) == 946728000LL * kUs);
  CHECK(utime_from_calendar({1900, 1, 1, 0, 0, 0.0}) == -2208988800LL * kUs);
  CHECK(utime_from_calendar({2024, 2, 29, 0, 0, 0.0}) == 1709164800LL * kUs);
  CHECK(utime_from_calendar({1969, 12, 31, 23, 59, 59.5}) == -500000);

  const CalendarTime c = calendar_from_utime(-500000);
  CHECK(c.year == 1969);
  CHECK(c.month == 12);
  CHECK(c.day == 31);
  CHECK(c.hour == 23);
  CHECK(c.minute == 59);
  CHECK(c.second == 59.5);
}

TEST_CASE("calendar round trip and Julian date against ERFA", "[time]") {
  std::mt19937_64 rng(20240601);
  std::uniform_int_distribution<int64_t> dist(-2208988800LL * kUs,
                                              4102444800LL * kUs);  // 1900-2100
  for (int i = 0; i < 20000; ++i) {
    const int64_t t = dist(rng);
    const CalendarTime c = calendar_from_utime(t);
    REQUIRE(utime_from_calendar(c) == t);

    double djm0 = 0.0, djm = 0.0;
    REQUIRE(eraCal2jd(c.year, c.month, c.day, &djm0, &djm) == 0);
    const double day_fraction = (c.hour * 3600.0 + c.minute * 60.0 + c.second) / 86400.0;
    const double jd_erfa = djm0 + djm + day_fraction;
    REQUIRE(std::abs(julian_date_from_utime(t) - jd_erfa) < kJdTolerance_days);
  }
  CHECK(julian_date_from_utime(946728000LL * kUs) == kJulianDateJ2000);
}

TEST_CASE("decimal year uses the length of that calendar year", "[time]") {
  // 1 July 2024 00:00: 182 days of a 366-day year; 2 July 2023 12:00: 182.5 of 365.
  CHECK(std::abs(decimal_year_from_utime(utime_from_calendar({2024, 7, 1, 0, 0, 0.0})) -
                 (2024.0 + 182.0 / 366.0)) < kYearTolerance);
  CHECK(std::abs(decimal_year_from_utime(utime_from_calendar({2023, 7, 2, 12, 0, 0.0})) -
                 (2023.0 + 182.5 / 365.0)) < kYearTolerance);
  CHECK(decimal_year_from_utime(utime_from_calendar({2025, 1, 1, 0, 0, 0.0})) == 2025.0);
  CHECK(decimal_year_from_utime(utime_from_calendar({1900, 1, 1, 0, 0, 0.0})) == 1900.0);
  // Just before New Year stays in the old year.
  const double end = decimal_year_from_utime(utime_from_calendar({2023, 12, 31, 23, 59, 59.0}));
  CHECK(end < 2024.0);
  CHECK(end > 2023.99999);
}

TEST_CASE("Julian centuries of TT", "[time]") {
  // J2000.0 is 2000-01-01T12:00:00 TT = 11:58:55.816 UTC (TT - UTC = 64.184 s then).
  const int64_t j2000_utc = 946728000LL * kUs - 64184000;
  CHECK(std::abs(julian_centuries_tt_from_utime(j2000_utc, 64.184)) < 1e-15);
  const int64_t later = j2000_utc + 36525LL * 86400 * kUs;
  CHECK(std::abs(julian_centuries_tt_from_utime(later, 64.184) - 1.0) < 1e-14);
}

TEST_CASE("ISO 8601 parsing accepts the documented forms", "[time]") {
  const int64_t base = utime_from_calendar({2025, 1, 2, 3, 4, 5.0});
  CHECK(parse_iso8601_utc("2025-01-02") == utime_from_calendar({2025, 1, 2, 0, 0, 0.0}));
  CHECK(parse_iso8601_utc("2025-01-02T03:04") == base - 5 * kUs);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05") == base);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05Z") == base);
  CHECK(parse_iso8601_utc("2025-01-02 03:04:05") == base);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05+00:00") == base);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05.25Z") == base + 250000);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05.123456Z") == base + 123456);
  CHECK(parse_iso8601_utc("2025-01-02T03:04:05.1234565Z") == base + 123457);  // rounded
  // Offsets: local 05:04:05+02:00 is 03:04:05Z; 22:04:05-05:00 the day before is 03:04:05Z.
  CHECK(parse_iso8601_utc("2025-01-02T05:04:05+02:00") == base);
  CHECK(parse_iso8601_utc("2025-01-01T22:04:05-05:00") == base);
  CHECK(parse_iso8601_utc("2024-02-29T00:00:00Z").has_value());
}

TEST_CASE("ISO 8601 parsing refuses malformed text", "[time]") {
  for (const char* bad :
       {"", "2025", "2025-1-02", "2025-13-01", "2025-00-10", "2025-02-29", "2024-02-30",
        "2025-01-32", "2025-01-02T24:00", "2025-01-02T23:60", "2025-01-02T23:59:60",
        "2025-01-02T03", "2025-01-02T03:04:05.", "2025-01-02T03:04:05ZZ", "2025-01-02x",
        "2025-01-02T03:04:05+2", "2025-01-02T03:04:05+25:00", " 2025-01-02", "abcd-ef-gh"}) {
    INFO(bad);
    CHECK_FALSE(parse_iso8601_utc(bad).has_value());
  }
}

TEST_CASE("ISO 8601 formatting and round trip", "[time]") {
  const int64_t t = utime_from_calendar({2025, 1, 2, 3, 4, 5.0}) + 123456;
  CHECK(format_iso8601_utc(t) == "2025-01-02T03:04:05Z");
  CHECK(format_iso8601_utc(t, 3) == "2025-01-02T03:04:05.123Z");
  CHECK(format_iso8601_utc(t, 6) == "2025-01-02T03:04:05.123456Z");
  // Rounding carries into the next second / day / year.
  const int64_t nye = utime_from_calendar({2025, 1, 1, 0, 0, 0.0}) - 1;
  CHECK(format_iso8601_utc(nye, 3) == "2025-01-01T00:00:00.000Z");
  CHECK(format_iso8601_utc(nye, 6) == "2024-12-31T23:59:59.999999Z");
  CHECK(format_iso8601_utc(-500000, 1) == "1969-12-31T23:59:59.5Z");

  std::mt19937_64 rng(7);
  std::uniform_int_distribution<int64_t> dist(-2208988800LL * kUs, 4102444800LL * kUs);
  for (int i = 0; i < 2000; ++i) {
    const int64_t u = dist(rng);
    REQUIRE(parse_iso8601_utc(format_iso8601_utc(u, 6)) == u);
  }
  CHECK(utime_from_seconds(1234.5678904) == 1234567890);
  CHECK(utime_from_seconds(-0.0000014) == -1);
  CHECK(seconds_from_utime(utime_from_seconds(-12.25)) == -12.25);
}
