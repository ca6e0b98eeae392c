// The column lists (and the one shared statement) the stores of both backends read and write,
// in the order their code binds and reads them (the SQLite and PostgreSQL schemas have the same
// columns under the same names: storage/migrations, storage/postgres/migrations). Internal to
// storage/.
#pragma once

namespace magcal::storage::columns {

// samples: a stored sample after its key (sat_id, utime) ... read back in this order.
inline constexpr const char* kSampleRead =
    "utime, seq, receive_utime, bx_nT, by_nT, bz_nT, has_direction, hx_nT, hy_nT, hz_nT, "
    "h_norm_nT, qw, qx, qy, qz, rx_m, ry_m, rz_m, temperature_C";
// samples: what an insert binds, in order (21 values).
inline constexpr const char* kSampleInsert =
    "sat_id, utime, seq, receive_utime, bx_nT, by_nT, bz_nT, has_direction, hx_nT, hy_nT, "
    "hz_nT, h_norm_nT, qw, qx, qy, qz, rx_m, ry_m, rz_m, temperature_C, station";
// refit_jobs: a RefitJob.
inline constexpr const char* kRefitJob =
    "id, sat_id, trigger_kind, scheduled_utime, started_utime, finished_utime, outcome, error, "
    "calibration_id, claimed_by";
// filter_states: a FilterState, written and read in this order (9 values).
inline constexpr const char* kFilterState =
    "sat_id, method, x, P, last_utime, n_samples, counters, updated_utime, "
    "anchor_calibration_id";

// refit_jobs: the job holding the claim of its (sat_id, trigger_kind, scheduled_utime), the
// predicate of the unique index refit_jobs_one_claim (migration 7), which an upsert names to
// use that index.
inline constexpr const char* kHoldsRefitClaim =
    "claimed_by IS NOT NULL AND outcome <> 'interrupted'";
// leases: a Lease.
inline constexpr const char* kLease = "sat_id, owner, epoch, acquired_utime, expires_utime";

// LeaseStore::try_acquire in one upsert, the same SQL on both backends (?1 sat_id, ?2 owner,
// ?3 now, ?4 ttl; PostgreSQL spells them $1..$4): a new row at epoch 1; an existing row changes
// only when it is the owner's own (a renewal: epoch and acquired time kept) or expired (a
// takeover: the next epoch). The upsert locks the row, so of racing daemons one takes an
// expired lease and the others then find it held. Returns the row when it changed, else nothing.
inline constexpr const char* kLeaseAcquire =
    "INSERT INTO leases (sat_id, owner, epoch, acquired_utime, expires_utime) "
    "VALUES (?1, ?2, 1, ?3, ?3 + ?4) ON CONFLICT (sat_id) DO UPDATE SET "
    "epoch = CASE WHEN leases.owner = excluded.owner THEN leases.epoch ELSE leases.epoch + 1 END, "
    "acquired_utime = CASE WHEN leases.owner = excluded.owner THEN leases.acquired_utime "
    "ELSE excluded.acquired_utime END, "
    "owner = excluded.owner, expires_utime = excluded.expires_utime "
    "WHERE leases.owner = excluded.owner OR leases.expires_utime <= excluded.acquired_utime "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

inline constexpr const char* kLeaseReclaim =
    "UPDATE leases SET epoch = epoch + 1, acquired_utime = ?4, expires_utime = ?4 + ?5 "
    "WHERE sat_id = ?1 AND owner = ?2 AND epoch = ?3 "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

// A lease row without an owner: expired (0), epoch 0, so its first owner gets epoch 1.
inline constexpr const char* kLeaseEnsure =
    "INSERT INTO leases (sat_id, owner, epoch, acquired_utime, expires_utime) "
    "VALUES (?1, '', 0, 0, 0) ON CONFLICT (sat_id) DO NOTHING";

// Only leases still held: a released or expired one is not brought back (another daemon may be
// taking it at this moment).
inline constexpr const char* kLeaseRenewAll =
    "UPDATE leases SET expires_utime = ?2 + ?3 WHERE owner = ?1 AND expires_utime > ?2 "
    "RETURNING sat_id, owner, epoch, acquired_utime, expires_utime";

inline constexpr const char* kStationHeartbeat =
    "INSERT INTO stations (station, heartbeat_utime, expires_utime, instance, settings, "
    "settings_hash) VALUES (?1, ?2, ?2 + ?3, ?4, ?5, ?6) "
    "ON CONFLICT (station) DO UPDATE SET heartbeat_utime = excluded.heartbeat_utime, "
    "expires_utime = excluded.expires_utime, instance = excluded.instance, "
    "settings = excluded.settings, settings_hash = excluded.settings_hash";
// Sorted by the bytes of the id on both backends (COLLATE "C" on PostgreSQL, as SQLite's BINARY).
inline constexpr const char* kStationList =
    "SELECT station, instance, heartbeat_utime, expires_utime, settings, settings_hash "
    "FROM stations ORDER BY station";
inline constexpr const char* kStationBeat =
    "SELECT instance, heartbeat_utime, expires_utime FROM stations WHERE station = ?1";

}  // namespace magcal::storage::columns
