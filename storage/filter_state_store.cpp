#include "storage/filter_state_store.hpp"

#include "pipeline/time_utc.hpp"

namespace magcal::storage {

int64_t save_utime(const FilterState& state) {
  return state.updated_utime != 0 ? state.updated_utime : now_utime();
}

void FilterStateStore::save_all(std::span<const FilterState> states) {
  for (const FilterState& s : states) save(s);
}

}  // namespace magcal::storage
