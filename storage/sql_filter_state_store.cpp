#include "storage/sql_filter_state_store.hpp"

#include "storage/filter_state_sql.hpp"

namespace magcal::storage {
namespace {

FilterState read_state(const SqlRow& row) {
  return row_codec::read<FilterStateRow>(row);
}

}  // namespace

SqlFilterStateStore::SqlFilterStateStore(SqlSession& db)
    : upsert_(db.prepare(filter_state_sql::upsert(1))),
      load_(db.prepare(row_codec::select_sql<FilterStateRow>("WHERE sat_id = ?1 AND method = ?2"))),
      load_all_(db.prepare(row_codec::select_sql<FilterStateRow>("ORDER BY sat_id, method"))) {}

void SqlFilterStateStore::save(const FilterState& s) {
  SqlRun run(*upsert_);
  row_codec::write<FilterStateRow>(s, *upsert_);
  run.changes();
}

std::optional<FilterState> SqlFilterStateStore::load(std::string_view sat_id,
                                                     std::string_view method) {
  return SqlRun(*load_, sat_id, method).first<FilterState>(read_state);
}

std::vector<FilterState> SqlFilterStateStore::load_all() {
  return SqlRun(*load_all_).all<FilterState>(read_state);
}

}  // namespace magcal::storage
