// The PostgreSQL FilterStateStore (storage/filter_state_store.hpp) on one PgDatabase, made by
// PgDatabase::make_filter_state_store(). save_all() upserts many states per statement.
#pragma once

#include <span>
#include <string>
#include <vector>

#include "storage/filter_state_store.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

class PgFilterStateStore final : public FilterStateStore {
 public:
  explicit PgFilterStateStore(PgDatabase& db) : db_(db) {}

  void save(const FilterState& state) override;
  // Statements of up to 2^kMaxLog2RowsPerUpsert states, in key order.
  void save_all(std::span<const FilterState> states) override;
  std::optional<FilterState> load(std::string_view sat_id, std::string_view method) override;
  std::vector<FilterState> load_all() override;
  static constexpr size_t kMaxLog2RowsPerUpsert = 6;

 private:
  PgDatabase& db_;
  PgParams params_;  // save_all's, reused
};

}  // namespace magcal::storage
