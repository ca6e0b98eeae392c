// The SQLite MetaStore (storage/meta_store.hpp) on one Database: statements prepared once in
// the constructor, reset and re-bound for every use. Made by Database::make_*(); tests and tools
// that hold a Database may construct it directly.
#pragma once

#include "storage/meta_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteMetaStore final : public MetaStore {
 public:
  explicit SqliteMetaStore(Database& db);
  void set(std::string_view key, std::string_view value) override;
  std::optional<std::string> get(std::string_view key) override;

 private:
  Statement set_;
  Statement get_;
};

}  // namespace magcal::storage
