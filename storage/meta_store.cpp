#include "storage/meta_store.hpp"

#include "storage/sqlite_stores.hpp"

namespace magcal::storage {

SqliteMetaStore::SqliteMetaStore(Database& db)
    : set_(db, "INSERT OR REPLACE INTO meta (key, value) VALUES (?1, ?2)"),
      get_(db, "SELECT value FROM meta WHERE key = ?1") {}

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
