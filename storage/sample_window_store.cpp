#include "storage/sample_window_store.hpp"

namespace magcal::storage {

std::vector<StoredSample> SampleWindowStore::window(std::string_view sat_id, int64_t t0_utime,
                                                    int64_t t1_utime) {
  std::vector<StoredSample> out;
  read_window(sat_id, t0_utime, t1_utime, out);
  return out;
}

void SampleWindowStore::read_windows(std::span<const WindowRequest> requests,
                                     std::vector<StoredSample>& out, std::vector<size_t>& ends) {
  out.clear();
  ends.clear();
  for (const WindowRequest& r : requests) {
    read_window(r.sat_id, r.t0_utime, r.t1_utime, window_rows_);
    out.insert(out.end(), std::make_move_iterator(window_rows_.begin()),
               std::make_move_iterator(window_rows_.end()));
    ends.push_back(out.size());
  }
}

RetentionStats SampleWindowStore::delete_before(std::string_view sat_id, int64_t cutoff_utime,
                                                int chunk_rows) {
  if (chunk_rows <= 0) {
    throw StorageError(StorageError::Kind::kInvalidArgument, "chunk_rows must be positive");
  }
  RetentionStats stats;
  for (;;) {
    const int64_t deleted = delete_chunk(sat_id, cutoff_utime, chunk_rows);
    ++stats.transactions;
    stats.deleted += deleted;
    if (deleted < chunk_rows) break;
  }
  return stats;
}

RetentionStats SampleWindowStore::apply_retention(std::string_view sat_id, int64_t window_utime,
                                                  int64_t margin_utime, int chunk_rows) {
  const auto newest = newest_utime(sat_id);
  if (!newest) return {};
  return delete_before(sat_id, *newest - window_utime - margin_utime, chunk_rows);
}

}  // namespace magcal::storage
