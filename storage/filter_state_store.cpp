#include "storage/filter_state_store.hpp"

#include <bit>
#include <chrono>
#include <cstring>

namespace magcal::storage {
namespace {

static_assert(std::endian::native == std::endian::little,
              "BLOBs hold little-endian doubles; add byte swapping for this platform");

template <size_t N>
void read_doubles(std::span<const unsigned char> blob, std::array<double, N>& out,
                  const char* what) {
  if (blob.size() != sizeof(double) * N) {
    throw StorageError(StorageError::Kind::kSqlite, std::string("filter_states.") + what + " has " +
                                                        std::to_string(blob.size()) +
                                                        " bytes, expected " +
                                                        std::to_string(sizeof(double) * N));
  }
  std::memcpy(out.data(), blob.data(), blob.size());
}

}  // namespace

FilterStateStore::FilterStateStore(Database& db)
    : db_(db),
      upsert_(
          db,
          "INSERT OR REPLACE INTO filter_states (sat_id, method, x, P, last_utime, "
          "n_samples, counters, updated_utime, anchor_calibration_id) VALUES (?1, ?2, ?3, ?4, ?5, "
          "?6, ?7, ?8, ?9)"),
      load_(db,
            "SELECT sat_id, method, x, P, last_utime, n_samples, counters, updated_utime, "
            "anchor_calibration_id FROM filter_states WHERE sat_id = ?1 AND method = ?2"),
      load_all_(db,
                "SELECT sat_id, method, x, P, last_utime, n_samples, counters, updated_utime, "
                "anchor_calibration_id FROM filter_states ORDER BY sat_id, method") {}

void FilterStateStore::save(const FilterState& s) {
  const int64_t updated = s.updated_utime != 0
                              ? s.updated_utime
                              : std::chrono::duration_cast<std::chrono::microseconds>(
                                    std::chrono::system_clock::now().time_since_epoch())
                                    .count();
  auto use = upsert_.use();
  upsert_.bind(1, s.sat_id).bind(2, s.method);
  upsert_.bind_blob(3, s.x.data(), sizeof(double) * s.x.size());
  upsert_.bind_blob(4, s.P.data(), sizeof(double) * s.P.size());
  upsert_.bind(5, s.last_utime).bind(6, s.n_samples);
  upsert_.bind_blob(7, s.counters.data(), s.counters.size());
  upsert_.bind(8, updated).bind(9, s.anchor_calibration_id);
  upsert_.execute();
}

FilterState FilterStateStore::read_row(Statement& st) {
  FilterState s;
  s.sat_id = st.column_text(0);
  s.method = st.column_text(1);
  read_doubles(st.column_blob(2), s.x, "x");
  read_doubles(st.column_blob(3), s.P, "P");
  s.last_utime = st.column_int64(4);
  s.n_samples = st.column_int64(5);
  const auto counters = st.column_blob(6);
  s.counters.assign(counters.begin(), counters.end());
  s.updated_utime = st.column_int64(7);
  s.anchor_calibration_id =
      st.is_null(8) ? std::nullopt : std::optional<int64_t>(st.column_int64(8));
  return s;
}

std::optional<FilterState> FilterStateStore::load(std::string_view sat_id,
                                                  std::string_view method) {
  auto use = load_.use();
  load_.bind(1, sat_id).bind(2, method);
  if (!load_.step()) return std::nullopt;
  return read_row(load_);
}

std::vector<FilterState> FilterStateStore::load_all() {
  std::vector<FilterState> out;
  auto use = load_all_.use();
  while (load_all_.step()) out.push_back(read_row(load_all_));
  return out;
}

}  // namespace magcal::storage
