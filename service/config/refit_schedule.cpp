#include "service/config/refit_schedule.hpp"

#include <cmath>

namespace magcal {
namespace {

// Calls visit(N_k) for k = 0, 1, ... while it returns true (and the terms stay far inside int64).
template <typename Visit>
void walk_early_levels(const EarlyRefitPlan& plan, Visit visit) {
  if (plan.min_samples <= 0) return;
  double level = plan.min_samples;
  int64_t n = plan.min_samples;
  while (visit(n) && plan.growth > 1.0) {
    level *= plan.growth;
    if (level > 1e18) return;
    n = static_cast<int64_t>(std::ceil(level - 1e-6));  // 1000 * 2 * 2 stays 4000
  }
}

}  // namespace

int64_t EarlyRefitPlan::next_after(int64_t covered_samples) const {
  int64_t next = 0;
  walk_early_levels(*this, [&](int64_t n) {
    if (n > covered_samples) next = n;
    return next == 0;
  });
  return next;
}

int64_t EarlyRefitPlan::latest_within(int64_t stored_samples) const {
  int64_t latest = 0;
  walk_early_levels(*this, [&](int64_t n) {
    if (n > stored_samples) return false;
    latest = n;
    return true;
  });
  return latest;
}

}  // namespace magcal
