#include "storage/lease_store.hpp"

#include "storage/sqlite_stores.hpp"
#include "storage/store_columns.hpp"

namespace magcal::storage {
namespace {

using columns::kLease;

Lease read_lease(const Statement& st) {
  return {st.column_text(0), st.column_text(1), st.column_int64(2), st.column_int64(3),
          st.column_int64(4)};
}

}  // namespace

void LeaseStore::check_request(std::string_view owner, int64_t ttl_utime) {
  if (owner.empty()) {
    throw StorageError(StorageError::Kind::kInvalidArgument, "a lease needs an owner");
  }
  if (ttl_utime <= 0) {
    throw StorageError(
        StorageError::Kind::kInvalidArgument,
        "a lease's time to live must be positive, not " + std::to_string(ttl_utime) + " us");
  }
}

std::optional<std::string> LeaseStore::owner_of(std::string_view sat_id, int64_t now_utime) {
  auto lease = get(sat_id);
  if (!lease || !lease->held_at(now_utime)) return std::nullopt;
  return std::move(lease->owner);
}

std::vector<std::string> LeaseStore::not_held(std::string_view owner,
                                              std::span<const Held> leases) {
  std::vector<std::string> out;
  for (const Held& l : leases) {
    if (!holds(l.sat_id, owner, l.epoch)) out.push_back(l.sat_id);
  }
  return out;
}

SqliteLeaseStore::SqliteLeaseStore(Database& db)
    : acquire_(db, columns::kLeaseAcquire),
      renew_(db,
             "UPDATE leases SET expires_utime = ?4 + ?5 WHERE sat_id = ?1 AND owner = ?2 AND "
             "epoch = ?3"),
      reclaim_(db, columns::kLeaseReclaim),
      release_(db,
               "UPDATE leases SET expires_utime = min(expires_utime, ?4) WHERE sat_id = ?1 AND "
               "owner = ?2 AND epoch = ?3"),
      holds_(db, "SELECT 1 FROM leases WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3"),
      get_(db, std::string("SELECT ") + kLease + " FROM leases WHERE sat_id = ?1"),
      list_(db, std::string("SELECT ") + kLease + " FROM leases ORDER BY sat_id"),
      ensure_(db, columns::kLeaseEnsure),
      renew_all_(db, columns::kLeaseRenewAll),
      heartbeat_(db, columns::kStationHeartbeat),
      beat_(db, columns::kStationBeat),
      leave_(db, "UPDATE stations SET expires_utime = min(expires_utime, ?2) WHERE station = ?1"),
      live_(db, "SELECT station FROM stations WHERE expires_utime > ?1 ORDER BY station"),
      stations_(db, columns::kStationList) {}

std::optional<Lease> SqliteLeaseStore::try_acquire(std::string_view sat_id, std::string_view owner,
                                                   int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  auto use = acquire_.use();
  acquire_.bind(1, sat_id).bind(2, owner).bind(3, now_utime).bind(4, ttl_utime);
  if (!acquire_.step()) return std::nullopt;  // another owner holds it
  return read_lease(acquire_);
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
  if (!reclaim_.step()) return std::nullopt;
  return read_lease(reclaim_);
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
  if (!get_.step()) return std::nullopt;
  return read_lease(get_);
}

std::vector<Lease> SqliteLeaseStore::list() {
  std::vector<Lease> out;
  auto use = list_.use();
  while (list_.step()) out.push_back(read_lease(list_));
  return out;
}

void SqliteLeaseStore::ensure(std::string_view sat_id) {
  auto use = ensure_.use();
  ensure_.bind(1, sat_id).execute();
}

std::vector<Lease> SqliteLeaseStore::renew_all(std::string_view owner, int64_t now_utime,
                                               int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  std::vector<Lease> out;
  auto use = renew_all_.use();
  renew_all_.bind(1, owner).bind(2, now_utime).bind(3, ttl_utime);
  while (renew_all_.step()) out.push_back(read_lease(renew_all_));
  return out;
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
    if (beat_.step()) {
      before = StationBeat{beat_.column_text(0), beat_.column_int64(1), beat_.column_int64(2)};
    }
  }
  auto use = heartbeat_.use();
  heartbeat_.bind(1, station).bind(2, now_utime).bind(3, ttl_utime).bind(4, instance);
  if (settings.text.empty()) {
    heartbeat_.bind_null(5).bind_null(6);
  } else {
    heartbeat_.bind(5, settings.text).bind(6, settings.hash);
  }
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
  while (stations_.step()) {
    StationRow& row = out.emplace_back(
        StationRow{stations_.column_text(0), stations_.column_text(1), stations_.column_int64(2),
                   stations_.column_int64(3), std::nullopt});
    if (!stations_.is_null(4)) {
      row.settings = StationSettings{stations_.column_text(4), stations_.column_text(5)};
    }
  }
  return out;
}

}  // namespace magcal::storage
