#include "storage/postgres/pg_meta_store.hpp"

#include "storage/meta_sql.hpp"

namespace magcal::storage {

void PgMetaStore::set(std::string_view key, std::string_view value) {
  static const std::string sql = dollar_params(meta_sql::kSet);
  PgParams p;
  p.add(key).add(value);
  db_.execute_prepared(sql, p);
}

std::optional<std::string> PgMetaStore::get(std::string_view key) {
  static const std::string sql = dollar_params(meta_sql::kGet);
  PgParams p;
  p.add(key);
  const PgResult r = db_.execute_prepared(sql, p);
  if (r.rows() == 0) return std::nullopt;
  return r.get_text(0, 0);
}

}  // namespace magcal::storage
