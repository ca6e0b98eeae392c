// One `filter_states` row, the same on both backends (storage/row_codec.hpp walks the list).
// Internal to storage/.
#pragma once

#include <type_traits>

#include "storage/filter_state_store.hpp"
#include "storage/row_codec.hpp"

namespace magcal::storage {

struct FilterStateRow {
  using Record = FilterState;
  static constexpr const char* kTable = "filter_states";
  template <typename State, typename Fields>
  static void fields(State& s, Fields& f) {
    f("sat_id", s.sat_id);
    f("method", s.method);
    f("x", s.x);
    f("P", s.P);
    f("last_utime", s.last_utime);
    f("n_samples", s.n_samples);
    f("counters", s.counters);
    // A state saved without a time is stamped with the time of the save.
    if constexpr (std::is_const_v<State>) {
      f("updated_utime", save_utime(s));
    } else {
      f("updated_utime", s.updated_utime);
    }
    f("anchor_calibration_id", s.anchor_calibration_id);
  }
};

}  // namespace magcal::storage
