// UTC time scales used across magcal.
//
// utime = microseconds since 1970-01-01T00:00:00Z. Leap seconds are ignored in all arithmetic
// (POSIX time): a UTC day is always 86 400 s. This is what the telemetry carries and what the
// IGRF reference software does with dates; the ~1e-3 arcsec it costs in Earth rotation is far
// below every accuracy this product needs. UT1 is taken as UTC + dut1_s (default 0).
#pragma once

#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <string_view>

namespace magcal {

constexpr int64_t kMicrosPerSecond = 1'000'000;
constexpr double kSecondsPerDay = 86400.0;
constexpr double kJulianDateUnixEpoch = 2440587.5;  // JD of 1970-01-01T00:00:00Z
constexpr double kJulianDateJ2000 = 2451545.0;      // JD of 2000-01-01T12:00:00 (TT≈UTC here)

struct CalendarTime {
  int year = 1970;
  int month = 1;  // 1..12
  int day = 1;    // 1..31
  int hour = 0;
  int minute = 0;
  double second = 0.0;
};

int64_t utime_from_calendar(const CalendarTime& c);
CalendarTime calendar_from_utime(int64_t utime);

// Decimal year = year + (elapsed time in that calendar year) / (length of that year, 365 or
// 366 days), as the IGRF reference software uses it.
double decimal_year_from_utime(int64_t utime);

// Julian date (UTC scale) of a utime.
double julian_date_from_utime(int64_t utime);
// Julian centuries of TT since J2000. TT = UTC + tt_minus_utc_s (69.184 s in 2017-2026;
// a constant is accurate enough for precession-nutation at the arcsec level).
double julian_centuries_tt_from_utime(int64_t utime, double tt_minus_utc_s = 69.184);

// ISO 8601 in UTC: accepts "YYYY-MM-DD", "YYYY-MM-DDTHH:MM[:SS[.ffffff]]" with optional "Z" or
// "+00:00", and a space instead of "T". Other offsets (+hh:mm) are applied. nullopt if malformed.
std::optional<int64_t> parse_iso8601_utc(std::string_view text);
// "YYYY-MM-DDTHH:MM:SS.ffffffZ"; fractional digits (0..6) as asked, rounded to that precision.
std::string format_iso8601_utc(int64_t utime, int fractional_digits = 0);

// The wall clock now, as a utime (system_clock). The one clock read of the code base: pipeline
// functions never call it (they take times as arguments); the service and storage layers do.
int64_t now_utime();

// Time tags magcal accepts from telemetry: 1990-01-01T00:00:00Z <= utime < 2100-01-01T00:00:00Z.
// Anything outside is a corrupt tag (and would overflow the arithmetic below near the int64
// limits). Differences of plausible utimes fit in int64 with 58 bits to spare.
constexpr int64_t kMinPlausibleUtime = 631'152'000'000'000;    // 1990-01-01T00:00:00Z
constexpr int64_t kMaxPlausibleUtime = 4'102'444'800'000'000;  // 2100-01-01T00:00:00Z
constexpr bool is_plausible_utime(int64_t utime) {
  return utime >= kMinPlausibleUtime && utime < kMaxPlausibleUtime;
}

// a - b and a + b clamped to [INT64_MIN, INT64_MAX] instead of overflowing (undefined
// behaviour): for differences of untrusted times and sequence numbers, e.g. utime - last_utime
// or newest_utime - window_utime.
constexpr int64_t saturating_sub(int64_t a, int64_t b) {
  int64_t r = 0;
  if (__builtin_sub_overflow(a, b, &r)) {
    return b < 0 ? std::numeric_limits<int64_t>::max() : std::numeric_limits<int64_t>::min();
  }
  return r;
}
constexpr int64_t saturating_add(int64_t a, int64_t b) {
  int64_t r = 0;
  if (__builtin_add_overflow(a, b, &r)) {
    return b > 0 ? std::numeric_limits<int64_t>::max() : std::numeric_limits<int64_t>::min();
  }
  return r;
}

inline double seconds_from_utime(int64_t utime) {
  return static_cast<double>(utime) / kMicrosPerSecond;
}
int64_t utime_from_seconds(double t_s);  // rounds to the nearest microsecond

}  // namespace magcal
