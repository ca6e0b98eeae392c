// The embedded schema migrations. Each entry is the verbatim text of
// storage/migrations/NNNN_name.sql (tests/storage/migrations_test.cpp checks they are identical):
// when adding a migration, add the .sql file and paste it here as a new raw string.
#include "storage/migrations.hpp"

#include <array>

namespace magcal::storage {
namespace {

constexpr const char* kMigration0001 =
    R"sql(-- magcal schema version 1. Applied in one transaction that also sets PRAGMA user_version = 1
-- (and application_id). Units: nT (fields), metres (positions), utime = microseconds since
-- 1970-01-01T00:00:00Z (leap seconds ignored). NULL means "not available".

-- Telemetry samples, per spacecraft and sample time: the refit windows. Retention deletes rows
-- older than (newest utime of the spacecraft) - window_hours - retention_margin_hours.
CREATE TABLE samples (
  sat_id        TEXT    NOT NULL,
  utime         INTEGER NOT NULL,  -- sample time
  seq           INTEGER NOT NULL,  -- per-spacecraft sequence number
  receive_utime INTEGER NOT NULL,  -- ground receive time (wall clock)
  bx_nT         REAL    NOT NULL,  -- measured field, sensor frame
  by_nT         REAL    NOT NULL,
  bz_nT         REAL    NOT NULL,
  has_direction INTEGER NOT NULL,  -- 1: hx..hz is the reference field in the body frame
  hx_nT         REAL,              -- reference field, body frame (NULL when has_direction = 0)
  hy_nT         REAL,
  hz_nT         REAL,
  h_norm_nT     REAL    NOT NULL,  -- |reference field| (always known)
  qw            REAL,              -- attitude q_body_from_eci (w,x,y,z), NULL when absent
  qx            REAL,
  qy            REAL,
  qz            REAL,
  rx_m          REAL,              -- GNSS position, ECEF, NULL when absent
  ry_m          REAL,
  rz_m          REAL,
  temperature_C REAL,              -- NULL when unknown
  PRIMARY KEY (sat_id, utime)
) WITHOUT ROWID;

-- Every calibration result (online filter snapshots and refits). Never deleted by retention.
CREATE TABLE calibrations (
  id                 INTEGER PRIMARY KEY,
  sat_id             TEXT    NOT NULL,
  method             TEXT    NOT NULL,  -- 'ukf', 'ekf', 'centered', 'twostep'
  utime              INTEGER NOT NULL,  -- time the estimate refers to
  window_start_utime INTEGER NOT NULL,
  window_end_utime   INTEGER NOT NULL,
  n_samples          INTEGER NOT NULL,
  bias_x_nT          REAL    NOT NULL,
  bias_y_nT          REAL    NOT NULL,
  bias_z_nT          REAL    NOT NULL,
  bias_sigma_x_nT    REAL,              -- 1-sigma, sqrt of the covariance diagonal
  bias_sigma_y_nT    REAL,
  bias_sigma_z_nT    REAL,
  D11 REAL NOT NULL, D22 REAL NOT NULL, D33 REAL NOT NULL,
  D12 REAL NOT NULL, D13 REAL NOT NULL, D23 REAL NOT NULL,
  cov                BLOB    NOT NULL,  -- 45 little-endian doubles: upper triangle, row-major,
                                        -- of the 9x9 covariance of [b1 b2 b3 D11 D22 D33 D12 D13 D23]
  has_alignment      INTEGER NOT NULL,
  R11 REAL, R12 REAL, R13 REAL,         -- R_sensor_from_body (NULL when has_alignment = 0)
  R21 REAL, R22 REAL, R23 REAL,
  R31 REAL, R32 REAL, R33 REAL,
  residual_rms_nT    REAL,
  status             INTEGER NOT NULL CHECK (status BETWEEN 0 AND 4),
                     -- 0 ok, 1 not converged, 2 unobservable, 3 failed, 4 rejected
  verdict            TEXT    NOT NULL CHECK (verdict IN ('accepted', 'rejected')),
  rejection_reasons  TEXT    NOT NULL DEFAULT '[]',  -- JSON array of strings
  iterations         INTEGER NOT NULL DEFAULT 0,
  software_version   TEXT    NOT NULL,
  created_utime      INTEGER NOT NULL   -- wall time the row was written
);
CREATE INDEX calibrations_by_sat_method_time ON calibrations (sat_id, method, utime);
CREATE INDEX calibrations_by_sat_time ON calibrations (sat_id, utime);

-- One row per scheduled or manual refit.
CREATE TABLE refit_jobs (
  id              INTEGER PRIMARY KEY,
  sat_id          TEXT    NOT NULL,
  trigger_kind    TEXT    NOT NULL,  -- 'scheduled' | 'manual'
  scheduled_utime INTEGER NOT NULL,  -- when it was due (data or wall clock, as configured)
  started_utime   INTEGER,           -- wall clock
  finished_utime  INTEGER,           -- wall clock
  outcome         TEXT    NOT NULL,  -- 'running', 'ok', 'rejected', 'failed', 'skipped',
                                     -- 'interrupted' (the process died while it ran)
  error           TEXT    NOT NULL DEFAULT '',
  calibration_id  INTEGER REFERENCES calibrations (id)
);
CREATE INDEX refit_jobs_by_sat ON refit_jobs (sat_id, id);

-- Latest online filter state per spacecraft and method (restart resumes from it).
CREATE TABLE filter_states (
  sat_id        TEXT    NOT NULL,
  method        TEXT    NOT NULL,  -- 'ukf' | 'ekf'
  x             BLOB    NOT NULL,  -- 9 little-endian doubles [b1 b2 b3 D11 D22 D33 D12 D13 D23]
  P             BLOB    NOT NULL,  -- 81 little-endian doubles, 9x9 covariance, row-major
  last_utime    INTEGER NOT NULL,  -- newest sample included in the state
  n_samples     INTEGER NOT NULL,
  counters      BLOB,              -- the filter's own counters (opaque)
  updated_utime INTEGER NOT NULL,  -- wall time of the save
  PRIMARY KEY (sat_id, method)
) WITHOUT ROWID;
)sql";

constexpr const char* kMigration0002 =
    R"sql(-- magcal schema version 2: a few named values about the database itself (e.g. the version of
-- the daemon that last opened it). Applied in one transaction that sets PRAGMA user_version = 2.
CREATE TABLE meta (
  key   TEXT NOT NULL PRIMARY KEY,
  value TEXT NOT NULL
) WITHOUT ROWID;
)sql";

constexpr std::array<Migration, 2> kMigrations = {{
    {1, "0001_init", kMigration0001},
    {2, "0002_meta", kMigration0002},
}};

}  // namespace

std::span<const Migration> migrations() {
  return kMigrations;
}

}  // namespace magcal::storage
