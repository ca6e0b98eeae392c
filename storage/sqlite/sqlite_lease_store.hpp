// The SQLite LeaseStore (storage/lease_store.hpp) on one Database: statements prepared once in
// the constructor, reset and re-bound for every use. Made by Database::make_*(); tests and tools
// that hold a Database may construct it directly.
#pragma once

#include "storage/lease_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {

class SqliteLeaseStore final : public LeaseStore {
 public:
  explicit SqliteLeaseStore(Database& db);

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
  Statement acquire_;
  Statement renew_;
  Statement reclaim_;
  Statement release_;
  Statement holds_;
  Statement get_;
  Statement list_;
  Statement ensure_;
  Statement renew_all_;
  Statement heartbeat_;
  Statement beat_;
  Statement leave_;
  Statement live_;
  Statement stations_;
};

}  // namespace magcal::storage
