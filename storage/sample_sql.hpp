// The `samples` statements whose SQL the two dialects share, written with SQLite's ?N
// (PostgreSQL runs them through dollar_params(), storage/postgres/pg_query.hpp). Internal to
// storage/.
#pragma once

#include <string>
#include <string_view>

#include "storage/sample_row.hpp"

namespace magcal::storage::sample_sql {

// A sample window: t0 <= utime < t1, by the primary key.
inline std::string window() {
  return "SELECT " + sample_row::read_columns() +
         " FROM samples WHERE sat_id = ?1 AND utime >= ?2 AND utime < ?3 ORDER BY utime";
}
// The samples of a window per station that stored them, sorted by the station's bytes
// (`collate`: PostgreSQL's COLLATE "C", as SQLite's BINARY).
inline std::string count_by_station(std::string_view collate) {
  return "SELECT coalesce(station, '')" + std::string(collate) +
         " AS s, count(*) FROM samples WHERE sat_id = ?1 AND utime >= ?2 AND utime < ?3 "
         "GROUP BY s ORDER BY s";
}
// Only a repeated key is ignored (and counted); a NOT NULL violation is an error.
inline constexpr const char* kIgnoreDuplicate = "ON CONFLICT (sat_id, utime) DO NOTHING";
inline constexpr const char* kCountInWindow =
    "SELECT count(*) FROM samples WHERE sat_id = ?1 AND utime >= ?2 AND utime < ?3";
inline constexpr const char* kNewest = "SELECT max(utime) FROM samples WHERE sat_id = ?1";
inline constexpr const char* kOldest = "SELECT min(utime) FROM samples WHERE sat_id = ?1";
inline constexpr const char* kCount = "SELECT count(*) FROM samples WHERE sat_id = ?1";
inline constexpr const char* kUtimeAtRank =
    "SELECT utime FROM samples WHERE sat_id = ?1 ORDER BY utime LIMIT 1 OFFSET ?2";
// Skip-scan over the primary key: one index descent per spacecraft, not a full scan.
inline constexpr const char* kSpacecraft =
    "WITH RECURSIVE s(id) AS (SELECT min(sat_id) FROM samples UNION ALL "
    "SELECT (SELECT min(sat_id) FROM samples WHERE sat_id > s.id) FROM s "
    "WHERE s.id IS NOT NULL) SELECT id FROM s WHERE id IS NOT NULL";

}  // namespace magcal::storage::sample_sql
