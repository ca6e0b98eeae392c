// The SQLite FilterStateStore (storage/filter_state_store.hpp) on one Database: statements prepared
// once in the constructor, reset and re-bound for every use. Made by Database::make_*(); tests and
// tools that hold a Database may construct it directly.
#pragma once

#include "storage/filter_state_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteFilterStateStore final : public FilterStateStore {
 public:
  explicit SqliteFilterStateStore(Database& db);

  void save(const FilterState& state) override;
  std::optional<FilterState> load(std::string_view sat_id, std::string_view method) override;
  std::vector<FilterState> load_all() override;

 private:
  FilterState read_row(Statement& st);
  Statement upsert_;
  Statement load_;
  Statement load_all_;
};

}  // namespace magcal::storage
