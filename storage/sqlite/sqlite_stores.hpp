// The SQLite stores, for the tests and tools that hold a Database and construct them directly:
// the sample window store and the calibration history of SQLite's own (storage/sqlite/), and
// the stores written once for both backends (storage/sql_*.hpp) under their SQLite names.
#pragma once

#include "storage/sql_calibration_history.hpp"
#include "storage/sql_filter_state_store.hpp"
#include "storage/sql_lease_store.hpp"
#include "storage/sql_meta_store.hpp"
#include "storage/sql_refit_job_log.hpp"
#include "storage/sqlite/sqlite_sample_window_store.hpp"

namespace magcal::storage {

using SqliteRefitJobLog = SqlRefitJobLog;
using SqliteFilterStateStore = SqlFilterStateStore;
using SqliteMetaStore = SqlMetaStore;
using SqliteLeaseStore = SqlLeaseStore;
using SqliteCalibrationHistory = SqlCalibrationHistory;

}  // namespace magcal::storage
