// The `filter_states` statements whose SQL the two dialects share, written with SQLite's ?N
// (PostgreSQL runs them through dollar_params(), storage/postgres/pg_query.hpp). Internal to
// storage/.
#pragma once

#include <string>

#include "storage/filter_state_row.hpp"

namespace magcal::storage::filter_state_sql {

// What an upsert does with a key already stored: the new state replaces the old.
inline constexpr const char* kReplace =
    " ON CONFLICT (sat_id, method) DO UPDATE SET x = excluded.x, P = excluded.P, "
    "last_utime = excluded.last_utime, n_samples = excluded.n_samples, "
    "counters = excluded.counters, updated_utime = excluded.updated_utime, "
    "anchor_calibration_id = excluded.anchor_calibration_id";
inline std::string load() {
  return row_codec::select_sql<FilterStateRow>("WHERE sat_id = ?1 AND method = ?2");
}
inline std::string load_all() {
  return row_codec::select_sql<FilterStateRow>("ORDER BY sat_id, method");
}

}  // namespace magcal::storage::filter_state_sql
