// Table `meta`: a few named text values about the database itself (e.g. which daemon version
// wrote it last, when it started). Not a store for data: every kind of data has its own table.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "storage/database.hpp"
#include "storage/statement.hpp"

namespace magcal::storage {

class MetaStore {
 public:
  explicit MetaStore(Database& db);
  void set(std::string_view key, std::string_view value);
  std::optional<std::string> get(std::string_view key);

 private:
  Statement set_;
  Statement get_;
};

}  // namespace magcal::storage
