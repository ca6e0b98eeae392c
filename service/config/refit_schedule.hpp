// The [refit] schedules as values: when scheduled refits fall due (RefitSchedule, run by
// service/refit/refit_scheduler.hpp) and a new spacecraft's early refits (EarlyRefitPlan). They
// live with the configuration that makes them, so the configuration depends on nothing that
// runs refits.
#pragma once

#include <cstdint>

namespace magcal {

// The union of a daily time (daily_at_utc, minutes after 00:00 UTC) and, when every_hours > 0,
// the times daily_at + k * every_hours (design.md "The daemon's command line and config").
struct RefitSchedule {
  int daily_minute_utc = 120;  // 02:00
  double every_hours = 0.0;    // 0 = off
};

// Early refits of a new spacecraft: on the daily schedule alone its first refit, at
// [refit] min_samples, is followed by the next scheduled one up to a day later, and its UKF stays
// not_converged until then. While its stored data span less than window_hours it therefore gets a
// refit each time its stored samples reach N_k = ceil(min_samples * growth^k), k = 0, 1, ...
// (k = 0 is the "first" refit). An early refit is keyed by its sample count N_k, not by a clock:
// its window ends at the N_k-th stored sample, so the refit, its job row and its key
// (sat_id, trigger, that time) follow from the stored samples alone, the same after a restart
// and for any daemon that reads the same database. growth <= 1: only the first refit.
struct EarlyRefitPlan {
  int min_samples = 1000;
  double growth = 1.4142135623730951;

  // The smallest N_k above `covered_samples` (the sample count of the spacecraft's latest refit;
  // 0 = none yet); 0 when there is none (growth <= 1 after the first).
  int64_t next_after(int64_t covered_samples) const;
  // The largest N_k <= `stored_samples` (several due at once, after a restart or a recorder
  // dump: only the latest runs); 0 when stored_samples < min_samples.
  int64_t latest_within(int64_t stored_samples) const;
};

}  // namespace magcal
