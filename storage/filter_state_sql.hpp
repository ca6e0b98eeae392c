// The `filter_states` upsert, the same SQL on both backends for any number of rows. Internal to
// storage/.
#pragma once

#include <string>

#include "storage/filter_state_row.hpp"

namespace magcal::storage::filter_state_sql {

// The upsert of `rows` states (distinct keys: a statement cannot update one row twice), with
// ?N parameters: a state already stored under its key is replaced.
inline std::string upsert(size_t rows) {
  const int columns = row_codec::column_count<FilterStateRow>();
  std::string sql =
      "INSERT INTO filter_states (" + row_codec::column_list<FilterStateRow>() + ") VALUES ";
  int param = 1;
  for (size_t row = 0; row < rows; ++row) {
    sql += row > 0 ? ", (" : "(";
    for (int c = 0; c < columns; ++c) sql += (c > 0 ? ", ?" : "?") + std::to_string(param++);
    sql += ")";
  }
  return sql +
         " ON CONFLICT (sat_id, method) DO UPDATE SET x = excluded.x, P = excluded.P, "
         "last_utime = excluded.last_utime, n_samples = excluded.n_samples, "
         "counters = excluded.counters, updated_utime = excluded.updated_utime, "
         "anchor_calibration_id = excluded.anchor_calibration_id";
}

}  // namespace magcal::storage::filter_state_sql
