// The MetaStore (storage/meta_store.hpp) of both backends, written once on their SqlSession
// (storage/sql_statement.hpp). Made by Connection::make_meta_store().
#pragma once

#include <memory>

#include "storage/meta_store.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlMetaStore final : public MetaStore {
 public:
  explicit SqlMetaStore(SqlSession& db);
  void set(std::string_view key, std::string_view value) override;
  std::optional<std::string> get(std::string_view key) override;

 private:
  std::unique_ptr<SqlStatement> set_, get_;
};

}  // namespace magcal::storage
