// The PostgreSQL MetaStore (storage/meta_store.hpp) on one PgDatabase, made by
// PgDatabase::make_meta_store().
#pragma once

#include "storage/meta_store.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

class PgMetaStore final : public MetaStore {
 public:
  explicit PgMetaStore(PgDatabase& db) : db_(db) {}
  void set(std::string_view key, std::string_view value) override;
  std::optional<std::string> get(std::string_view key) override;

 private:
  PgDatabase& db_;
};

}  // namespace magcal::storage
