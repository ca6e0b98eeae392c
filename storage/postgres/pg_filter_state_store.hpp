// The PostgreSQL FilterStateStore: the statements of both backends
// (storage/sql_filter_state_store.hpp), and save_all() upserting many states per statement (a
// worker round's states in a round trip or few). Made by PgDatabase::make_filter_state_store().
#pragma once

#include <span>

#include "storage/postgres/pg_database.hpp"
#include "storage/sql_filter_state_store.hpp"

namespace magcal::storage {

class PgFilterStateStore final : public SqlFilterStateStore {
 public:
  explicit PgFilterStateStore(PgDatabase& db) : SqlFilterStateStore(db), db_(db) {}

  // Statements of up to 2^kMaxLog2RowsPerUpsert states, in key order.
  void save_all(std::span<const FilterState> states) override;
  static constexpr size_t kMaxLog2RowsPerUpsert = 6;

 private:
  PgDatabase& db_;
  PgParams params_;  // reused
};

}  // namespace magcal::storage
