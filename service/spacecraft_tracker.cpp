#include "service/spacecraft_tracker.hpp"

namespace magcal {

int64_t SpacecraftTracker::observe_seq(int64_t seq) {
  int64_t missing = 0;
  if (last_seq != std::numeric_limits<int64_t>::min() && seq > last_seq + 1 &&
      seq - last_seq - 1 <= kMaxSeqGap) {
    missing = seq - last_seq - 1;
  }
  // Out-of-order (older) numbers do not move the edge back: recorder playback interleaves.
  if (last_seq == std::numeric_limits<int64_t>::min() || seq > last_seq ||
      last_seq - seq > kMaxSeqGap) {
    last_seq = seq;
  }
  return missing;
}

SpacecraftTracker* SpacecraftFleet::find(const std::string& sat_id) {
  const auto it = trackers_.find(sat_id);
  return it == trackers_.end() ? nullptr : &it->second;
}

SpacecraftTracker& SpacecraftFleet::get(const std::string& sat_id, bool* created) {
  auto [it, inserted] = trackers_.try_emplace(sat_id, options_);
  if (created) *created = inserted;
  return it->second;
}

size_t SpacecraftFleet::approx_bytes_per_spacecraft() {
  // libstdc++ node: next pointer + cached hash + pair<const string, tracker>; one bucket
  // pointer per element at load factor 1.
  return sizeof(void*) + sizeof(size_t) + sizeof(std::pair<const std::string, SpacecraftTracker>) +
         sizeof(void*);
}

}  // namespace magcal
