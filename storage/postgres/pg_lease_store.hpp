// The PostgreSQL LeaseStore: the statements of both backends (storage/sql_lease_store.hpp) and a
// fence of many leases in one statement. Lease checks lock the rows they read (FOR SHARE), so a
// takeover waits for the transaction that relies on the lease. Made by
// PgDatabase::make_lease_store().
#pragma once

#include <span>
#include <string>
#include <vector>

#include "storage/postgres/pg_database.hpp"
#include "storage/sql_lease_store.hpp"

namespace magcal::storage {

class PgLeaseStore final : public SqlLeaseStore {
 public:
  explicit PgLeaseStore(PgDatabase& db) : SqlLeaseStore(db), db_(db) {}

  std::vector<std::string> not_held(std::string_view owner, std::span<const Held> leases) override;

 private:
  PgDatabase& db_;
};

}  // namespace magcal::storage
