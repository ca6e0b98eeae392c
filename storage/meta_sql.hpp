// The `meta` statements, the same SQL on both backends (written with SQLite's ?N; PostgreSQL
// runs them through dollar_params(), storage/postgres/pg_query.hpp). Internal to storage/.
#pragma once

namespace magcal::storage::meta_sql {

inline constexpr const char* kSet =
    "INSERT INTO meta (key, value) VALUES (?1, ?2) "
    "ON CONFLICT (key) DO UPDATE SET value = excluded.value";
inline constexpr const char* kGet = "SELECT value FROM meta WHERE key = ?1";

}  // namespace magcal::storage::meta_sql
