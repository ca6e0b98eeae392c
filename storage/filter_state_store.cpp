#include "storage/filter_state_store.hpp"

#include <chrono>

#include "storage/blob_doubles.hpp"
#include "storage/sqlite_stores.hpp"
#include "storage/store_columns.hpp"

namespace magcal::storage {

int64_t save_utime(const FilterState& state) {
  if (state.updated_utime != 0) return state.updated_utime;
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

SqliteFilterStateStore::SqliteFilterStateStore(Database& db)
    : upsert_(db, std::string("INSERT OR REPLACE INTO filter_states (") + columns::kFilterState +
                      ") VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)"),
      load_(db, std::string("SELECT ") + columns::kFilterState +
                    " FROM filter_states WHERE sat_id = ?1 AND method = ?2"),
      load_all_(db, std::string("SELECT ") + columns::kFilterState +
                        " FROM filter_states ORDER BY sat_id, method") {}

void FilterStateStore::save_all(std::span<const FilterState> states) {
  for (const FilterState& s : states) save(s);
}

void SqliteFilterStateStore::save(const FilterState& s) {
  auto use = upsert_.use();
  upsert_.bind(1, s.sat_id).bind(2, s.method);
  upsert_.bind_blob(3, s.x.data(), sizeof(double) * s.x.size());
  upsert_.bind_blob(4, s.P.data(), sizeof(double) * s.P.size());
  upsert_.bind(5, s.last_utime).bind(6, s.n_samples);
  upsert_.bind_blob(7, s.counters.data(), s.counters.size());
  upsert_.bind(8, save_utime(s)).bind(9, s.anchor_calibration_id);
  upsert_.execute();
}

FilterState SqliteFilterStateStore::read_row(Statement& st) {
  FilterState s;
  s.sat_id = st.column_text(0);
  s.method = st.column_text(1);
  const auto x = st.column_blob(2);
  doubles_from_blob(x.data(), x.size(), s.x, "filter_states.x");
  const auto P = st.column_blob(3);
  doubles_from_blob(P.data(), P.size(), s.P, "filter_states.P");
  s.last_utime = st.column_int64(4);
  s.n_samples = st.column_int64(5);
  const auto counters = st.column_blob(6);
  s.counters.assign(counters.begin(), counters.end());
  s.updated_utime = st.column_int64(7);
  s.anchor_calibration_id =
      st.is_null(8) ? std::nullopt : std::optional<int64_t>(st.column_int64(8));
  return s;
}

std::optional<FilterState> SqliteFilterStateStore::load(std::string_view sat_id,
                                                        std::string_view method) {
  auto use = load_.use();
  load_.bind(1, sat_id).bind(2, method);
  if (!load_.step()) return std::nullopt;
  return read_row(load_);
}

std::vector<FilterState> SqliteFilterStateStore::load_all() {
  std::vector<FilterState> out;
  auto use = load_all_.use();
  while (load_all_.step()) out.push_back(read_row(load_all_));
  return out;
}

}  // namespace magcal::storage
