// Table `meta`: a few named text values about the database itself (e.g. which daemon version
// wrote it last, when it started). Not a store for data: every kind of data has its own table.
// An interface: SqlMetaStore (storage/sql_meta_store.hpp, both backends), made by
// Connection::make_meta_store().
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "storage/connection.hpp"

namespace magcal::storage {

class MetaStore {
 public:
  virtual ~MetaStore() = default;
  // Insert or replace.
  virtual void set(std::string_view key, std::string_view value) = 0;
  virtual std::optional<std::string> get(std::string_view key) = 0;
};

}  // namespace magcal::storage
