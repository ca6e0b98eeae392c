// The column lists the stores of both backends read and write, in the order their code binds
// and reads them (the SQLite and PostgreSQL schemas have the same columns under the same names:
// storage/migrations, storage/postgres/migrations). Internal to storage/.
#pragma once

namespace magcal::storage::columns {

// samples: a stored sample after its key (sat_id, utime) ... read back in this order.
inline constexpr const char* kSampleRead =
    "utime, seq, receive_utime, bx_nT, by_nT, bz_nT, has_direction, hx_nT, hy_nT, hz_nT, "
    "h_norm_nT, qw, qx, qy, qz, rx_m, ry_m, rz_m, temperature_C";
// samples: what an insert binds, in order (20 values).
inline constexpr const char* kSampleInsert =
    "sat_id, utime, seq, receive_utime, bx_nT, by_nT, bz_nT, has_direction, hx_nT, hy_nT, "
    "hz_nT, h_norm_nT, qw, qx, qy, qz, rx_m, ry_m, rz_m, temperature_C";
// refit_jobs: a RefitJob.
inline constexpr const char* kRefitJob =
    "id, sat_id, trigger_kind, scheduled_utime, started_utime, finished_utime, outcome, error, "
    "calibration_id";
// filter_states: a FilterState, written and read in this order (9 values).
inline constexpr const char* kFilterState =
    "sat_id, method, x, P, last_utime, n_samples, counters, updated_utime, "
    "anchor_calibration_id";

}  // namespace magcal::storage::columns
