#include "storage/sql_meta_store.hpp"

namespace magcal::storage {

SqlMetaStore::SqlMetaStore(SqlSession& db)
    : set_(db.prepare("INSERT INTO meta (key, value) VALUES (?1, ?2) "
                      "ON CONFLICT (key) DO UPDATE SET value = excluded.value")),
      get_(db.prepare("SELECT value FROM meta WHERE key = ?1")) {}

void SqlMetaStore::set(std::string_view key, std::string_view value) {
  SqlRun(*set_, key, value).changes();
}

std::optional<std::string> SqlMetaStore::get(std::string_view key) {
  return SqlRun(*get_, key).first<std::string>([](const SqlRow& row) { return row.text(0); });
}

}  // namespace magcal::storage
