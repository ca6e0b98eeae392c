// The LeaseStore (storage/lease_store.hpp) of both backends, written once on their SqlSession
// (storage/sql_statement.hpp): statements prepared once, rows read by LeaseRow. PostgreSQL's
// adds a fence of many leases in one statement (storage/postgres/pg_lease_store.hpp). Made by
// Connection::make_lease_store(); tests and tools that hold a database may construct it.
#pragma once

#include <memory>

#include "storage/lease_store.hpp"
#include "storage/sql_statement.hpp"

namespace magcal::storage {

class SqlLeaseStore : public LeaseStore {
 public:
  explicit SqlLeaseStore(SqlSession& db);  // prepares its statements; throws StorageError

  std::optional<Lease> try_acquire(std::string_view sat_id, std::string_view owner,
                                   int64_t now_utime, int64_t ttl_utime) override;
  std::optional<Lease> reclaim(std::string_view sat_id, std::string_view owner, int64_t epoch,
                               int64_t now_utime, int64_t ttl_utime) override;
  bool renew(std::string_view sat_id, std::string_view owner, int64_t epoch, int64_t now_utime,
             int64_t ttl_utime) override;
  bool release(std::string_view sat_id, std::string_view owner, int64_t epoch,
               int64_t now_utime) override;
  bool holds(std::string_view sat_id, std::string_view owner, int64_t epoch) override;
  std::optional<Lease> get(std::string_view sat_id) override;
  std::vector<Lease> list() override;
  void ensure(std::string_view sat_id) override;
  std::vector<Lease> renew_all(std::string_view owner, int64_t now_utime,
                               int64_t ttl_utime) override;
  std::optional<StationBeat> heartbeat(std::string_view station, std::string_view instance,
                                       const StationSettings& settings, int64_t now_utime,
                                       int64_t ttl_utime) override;
  void leave(std::string_view station, int64_t now_utime) override;
  std::vector<std::string> live_stations(int64_t now_utime) override;
  std::vector<StationRow> stations() override;

 private:
  std::unique_ptr<SqlStatement> acquire_, renew_, reclaim_, release_, holds_, get_, list_, ensure_,
      renew_all_, heartbeat_, beat_, leave_, live_, stations_;
};

}  // namespace magcal::storage
