// The `leases` and `stations` rows, the same on both backends (storage/row_codec.hpp walks the
// lists), and the lease statements whose SQL the two dialects share (written with SQLite's ?N;
// PostgreSQL runs them through dollar_params()). Internal to storage/.
#pragma once

#include <string_view>

#include "storage/lease_store.hpp"
#include "storage/row_codec.hpp"

namespace magcal::storage {

struct LeaseRow {
  using Record = Lease;
  static constexpr const char* kTable = "leases";
  template <typename L, typename Fields>
  static void fields(L& l, Fields& f) {
    f("sat_id", l.sat_id);
    f("owner", l.owner);
    f("epoch", l.epoch);
    f("acquired_utime", l.acquired_utime);
    f("expires_utime", l.expires_utime);
  }
};

// A station's last beat, as the heartbeat reads it before writing its own.
struct StationBeatRow {
  using Record = StationBeat;
  static constexpr const char* kTable = "stations";
  template <typename B, typename Fields>
  static void fields(B& b, Fields& f) {
    f("instance", b.instance);
    f("heartbeat_utime", b.heartbeat_utime);
    f("expires_utime", b.expires_utime);
  }
};

// A station's row as `magcal status` lists it. The declared settings are two nullable columns
// (settings, settings_hash), NULL together when the station declared none.
template <typename Row>
StationRow read_station(const Row& row) {
  StationRow s{row.text(0), row.text(1), row.integer(2), row.integer(3), std::nullopt};
  if (!row.is_null(4)) s.settings = StationSettings{row.text(4), row.text(5)};
  return s;
}

// The heartbeat's values (lease_sql::kHeartbeat's ?1..?6): settings NULL when none declared.
template <typename Sink>
void bind_heartbeat(Sink& sink, std::string_view station, std::string_view instance,
                    const StationSettings& settings, int64_t now_utime, int64_t ttl_utime) {
  sink.text(station);
  sink.integer(now_utime);
  sink.integer(ttl_utime);
  sink.text(instance);
  if (settings.text.empty()) {
    sink.null();
    sink.null();
  } else {
    sink.text(settings.text);
    sink.text(settings.hash);
  }
}

namespace lease_sql {

// LeaseStore::try_acquire in one upsert (?1 sat_id, ?2 owner, ?3 now, ?4 ttl): a new row at
// epoch 1; an existing row changes only when it is the owner's own (a renewal: epoch and
// acquired time kept) or expired (a takeover: the next epoch). The upsert locks the row, so of
// racing daemons one takes an expired lease and the others then find it held. Returns the row
// when it changed, else nothing.
inline constexpr const char* kAcquire =
    "INSERT INTO leases (sat_id, owner, epoch, acquired_utime, expires_utime) "
    "VALUES (?1, ?2, 1, ?3, ?3 + ?4) ON CONFLICT (sat_id) DO UPDATE SET "
    "epoch = CASE WHEN leases.owner = excluded.owner THEN leases.epoch ELSE leases.epoch + 1 END, "
    "acquired_utime = CASE WHEN leases.owner = excluded.owner THEN leases.acquired_utime "
    "ELSE excluded.acquired_utime END, "
    "owner = excluded.owner, expires_utime = excluded.expires_utime "
    "WHERE leases.owner = excluded.owner OR leases.expires_utime <= excluded.acquired_utime "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

inline constexpr const char* kReclaim =
    "UPDATE leases SET epoch = epoch + 1, acquired_utime = ?4, expires_utime = ?4 + ?5 "
    "WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3 "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

// Ends a lease now unless it already ended (CASE: SQLite's min() of two values is PostgreSQL's
// least()).
inline constexpr const char* kRelease =
    "UPDATE leases SET expires_utime = CASE WHEN expires_utime < ?4 THEN expires_utime ELSE ?4 "
    "END WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3";
inline constexpr const char* kLeave =
    "UPDATE stations SET expires_utime = CASE WHEN expires_utime < ?2 THEN expires_utime ELSE ?2 "
    "END WHERE station = ?1";

inline constexpr const char* kRenew =
    "UPDATE leases SET expires_utime = ?4 + ?5 WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3";

// A lease row without an owner: expired (0), epoch 0, so its first owner gets epoch 1.
inline constexpr const char* kEnsure =
    "INSERT INTO leases (sat_id, owner, epoch, acquired_utime, expires_utime) "
    "VALUES (?1, '', 0, 0, 0) ON CONFLICT (sat_id) DO NOTHING";

// Only leases still held: a released or expired one is not brought back (another daemon may be
// taking it at this moment).
inline constexpr const char* kRenewAll =
    "UPDATE leases SET expires_utime = ?2 + ?3 WHERE owner = ?1 AND expires_utime > ?2 "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

inline constexpr const char* kHeartbeat =
    "INSERT INTO stations (station, heartbeat_utime, expires_utime, instance, settings, "
    "settings_hash) VALUES (?1, ?2, ?2 + ?3, ?4, ?5, ?6) "
    "ON CONFLICT (station) DO UPDATE SET heartbeat_utime = excluded.heartbeat_utime, "
    "expires_utime = excluded.expires_utime, instance = excluded.instance, "
    "settings = excluded.settings, settings_hash = excluded.settings_hash";
// Sorted by the bytes of the id on both backends (followed by SqlSession::byte_order()).
inline constexpr const char* kStationList =
    "SELECT station, instance, heartbeat_utime, expires_utime, settings, settings_hash "
    "FROM stations ORDER BY station";

}  // namespace lease_sql
}  // namespace magcal::storage
