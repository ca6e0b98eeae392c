// Table `filter_states`: the latest online filter state per (sat_id, method), so the daemon
// resumes exactly after a restart (with the refit it was last re-anchored on). x and P are stored
// as blobs of raw little-endian IEEE-754 doubles: the round trip is bit-exact. An interface:
// SqlFilterStateStore (storage/sql_filter_state_store.hpp, both backends) and PgFilterStateStore
// (storage/postgres/pg_filter_state_store.hpp), made by Connection::make_filter_state_store().
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::storage {

struct FilterState {
  std::string sat_id;
  std::string method;             // "ukf" | "ekf"
  std::array<double, 9> x{};      // [b1 b2 b3 D11 D22 D33 D12 D13 D23]
  std::array<double, 81> P{};     // 9x9 covariance, row-major
  int64_t last_utime = 0;         // newest sample the state includes
  int64_t n_samples = 0;          // samples processed
  std::vector<uint8_t> counters;  // opaque to storage (the filter's own counters)
  // calibrations.id of the refit the state was last re-anchored on, 0 if none; nullopt: saved
  // before schema 4 (unknown).
  std::optional<int64_t> anchor_calibration_id = 0;
  int64_t updated_utime = 0;  // wall time of the save; 0: now
};

class FilterStateStore {
 public:
  virtual ~FilterStateStore() = default;
  // Insert or replace the row of (sat_id, method).
  virtual void save(const FilterState& state) = 0;
  // save() of each, in order (of two states of one (sat_id, method) the later one stays). On
  // PostgreSQL a few statements for the lot instead of a round trip each. Throws StorageError
  // (call it inside a transaction to store all or nothing).
  virtual void save_all(std::span<const FilterState> states);
  virtual std::optional<FilterState> load(std::string_view sat_id, std::string_view method) = 0;
  // Every stored state, ordered by (sat_id, method).
  virtual std::vector<FilterState> load_all() = 0;
};

// updated_utime of a save: the state's own, or now when it is 0.
int64_t save_utime(const FilterState& state);

}  // namespace magcal::storage
