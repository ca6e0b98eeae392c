#include "storage/sqlite/sqlite_filter_state_store.hpp"

#include "storage/filter_state_sql.hpp"
#include "storage/sqlite/sqlite_row.hpp"

namespace magcal::storage {
namespace {

std::string upsert_sql() {
  std::string sql =
      "INSERT INTO filter_states (" + row_codec::column_list<FilterStateRow>() + ") VALUES (";
  const int values = row_codec::column_count<FilterStateRow>();
  for (int i = 1; i <= values; ++i) sql += (i > 1 ? ", ?" : "?") + std::to_string(i);
  return sql + ")" + filter_state_sql::kReplace;
}

}  // namespace

SqliteFilterStateStore::SqliteFilterStateStore(Database& db)
    : upsert_(db, upsert_sql()),
      load_(db, filter_state_sql::load()),
      load_all_(db, filter_state_sql::load_all()) {}

void SqliteFilterStateStore::save(const FilterState& s) {
  auto use = upsert_.use();
  SqliteBinder binder{upsert_};
  row_codec::write<FilterStateRow>(s, binder);
  upsert_.execute();
}

FilterState SqliteFilterStateStore::read_row(Statement& st) {
  return row_codec::read<FilterStateRow>(SqliteRow{st});
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
