#include "storage/postgres/pg_lease_store.hpp"

#include <algorithm>

#include "storage/lease_row.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {
namespace {

std::vector<Lease> leases(const PgResult& r) {
  std::vector<Lease> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(row_codec::read<LeaseRow>(PgRow{r, row}));
  return out;
}

std::optional<Lease> first_lease(const PgResult& r) {
  if (r.rows() == 0) return std::nullopt;
  return row_codec::read<LeaseRow>(PgRow{r, 0});
}

// sat_id, owner, epoch, now, ttl: the parameters of a lease's own statements.
PgParams lease_params(std::string_view sat_id, std::string_view owner, int64_t epoch,
                      int64_t now_utime, int64_t ttl_utime) {
  PgParams p;
  p.add(sat_id).add(owner).add(epoch).add(now_utime).add(ttl_utime);
  return p;
}

}  // namespace

std::optional<Lease> PgLeaseStore::try_acquire(std::string_view sat_id, std::string_view owner,
                                               int64_t now_utime, int64_t ttl_utime) {
  static const std::string sql = dollar_params(lease_sql::kAcquire);
  check_request(owner, ttl_utime);
  PgParams p;
  p.add(sat_id).add(owner).add(now_utime).add(ttl_utime);
  return first_lease(db_.execute_prepared(sql, p, PgFormat::kBinary));  // nothing: held
}

bool PgLeaseStore::renew(std::string_view sat_id, std::string_view owner, int64_t epoch,
                         int64_t now_utime, int64_t ttl_utime) {
  static const std::string sql = dollar_params(lease_sql::kRenew);
  check_request(owner, ttl_utime);
  const PgParams p = lease_params(sat_id, owner, epoch, now_utime, ttl_utime);
  return db_.execute_prepared(sql, p).affected_rows() == 1;
}

std::optional<Lease> PgLeaseStore::reclaim(std::string_view sat_id, std::string_view owner,
                                           int64_t epoch, int64_t now_utime, int64_t ttl_utime) {
  static const std::string sql = dollar_params(lease_sql::kReclaim);
  check_request(owner, ttl_utime);
  const PgParams p = lease_params(sat_id, owner, epoch, now_utime, ttl_utime);
  return first_lease(db_.execute_prepared(sql, p, PgFormat::kBinary));
}

bool PgLeaseStore::release(std::string_view sat_id, std::string_view owner, int64_t epoch,
                           int64_t now_utime) {
  PgParams p;
  p.add(sat_id).add(owner).add(epoch).add(now_utime);
  return db_.execute_prepared(
                "UPDATE leases SET expires_utime = least(expires_utime, $4) WHERE "
                "sat_id = $1 AND owner = $2 AND epoch = $3",
                p)
             .affected_rows() == 1;
}

bool PgLeaseStore::holds(std::string_view sat_id, std::string_view owner, int64_t epoch) {
  PgParams p;
  p.add(sat_id).add(owner).add(epoch);
  // FOR SHARE: a takeover's upsert waits until the caller's transaction ends.
  return db_.execute_prepared(
                "SELECT 1 FROM leases WHERE sat_id = $1 AND owner = $2 AND "
                "epoch = $3 FOR SHARE",
                p)
             .rows() == 1;
}

std::vector<std::string> PgLeaseStore::not_held(std::string_view owner,
                                                std::span<const Held> leases) {
  if (leases.empty()) return {};
  std::vector<std::string> sats;
  std::vector<int64_t> epochs;
  for (const Held& l : leases) {
    sats.push_back(l.sat_id);
    epochs.push_back(l.epoch);
  }
  PgParams p;
  p.add(owner).add_array(sats).add_array(epochs);
  // Locked in one order (sat_id, as renew_all and the takeovers' single rows need no other), so
  // two fences never wait for each other crosswise.
  const PgResult r = db_.execute_prepared(
      "SELECT l.sat_id FROM leases l JOIN unnest($2::text[], $3::bigint[]) AS q(sat_id, epoch) "
      "ON l.sat_id = q.sat_id AND l.epoch = q.epoch WHERE l.owner = $1 ORDER BY l.sat_id "
      "FOR SHARE OF l",
      p);
  std::vector<std::string> held;
  held.reserve(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) held.push_back(r.get_text(row, 0));
  std::sort(held.begin(), held.end());
  std::vector<std::string> out;
  for (const Held& l : leases) {
    if (!std::binary_search(held.begin(), held.end(), l.sat_id)) out.push_back(l.sat_id);
  }
  return out;
}

std::optional<Lease> PgLeaseStore::get(std::string_view sat_id) {
  static const std::string sql = row_codec::select_sql<LeaseRow>("WHERE sat_id = $1");
  PgParams p;
  p.add(sat_id);
  return first_lease(db_.execute_prepared(sql, p, PgFormat::kBinary));
}

std::vector<Lease> PgLeaseStore::list() {
  static const std::string sql = row_codec::select_sql<LeaseRow>("ORDER BY sat_id COLLATE \"C\"");
  return leases(db_.execute_prepared(sql, {}, PgFormat::kBinary));
}

void PgLeaseStore::ensure(std::string_view sat_id) {
  static const std::string sql = dollar_params(lease_sql::kEnsure);
  PgParams p;
  p.add(sat_id);
  db_.execute_prepared(sql, p);
}

std::vector<Lease> PgLeaseStore::renew_all(std::string_view owner, int64_t now_utime,
                                           int64_t ttl_utime) {
  static const std::string sql = dollar_params(lease_sql::kRenewAll);
  check_request(owner, ttl_utime);
  PgParams p;
  p.add(owner).add(now_utime).add(ttl_utime);
  return leases(db_.execute_prepared(sql, p, PgFormat::kBinary));
}

std::optional<StationBeat> PgLeaseStore::heartbeat(std::string_view station,
                                                   std::string_view instance,
                                                   const StationSettings& settings,
                                                   int64_t now_utime, int64_t ttl_utime) {
  static const std::string beat_sql = dollar_params(lease_sql::kStationBeat);
  static const std::string heartbeat_sql = dollar_params(lease_sql::kHeartbeat);
  check_request(station, ttl_utime);
  std::optional<StationBeat> before;
  {
    PgParams p;
    p.add(station);
    const PgResult r = db_.execute_prepared(beat_sql, p, PgFormat::kBinary);
    if (r.rows() > 0) before = row_codec::read<StationBeatRow>(PgRow{r, 0});
  }
  PgParams p;
  PgBinder binder{p};
  bind_heartbeat(binder, station, instance, settings, now_utime, ttl_utime);
  db_.execute_prepared(heartbeat_sql, p);
  return before;
}

void PgLeaseStore::leave(std::string_view station, int64_t now_utime) {
  PgParams p;
  p.add(station).add(now_utime);
  db_.execute_prepared(
      "UPDATE stations SET expires_utime = least(expires_utime, $2) WHERE station = $1", p);
}

std::vector<std::string> PgLeaseStore::live_stations(int64_t now_utime) {
  PgParams p;
  p.add(now_utime);
  const PgResult r = db_.execute_prepared(
      "SELECT station FROM stations WHERE expires_utime > $1 ORDER BY station COLLATE \"C\"", p);
  std::vector<std::string> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(r.get_text(row, 0));
  return out;
}

std::vector<StationRow> PgLeaseStore::stations() {
  static const std::string sql = std::string(lease_sql::kStationList) + " COLLATE \"C\"";
  const PgResult r = db_.execute_prepared(sql, PgParams{}, PgFormat::kBinary);
  std::vector<StationRow> out;
  for (int row = 0; row < r.rows(); ++row) out.push_back(read_station(PgRow{r, row}));
  return out;
}

}  // namespace magcal::storage
