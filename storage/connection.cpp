#include "storage/connection.hpp"

#include "storage/database.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

std::unique_ptr<Connection> open_database(const std::string& db, const OpenOptions& options) {
  if (is_postgres_uri(db)) return std::make_unique<PgDatabase>(db, options);
  return std::make_unique<Database>(db, options);
}

std::string database_name(const std::string& db) {
  if (!is_postgres_uri(db)) return db;
  std::string uri = db;
  const std::size_t authority = uri.find("://") + 3;
  const std::size_t authority_end = uri.find_first_of("/?", authority);
  const std::size_t at = uri.rfind('@', authority_end);
  if (at != std::string::npos && at >= authority) {
    const std::size_t colon = uri.find(':', authority);
    if (colon < at) uri.replace(colon + 1, at - colon - 1, "***");
  }
  for (std::size_t key = uri.find("password=", authority); key != std::string::npos;
       key = uri.find("password=", key + 1)) {
    if (uri[key - 1] != '?' && uri[key - 1] != '&') continue;
    const std::size_t value = key + 9;
    uri.replace(value, uri.find('&', value) - value, "***");
  }
  return uri;
}

int migration_target(const OpenOptions& options, int latest) {
  const int target = options.migrate_to < 0 ? latest : options.migrate_to;
  if (target > latest) {
    throw StorageError(
        StorageError::Kind::kInvalidArgument,
        "migrate_to " + std::to_string(target) + " > known schema " + std::to_string(latest));
  }
  return target;
}

}  // namespace magcal::storage
