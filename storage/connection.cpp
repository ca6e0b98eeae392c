#include "storage/connection.hpp"

#include "storage/database.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

std::unique_ptr<Connection> open_database(const std::string& db, const OpenOptions& options) {
  if (is_postgres_uri(db)) return std::make_unique<PgDatabase>(db, options);
  return std::make_unique<Database>(db, options);
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
