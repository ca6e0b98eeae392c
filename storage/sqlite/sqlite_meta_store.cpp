#include "storage/sqlite/sqlite_meta_store.hpp"

#include "storage/meta_sql.hpp"

namespace magcal::storage {

SqliteMetaStore::SqliteMetaStore(Database& db)
    : set_(db, meta_sql::kSet), get_(db, meta_sql::kGet) {}

void SqliteMetaStore::set(std::string_view key, std::string_view value) {
  auto use = set_.use();
  set_.bind(1, key).bind(2, value);
  set_.execute();
}

std::optional<std::string> SqliteMetaStore::get(std::string_view key) {
  auto use = get_.use();
  get_.bind(1, key);
  if (!get_.step()) return std::nullopt;
  return get_.column_text(0);
}

}  // namespace magcal::storage
