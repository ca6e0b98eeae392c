#include "service/daemon/ownership/spacecraft_tracker.hpp"

#include <algorithm>

#include "pipeline/time_utc.hpp"
#include "service/daemon/ops/health.hpp"

namespace magcal {

int64_t SeqGapCounter::observe(int64_t seq) {
  if (last_seq == kNone) {
    last_seq = seq;
    return 0;
  }
  // Saturating: seq is untrusted and may sit at either int64 limit.
  if (gap_seq != kNone) {
    // A forward jump is believed once the next number continues after it; a number that does
    // not (the old sequence goes on) shows the jump was one corrupt seq, which implies nothing.
    // last_seq is still the edge before the jump (nothing moves it while a jump is pending).
    const int64_t after_jump = saturating_sub(seq, gap_seq);
    const int64_t jump = saturating_sub(gap_seq, last_seq);
    gap_seq = kNone;
    if (after_jump > 0 && after_jump <= kMaxSeqGap) {
      last_seq = seq;
      return (jump - 1) + (after_jump - 1);
    }
  }
  const int64_t ahead = saturating_sub(seq, last_seq);
  if (ahead == 1) {
    last_seq = seq;
    return 0;
  }
  if (ahead > 1 && ahead - 1 <= kMaxSeqGap) {
    gap_seq = seq;  // counted when the next number confirms it
    return 0;
  }
  // Out-of-order (older) numbers do not move the edge back: recorder playback interleaves.
  // A jump beyond kMaxSeqGap either way is a counter reset: a new edge, nothing missing.
  if (ahead > kMaxSeqGap || ahead < -kMaxSeqGap) last_seq = seq;
  return 0;
}

bool ReceivedSpacecraft::on_time_base(int64_t utime, int64_t max_time_jump_utime) const {
  return newest_utime != kNoTime && utime <= saturating_add(newest_utime, max_time_jump_utime);
}

int64_t ReceivedSpacecraft::corroborated_utime(int64_t max_time_jump_utime) const {
  if (held.size() < static_cast<size_t>(kCorroborating) + 1) return kNoTime;
  const HeldSample& latest = held.back();
  int members = 0;
  bool several_frames = false;
  int64_t newest = kNoTime;
  for (const auto& h : held) {
    const int64_t d = saturating_sub(h.sample.utime, latest.sample.utime);
    if (d > max_time_jump_utime || d < -max_time_jump_utime) continue;
    ++members;  // distinct times: a repeated time is rejected as a duplicate before holding
    several_frames = several_frames || h.frame != latest.frame;
    newest = std::max(newest, h.sample.utime);
  }
  if (members < kCorroborating + 1 || !several_frames) return kNoTime;
  return newest;
}

int64_t ReceivedSpacecraft::likeliest_held_utime(int64_t max_time_jump_utime) const {
  // Quadratic in the hold (at most kHeldCapacity), run once per spacecraft that needs it.
  int best_members = 0;
  int64_t best = kNoTime;
  for (const auto& c : held) {
    int members = 0;
    int64_t newest = kNoTime;
    for (const auto& h : held) {
      const int64_t d = saturating_sub(h.sample.utime, c.sample.utime);
      if (d > max_time_jump_utime || d < -max_time_jump_utime) continue;
      ++members;
      newest = std::max(newest, h.sample.utime);
    }
    if (members > best_members || (members == best_members && newest > best)) {
      best_members = members;
      best = newest;
    }
  }
  return best;
}

void ReceivedSpacecraft::hold(const mag_sample_t& s, int64_t receive_utime, int64_t frame) {
  HeldSample& h = held.emplace_back();
  // Field by field: the sat_id (possibly long) is the tracker's and is not copied.
  h.sample.utime = s.utime;
  h.sample.seq = s.seq;
  for (int i = 0; i < 3; ++i) h.sample.b_sensor_nT[i] = s.b_sensor_nT[i];
  h.sample.has_position = s.has_position;
  for (int i = 0; i < 3; ++i) h.sample.r_ecef_m[i] = s.r_ecef_m[i];
  h.sample.has_attitude = s.has_attitude;
  for (int i = 0; i < 4; ++i) h.sample.q_body_from_eci[i] = s.q_body_from_eci[i];
  h.sample.has_reference = s.has_reference;
  for (int i = 0; i < 3; ++i) h.sample.h_body_nT[i] = s.h_body_nT[i];
  h.sample.temperature_C = s.temperature_C;
  h.receive_utime = receive_utime;
  h.frame = frame;
  h.advances_at_hold = advances;
}

bool ReceivedSpacecraft::holds_utime(int64_t utime) const {
  for (const auto& h : held) {
    if (h.sample.utime == utime) return true;
  }
  return false;
}

SpacecraftTracker* SpacecraftFleet::find(const std::string& sat_id) {
  const auto it = trackers_.find(sat_id);
  return it == trackers_.end() ? nullptr : &it->second;
}

SpacecraftTracker& SpacecraftFleet::get(const std::string& sat_id, bool* created) {
  auto [it, inserted] = trackers_.try_emplace(sat_id, options_);
  if (inserted && counters_ != nullptr) {
    SpacecraftCounters* c = &counters_->spacecraft.spacecraft(sat_id);
    static_cast<ReceivedSpacecraft&>(it->second).counters = c;
    static_cast<OwnedSpacecraft&>(it->second).counters = c;
    counters_->n_spacecraft.store(static_cast<int32_t>(trackers_.size()));
  }
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
