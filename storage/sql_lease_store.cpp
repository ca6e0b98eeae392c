#include "storage/sql_lease_store.hpp"

#include "storage/lease_row.hpp"

namespace magcal::storage {
namespace {

Lease read_lease(const SqlRow& row) {
  return row_codec::read<LeaseRow>(row);
}

}  // namespace

SqlLeaseStore::SqlLeaseStore(SqlSession& db)
    : acquire_(db.prepare(lease_sql::kAcquire)),
      renew_(db.prepare(lease_sql::kRenew)),
      reclaim_(db.prepare(lease_sql::kReclaim)),
      release_(db.prepare(lease_sql::kRelease)),
      // Locked (PostgreSQL): a takeover's upsert waits until the caller's transaction ends.
      holds_(db.prepare(std::string("SELECT 1 FROM leases WHERE sat_id = ?1 AND owner = ?2 AND "
                                    "epoch = ?3") +
                        db.lock_rows_shared())),
      get_(db.prepare(row_codec::select_sql<LeaseRow>("WHERE sat_id = ?1"))),
      list_(db.prepare(
          row_codec::select_sql<LeaseRow>(std::string("ORDER BY sat_id") + db.byte_order()))),
      ensure_(db.prepare(lease_sql::kEnsure)),
      renew_all_(db.prepare(lease_sql::kRenewAll)),
      heartbeat_(db.prepare(lease_sql::kHeartbeat)),
      beat_(db.prepare(row_codec::select_sql<StationBeatRow>("WHERE station = ?1"))),
      leave_(db.prepare(lease_sql::kLeave)),
      live_(db.prepare(std::string("SELECT station FROM stations WHERE expires_utime > ?1 "
                                   "ORDER BY station") +
                       db.byte_order())),
      stations_(db.prepare(std::string(lease_sql::kStationList) + db.byte_order())) {}

std::optional<Lease> SqlLeaseStore::try_acquire(std::string_view sat_id, std::string_view owner,
                                                int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  // Nothing: another owner holds it.
  return SqlRun(*acquire_, sat_id, owner, now_utime, ttl_utime).first<Lease>(read_lease);
}

bool SqlLeaseStore::renew(std::string_view sat_id, std::string_view owner, int64_t epoch,
                          int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  return SqlRun(*renew_, sat_id, owner, epoch, now_utime, ttl_utime).changes() == 1;
}

std::optional<Lease> SqlLeaseStore::reclaim(std::string_view sat_id, std::string_view owner,
                                            int64_t epoch, int64_t now_utime, int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  return SqlRun(*reclaim_, sat_id, owner, epoch, now_utime, ttl_utime).first<Lease>(read_lease);
}

bool SqlLeaseStore::release(std::string_view sat_id, std::string_view owner, int64_t epoch,
                            int64_t now_utime) {
  return SqlRun(*release_, sat_id, owner, epoch, now_utime).changes() == 1;
}

bool SqlLeaseStore::holds(std::string_view sat_id, std::string_view owner, int64_t epoch) {
  return SqlRun(*holds_, sat_id, owner, epoch).next();
}

std::optional<Lease> SqlLeaseStore::get(std::string_view sat_id) {
  return SqlRun(*get_, sat_id).first<Lease>(read_lease);
}

std::vector<Lease> SqlLeaseStore::list() {
  return SqlRun(*list_).all<Lease>(read_lease);
}

void SqlLeaseStore::ensure(std::string_view sat_id) {
  SqlRun(*ensure_, sat_id).changes();
}

std::vector<Lease> SqlLeaseStore::renew_all(std::string_view owner, int64_t now_utime,
                                            int64_t ttl_utime) {
  check_request(owner, ttl_utime);
  return SqlRun(*renew_all_, owner, now_utime, ttl_utime).all<Lease>(read_lease);
}

std::optional<StationBeat> SqlLeaseStore::heartbeat(std::string_view station,
                                                    std::string_view instance,
                                                    const StationSettings& settings,
                                                    int64_t now_utime, int64_t ttl_utime) {
  check_request(station, ttl_utime);
  const std::optional<StationBeat> before =
      SqlRun(*beat_, station).first<StationBeat>([](const SqlRow& row) {
        return row_codec::read<StationBeatRow>(row);
      });
  SqlRun run(*heartbeat_);
  bind_heartbeat(*heartbeat_, station, instance, settings, now_utime, ttl_utime);
  run.changes();
  return before;
}

void SqlLeaseStore::leave(std::string_view station, int64_t now_utime) {
  SqlRun(*leave_, station, now_utime).changes();
}

std::vector<std::string> SqlLeaseStore::live_stations(int64_t now_utime) {
  return SqlRun(*live_, now_utime).all<std::string>([](const SqlRow& row) { return row.text(0); });
}

std::vector<StationRow> SqlLeaseStore::stations() {
  return SqlRun(*stations_).all<StationRow>([](const SqlRow& row) { return read_station(row); });
}

}  // namespace magcal::storage
