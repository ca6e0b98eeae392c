// Per-spacecraft online state held by the daemon's worker: the UKF (estimation.md section 3),
// the newest sample time (the spacecraft's window edge, data time), the last sequence number
// (gaps count as missing samples) and the next snapshot time. A spacecraft appears on its first
// valid frame. Size is what the memory target counts (design.md: < 4 KB per spacecraft).
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <unordered_map>

#include "pipeline/magnetometer_ukf.hpp"

namespace magcal {

struct SpacecraftTracker {
  explicit SpacecraftTracker(const MagnetometerUkf::Options& options) : ukf(options) {}

  MagnetometerUkf ukf;
  int64_t newest_utime = std::numeric_limits<int64_t>::min();  // newest stored sample
  int64_t last_seq = std::numeric_limits<int64_t>::min();      // none yet
  int64_t next_snapshot_utime = std::numeric_limits<int64_t>::min();
  bool state_dirty = false;    // filter changed since its state was last written
  bool retention_due = false;  // new samples since the last retention pass

  // Missing samples implied by `seq` (a forward gap); out-of-order or repeated numbers, and
  // jumps larger than kMaxSeqGap (a counter reset), imply none. Advances last_seq.
  int64_t observe_seq(int64_t seq);
  static constexpr int64_t kMaxSeqGap = 1'000'000;
};

class SpacecraftFleet {
 public:
  explicit SpacecraftFleet(MagnetometerUkf::Options options) : options_(options) {}

  SpacecraftTracker* find(const std::string& sat_id);
  // Creates the tracker on first use; `created` (optional) tells whether it did.
  SpacecraftTracker& get(const std::string& sat_id, bool* created = nullptr);
  size_t size() const { return trackers_.size(); }

  template <typename F>
  void for_each(F&& f) {
    for (auto& [sat, t] : trackers_) f(sat, t);
  }

  // Approximate resident bytes per spacecraft: the tracker, the map node and bucket share.
  static size_t approx_bytes_per_spacecraft();

 private:
  MagnetometerUkf::Options options_;
  std::unordered_map<std::string, SpacecraftTracker> trackers_;
};

}  // namespace magcal
