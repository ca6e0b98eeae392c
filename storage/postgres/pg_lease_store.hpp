// The PostgreSQL LeaseStore (storage/lease_store.hpp) on one PgDatabase, made by
// PgDatabase::make_lease_store(). Lease checks lock the rows they read (FOR SHARE), so a takeover
// waits for the transaction that relies on the lease.
#pragma once

#include <span>
#include <string>
#include <vector>

#include "storage/lease_store.hpp"
#include "storage/postgres/pg_database.hpp"

namespace magcal::storage {

class PgLeaseStore final : public LeaseStore {
 public:
  explicit PgLeaseStore(PgDatabase& db) : db_(db) {}

  std::optional<Lease> try_acquire(std::string_view sat_id, std::string_view owner,
                                   int64_t now_utime, int64_t ttl_utime) override;
  std::optional<Lease> reclaim(std::string_view sat_id, std::string_view owner, int64_t epoch,
                               int64_t now_utime, int64_t ttl_utime) override;
  bool renew(std::string_view sat_id, std::string_view owner, int64_t epoch, int64_t now_utime,
             int64_t ttl_utime) override;
  bool release(std::string_view sat_id, std::string_view owner, int64_t epoch,
               int64_t now_utime) override;
  bool holds(std::string_view sat_id, std::string_view owner, int64_t epoch) override;
  std::vector<std::string> not_held(std::string_view owner, std::span<const Held> leases) override;
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
  PgDatabase& db_;
};

}  // namespace magcal::storage
