// The schema migrations, embedded in the binary (the binary never needs the source tree).
// storage/migrations/NNNN_name.sql are the one copy: storage/embed_migrations.cmake turns them
// into a generated embedded_migrations.cpp at build time (numbered 0001, 0002, ... without gaps).
#pragma once

#include <span>

namespace magcal::storage {

struct Migration {
  int version;       // becomes PRAGMA user_version after it is applied
  const char* name;  // "0001_init"
  const char* sql;
};

// In version order 1, 2, ...
std::span<const Migration> migrations();

}  // namespace magcal::storage
