#include "service/refit/refit_scheduler.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "pipeline/time_utc.hpp"

namespace magcal {
namespace {

constexpr int64_t kMicrosPerMinute = 60'000'000;
constexpr int64_t kMicrosPerDay = 86'400'000'000;

// floor division for negative numerators too
int64_t floor_div(int64_t a, int64_t b) {
  return a / b - ((a % b != 0) && ((a < 0) != (b < 0)));
}

}  // namespace

int64_t next_scheduled_utime(const RefitSchedule& schedule, int64_t after_utime) {
  const int64_t anchor = schedule.daily_minute_utc * kMicrosPerMinute;  // on 1970-01-01
  // Daily sequence: anchor + k * day.
  int64_t best = anchor + (floor_div(after_utime - anchor, kMicrosPerDay) + 1) * kMicrosPerDay;
  if (schedule.every_hours > 0.0) {
    const auto period = static_cast<int64_t>(std::llround(schedule.every_hours * 3.6e9));
    if (period > 0) {
      // Periodic sequence anchored on the daily time of the day containing after_utime, so the
      // phase restarts every day at daily_at (identical to a global grid when 24 h is a
      // multiple of the period).
      const int64_t day_anchor =
          anchor + floor_div(after_utime - anchor, kMicrosPerDay) * kMicrosPerDay;
      const int64_t k = floor_div(after_utime - day_anchor, period) + 1;
      best = std::min(best, day_anchor + k * period);
    }
  }
  return best;
}

// Scheduled times <= t counted from an arbitrary origin (only differences are meaningful): the
// schedule repeats every day from the daily time, with ceil(day / period) times per day.
int64_t scheduled_count_through(const RefitSchedule& schedule, int64_t t) {
  const int64_t anchor = schedule.daily_minute_utc * kMicrosPerMinute;
  const int64_t day = floor_div(t - anchor, kMicrosPerDay);
  const int64_t into_day = t - anchor - day * kMicrosPerDay;  // [0, day)
  int64_t per_day = 1;
  int64_t today = 1;
  if (schedule.every_hours > 0.0) {
    const auto period = static_cast<int64_t>(std::llround(schedule.every_hours * 3.6e9));
    if (period > 0) {
      per_day = (kMicrosPerDay + period - 1) / period;
      today = into_day / period + 1;
    }
  }
  return day * per_day + today;
}

std::vector<int64_t> RefitScheduler::advance(int64_t clock_utime) {
  std::vector<int64_t> due;
  clock_utime = std::clamp(clock_utime, kMinPlausibleUtime, kMaxPlausibleUtime);
  if (!clock_utime_) {
    clock_utime_ = clock_utime;
    return due;
  }
  if (clock_utime <= *clock_utime_) return due;
  int64_t t = next_scheduled_utime(schedule_, *clock_utime_);
  if (clock_utime - *clock_utime_ > kMicrosPerDay) {
    // Only the latest due time (found within the last day before the clock).
    int64_t latest = t;
    for (int64_t u = next_scheduled_utime(schedule_, clock_utime - kMicrosPerDay); u <= clock_utime;
         u = next_scheduled_utime(schedule_, u)) {
      latest = u;
    }
    skipped_ += scheduled_count_through(schedule_, clock_utime) -
                scheduled_count_through(schedule_, *clock_utime_) - 1;
    due.push_back(latest);
    clock_utime_ = clock_utime;
    return due;
  }
  while (t <= clock_utime) {
    due.push_back(t);
    t = next_scheduled_utime(schedule_, t);
  }
  clock_utime_ = clock_utime;
  return due;
}

std::optional<int64_t> RefitScheduler::next_due() const {
  if (!clock_utime_) return std::nullopt;
  return next_scheduled_utime(schedule_, *clock_utime_);
}

}  // namespace magcal
