#include "storage/sqlite/sqlite_lease_store.hpp"

#include "storage/lease_row.hpp"
#include "storage/sqlite/sqlite_row.hpp"

namespace magcal::storage {
namespace {

Lease read_lease(const Statement& st) {
  return row_codec::read<LeaseRow>(SqliteRow{st});
}

// The leases a statement returns.
std::vector<Lease> leases(Statement& st) {
  std::vector<Lease> out;
  while (st.step()) out.push_back(read_lease(st));
  return out;
}

std::optional<Lease> first_lease(Statement& st) {
  if (!st.step()) return std::nullopt;
  return read_lease(st);
}

}  // namespace

SqliteLeaseStore::SqliteLeaseStore(Database& db)
    : acquire_(db, lease_sql::kAcquire),
      renew_(db, lease_sql::kRenew),
      reclaim_(db, lease_sql::kReclaim),
      release_(db,
               "UPDATE leases SET expires_utime = min(expires_utime, ?4) WHERE sat_id = ?1 AND "
               "owner = ?2 AND epoch = ?3"),
      holds_(db, "SELECT 1 FROM leases WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3"),
      get_(db, row_codec::select_sql<LeaseRow>("WHERE sat_id = ?1")),
      list_(db, row_codec::select_sql<LeaseRow>("ORDER BY sat_id")),
      ensure_(db, lease_sql::kEnsure),
      renew_all_(db, lease_sql::kRenewAll),
      heartbeat_(db, lease_sql::kHeartbeat),
      beat_(db, lease_sql::kStationBeat),
      leave_(db, "UPDATE stations SET expires_utime = min(expires_utime, ?2) WHERE station = ?1"),
      live_(db, "SELECT station FROM stations WHERE expires_utime > ?1 ORDER BY station"),
      stations_(db, lease_sql::kStationList) {}

std::optional<Lease> SqliteLeaseStore::try_acquire(std::string_view sat_id, std::string_view owner,
                                                   int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  auto use = acquire_.use();
  acquire_.bind(1, sat_id).bind(2, owner).bind(3, now_utime).bind(4, ttl_utime);
  return first_lease(acquire_);  // nothing: another owner holds it
}

bool SqliteLeaseStore::renew(std::string_view sat_id, std::string_view owner, int64_t epoch,
                             int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  auto use = renew_.use();
  renew_.bind(1, sat_id).bind(2, owner).bind(3, epoch).bind(4, now_utime).bind(5, ttl_utime);
  return renew_.execute() == 1;
}

std::optional<Lease> SqliteLeaseStore::reclaim(std::string_view sat_id, std::string_view owner,
                                               int64_t epoch, int64_t now_utime,
                                               int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  auto use = reclaim_.use();
  reclaim_.bind(1, sat_id).bind(2, owner).bind(3, epoch).bind(4, now_utime).bind(5, ttl_utime);
  return first_lease(reclaim_);
}

bool SqliteLeaseStore::release(std::string_view sat_id, std::string_view owner, int64_t epoch,
                               int64_t now_utime) {
  auto use = release_.use();
  release_.bind(1, sat_id).bind(2, owner).bind(3, epoch).bind(4, now_utime);
  return release_.execute() == 1;
}

bool SqliteLeaseStore::holds(std::string_view sat_id, std::string_view owner, int64_t epoch) {
  auto use = holds_.use();
  holds_.bind(1, sat_id).bind(2, owner).bind(3, epoch);
  return holds_.step();
}

std::optional<Lease> SqliteLeaseStore::get(std::string_view sat_id) {
  auto use = get_.use();
  get_.bind(1, sat_id);
  return first_lease(get_);
}

std::vector<Lease> SqliteLeaseStore::list() {
  auto use = list_.use();
  return leases(list_);
}

void SqliteLeaseStore::ensure(std::string_view sat_id) {
  auto use = ensure_.use();
  ensure_.bind(1, sat_id).execute();
}

std::vector<Lease> SqliteLeaseStore::renew_all(std::string_view owner, int64_t now_utime,
                                               int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  auto use = renew_all_.use();
  renew_all_.bind(1, owner).bind(2, now_utime).bind(3, ttl_utime);
  return leases(renew_all_);
}

std::optional<StationBeat> SqliteLeaseStore::heartbeat(std::string_view station,
                                                       std::string_view instance,
                                                       const StationSettings& settings,
                                                       int64_t now_utime, int64_t ttl_utime) {
  check_request(station, ttl_utime);
  std::optional<StationBeat> before;
  {
    auto use = beat_.use();
    beat_.bind(1, station);
    if (beat_.step()) before = row_codec::read<StationBeatRow>(SqliteRow{beat_});
  }
  auto use = heartbeat_.use();
  SqliteBinder binder{heartbeat_};
  bind_heartbeat(binder, station, instance, settings, now_utime, ttl_utime);
  heartbeat_.execute();
  return before;
}

void SqliteLeaseStore::leave(std::string_view station, int64_t now_utime) {
  auto use = leave_.use();
  leave_.bind(1, station).bind(2, now_utime).execute();
}

std::vector<std::string> SqliteLeaseStore::live_stations(int64_t now_utime) {
  std::vector<std::string> out;
  auto use = live_.use();
  live_.bind(1, now_utime);
  while (live_.step()) out.push_back(live_.column_text(0));
  return out;
}

std::vector<StationRow> SqliteLeaseStore::stations() {
  std::vector<StationRow> out;
  auto use = stations_.use();
  while (stations_.step()) out.push_back(read_station(SqliteRow{stations_}));
  return out;
}

}  // namespace magcal::storage
