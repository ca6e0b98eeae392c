// The FilterStateStore (storage/filter_state_store.hpp) of both backends, written once on their
// SqlSession (storage/sql_statement.hpp): states written and read by FilterStateRow. PostgreSQL's
// upserts many states per statement (storage/postgres/pg_filter_state_store.hpp). Made by
// Connection::make_filter_state_store(); tests and tools that hold a database may construct it.
#pragma once

#include <memory>

#include "storage/filter_state_store.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlFilterStateStore : public FilterStateStore {
 public:
  explicit SqlFilterStateStore(SqlSession& db);  // prepares its statements; throws StorageError

  void save(const FilterState& state) override;
  std::optional<FilterState> load(std::string_view sat_id, std::string_view method) override;
  std::vector<FilterState> load_all() override;

 private:
  std::unique_ptr<SqlStatement> upsert_, load_, load_all_;
};

}  // namespace magcal::storage
