// When scheduled refits are due (design.md "The daemon's command line and config", [refit]).
//
// The schedule is the union of a daily time (daily_at_utc, minutes after 00:00 UTC) and, when
// every_hours > 0, the times daily_at + k * every_hours (k integer, anchored on the daily time so
// 02:00 with every_hours = 6 gives 02:00, 08:00, 14:00, 20:00). The clock is either the wall
// clock (one scheduler for every spacecraft) or the data clock (one scheduler per spacecraft,
// fed its newest sample time), so a replayed or backfilled day produces the refits that day
// would have had. Pure logic, no threads: the caller feeds it the clock.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "service/config/refit_schedule.hpp"

namespace magcal {

// The first scheduled time strictly after t (utime).
int64_t next_scheduled_utime(const RefitSchedule& schedule, int64_t after_utime);

class RefitScheduler {
 public:
  explicit RefitScheduler(RefitSchedule schedule) : schedule_(schedule) {}

  // Scheduled times in (previous clock, clock], ascending. The first call only sets the clock
  // (nothing before the daemon saw its first clock value is due). A clock that goes backwards
  // is ignored. A clock that jumps forward by more than a day (first data after a long outage,
  // a stepped wall clock) gives only the latest due time: catching up on stale windows would
  // refit the same data many times; the others are counted in skipped(). The clock is clamped
  // to the plausible utime range (pipeline/time_utc.hpp).
  std::vector<int64_t> advance(int64_t clock_utime);
  // Due times dropped by advance() so far.
  int64_t skipped() const { return skipped_; }

  // Next due time after the current clock (for logs); nullopt before the first advance().
  std::optional<int64_t> next_due() const;

 private:
  RefitSchedule schedule_;
  std::optional<int64_t> clock_utime_;
  int64_t skipped_ = 0;
};

}  // namespace magcal
