// The PostgreSQL schema migrations, embedded in the binary like the SQLite ones
// (storage/migrations.hpp): storage/postgres/migrations/NNNN_name.sql are the one copy. Version N
// here is the same schema as SQLite's version N, in PostgreSQL's types, so both backends carry
// one schema version number.
#pragma once

#include <span>

#include "storage/migrations.hpp"

namespace magcal::storage {

// In version order 1, 2, ...; `version` is recorded in magcal_schema_version.
std::span<const Migration> pg_migrations();

}  // namespace magcal::storage
