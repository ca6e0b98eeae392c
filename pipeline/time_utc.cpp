// UTC time scales. Leap seconds are ignored everywhere (POSIX time, every day is 86 400 s);
// see time_utc.hpp for why that is acceptable.
#include "pipeline/time_utc.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>

namespace magcal {
namespace {

constexpr int64_t kMicrosPerDay = 86'400LL * kMicrosPerSecond;

// Floor division/modulo for possibly negative utimes (before 1970).
constexpr int64_t floor_div(int64_t a, int64_t b) {
  const int64_t q = a / b;
  return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
}

// Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's days_from_civil).
constexpr int64_t days_from_civil(int64_t y, int m, int d) {
  y -= m <= 2 ? 1 : 0;
  const int64_t era = (y >= 0 ? y : y - 399) / 400;
  const int64_t yoe = y - era * 400;                                   // [0, 399]
  const int64_t doy = (153 * (m + (m > 2 ? -3 : 9)) + 2) / 5 + d - 1;  // [0, 365]
  const int64_t doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;           // [0, 146096]
  return era * 146097 + doe - 719468;
}

struct Civil {
  int64_t year;
  int month;
  int day;
};
// Inverse of days_from_civil (H. Hinnant's civil_from_days).
constexpr Civil civil_from_days(int64_t z) {
  z += 719468;
  const int64_t era = (z >= 0 ? z : z - 146096) / 146097;
  const int64_t doe = z - era * 146097;
  const int64_t yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
  const int64_t doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
  const int64_t mp = (5 * doy + 2) / 153;
  const int d = static_cast<int>(doy - (153 * mp + 2) / 5 + 1);
  const int m = static_cast<int>(mp < 10 ? mp + 3 : mp - 9);
  return {yoe + era * 400 + (m <= 2 ? 1 : 0), m, d};
}

constexpr bool is_leap_year(int64_t y) {
  return (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
}

int days_in_month(int64_t y, int m) {
  static constexpr int kDays[12] = {31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  return (m == 2 && is_leap_year(y)) ? 29 : kDays[m - 1];
}

// Small cursor-based parser for the ISO 8601 subset documented in the header.
class Cursor {
 public:
  explicit Cursor(std::string_view s) : s_(s) {}
  bool done() const { return i_ == s_.size(); }
  char peek() const { return done() ? '\0' : s_[i_]; }
  bool eat(char c) {
    if (peek() != c) return false;
    ++i_;
    return true;
  }
  // Exactly `n` decimal digits.
  std::optional<int> digits(int n) {
    int v = 0;
    for (int k = 0; k < n; ++k) {
      const char c = peek();
      if (c < '0' || c > '9') return std::nullopt;
      v = v * 10 + (c - '0');
      ++i_;
    }
    return v;
  }
  // One or more digits as a fraction in microseconds (rounded); at most 9 digits.
  std::optional<int64_t> fraction_us() {
    int64_t value = 0;
    int count = 0;
    while (peek() >= '0' && peek() <= '9') {
      if (count == 9) return std::nullopt;
      value = value * 10 + (peek() - '0');
      ++count;
      ++i_;
    }
    if (count == 0) return std::nullopt;
    int64_t scale = 1;
    for (int k = count; k < 9; ++k) scale *= 10;
    const int64_t ns = value * scale;
    return (ns + 500) / 1000;
  }

 private:
  std::string_view s_;
  size_t i_ = 0;
};

}  // namespace

int64_t utime_from_calendar(const CalendarTime& c) {
  const int64_t days = days_from_civil(c.year, c.month, c.day);
  const int64_t whole_us = ((days * 24 + c.hour) * 60 + c.minute) * 60 * kMicrosPerSecond;
  return whole_us + static_cast<int64_t>(std::llround(c.second * kMicrosPerSecond));
}

CalendarTime calendar_from_utime(int64_t utime) {
  const int64_t days = floor_div(utime, kMicrosPerDay);
  int64_t us = utime - days * kMicrosPerDay;  // [0, kMicrosPerDay)
  const Civil civil = civil_from_days(days);
  CalendarTime c;
  c.year = static_cast<int>(civil.year);
  c.month = civil.month;
  c.day = civil.day;
  c.hour = static_cast<int>(us / (3600 * kMicrosPerSecond));
  us -= c.hour * 3600 * kMicrosPerSecond;
  c.minute = static_cast<int>(us / (60 * kMicrosPerSecond));
  us -= c.minute * 60 * kMicrosPerSecond;
  c.second = static_cast<double>(us) / kMicrosPerSecond;
  return c;
}

double decimal_year_from_utime(int64_t utime) {
  const int64_t days = floor_div(utime, kMicrosPerDay);
  const int64_t year = civil_from_days(days).year;
  const int64_t start = days_from_civil(year, 1, 1) * kMicrosPerDay;
  const double length_us = (is_leap_year(year) ? 366.0 : 365.0) * kMicrosPerDay;
  return static_cast<double>(year) + static_cast<double>(utime - start) / length_us;
}

double julian_date_from_utime(int64_t utime) {
  return kJulianDateUnixEpoch + static_cast<double>(utime) / kMicrosPerDay;
}

double julian_centuries_tt_from_utime(int64_t utime, double tt_minus_utc_s) {
  // Days since J2000 computed from the utime directly (not via a large JD) to keep precision.
  constexpr double kUnixEpochMinusJ2000_days = kJulianDateUnixEpoch - kJulianDateJ2000;
  const double days =
      kUnixEpochMinusJ2000_days +
      (static_cast<double>(utime) / kMicrosPerSecond + tt_minus_utc_s) / kSecondsPerDay;
  return days / 36525.0;
}

std::optional<int64_t> parse_iso8601_utc(std::string_view text) {
  Cursor cur(text);
  const auto year = cur.digits(4);
  if (!year || !cur.eat('-')) return std::nullopt;
  const auto month = cur.digits(2);
  if (!month || !cur.eat('-')) return std::nullopt;
  const auto day = cur.digits(2);
  if (!day || *month < 1 || *month > 12 || *day < 1 || *day > days_in_month(*year, *month))
    return std::nullopt;

  int hour = 0, minute = 0, second = 0;
  int64_t micros = 0;
  int64_t offset_min = 0;
  if (!cur.done()) {
    if (!cur.eat('T') && !cur.eat(' ')) return std::nullopt;
    const auto h = cur.digits(2);
    if (!h || !cur.eat(':')) return std::nullopt;
    const auto mi = cur.digits(2);
    if (!mi) return std::nullopt;
    hour = *h;
    minute = *mi;
    if (cur.eat(':')) {
      const auto s = cur.digits(2);
      if (!s) return std::nullopt;
      second = *s;
      if (cur.eat('.') || cur.eat(',')) {
        const auto f = cur.fraction_us();
        if (!f) return std::nullopt;
        micros = *f;
      }
    }
    // Leap seconds are ignored, so :60 is refused rather than silently shifted.
    if (hour > 23 || minute > 59 || second > 59) return std::nullopt;
    if (cur.eat('Z')) {
    } else if (cur.peek() == '+' || cur.peek() == '-') {
      const int sign = cur.peek() == '-' ? -1 : 1;
      cur.eat(cur.peek());
      const auto oh = cur.digits(2);
      if (!oh) return std::nullopt;
      cur.eat(':');
      const auto om = cur.digits(2);
      if (!om || *oh > 23 || *om > 59) return std::nullopt;
      offset_min = sign * (*oh * 60 + *om);
    }
  }
  if (!cur.done()) return std::nullopt;

  const int64_t days = days_from_civil(*year, *month, *day);
  const int64_t local_s = ((days * 24 + hour) * 60 + minute) * 60 + second;
  // Local time = UTC + offset, so UTC = local - offset.
  return (local_s - offset_min * 60) * kMicrosPerSecond + micros;
}

std::string format_iso8601_utc(int64_t utime, int fractional_digits) {
  if (fractional_digits < 0) fractional_digits = 0;
  if (fractional_digits > 6) fractional_digits = 6;
  int64_t unit = 1;
  for (int k = fractional_digits; k < 6; ++k) unit *= 10;
  // Round half up to the requested precision (floor-based so negative utimes round the same).
  const int64_t rounded = floor_div(utime + unit / 2, unit) * unit;

  const int64_t days = floor_div(rounded, kMicrosPerDay);
  int64_t us = rounded - days * kMicrosPerDay;
  const Civil civil = civil_from_days(days);
  const int64_t total_s = us / kMicrosPerSecond;
  us -= total_s * kMicrosPerSecond;
  char buf[64];
  int len = std::snprintf(
      buf, sizeof buf, "%04lld-%02d-%02dT%02lld:%02lld:%02lld", static_cast<long long>(civil.year),
      civil.month, civil.day, static_cast<long long>(total_s / 3600),
      static_cast<long long>(total_s / 60 % 60), static_cast<long long>(total_s % 60));
  if (fractional_digits > 0) {
    len += std::snprintf(buf + len, sizeof buf - len, ".%0*lld", fractional_digits,
                         static_cast<long long>(us / unit));
  }
  std::snprintf(buf + len, sizeof buf - len, "Z");
  return buf;
}

int64_t utime_from_seconds(double t_s) {
  return static_cast<int64_t>(std::llround(t_s * kMicrosPerSecond));
}

int64_t now_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace magcal
