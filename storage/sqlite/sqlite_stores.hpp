// The SQLite implementations of the stores, one header each (storage/sqlite/sqlite_*.hpp), for
// the tests and tools that hold a Database and construct them directly.
#pragma once

#include "storage/sqlite/sqlite_calibration_history.hpp"
#include "storage/sqlite/sqlite_filter_state_store.hpp"
#include "storage/sqlite/sqlite_lease_store.hpp"
#include "storage/sqlite/sqlite_meta_store.hpp"
#include "storage/sqlite/sqlite_refit_job_log.hpp"
#include "storage/sqlite/sqlite_sample_window_store.hpp"
