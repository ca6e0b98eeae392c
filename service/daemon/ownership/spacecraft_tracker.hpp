// Per-spacecraft online state held by the daemon's worker, in two halves: what the receiving
// station keeps (ReceivedSpacecraft: the newest accepted sample time, the spacecraft's window
// edge in data time; the last sequence number, gaps count as missing samples; the samples held
// while their time is uncorroborated) and what the owner keeps (OwnedSpacecraft: the UKF,
// estimation.md section 3, the next snapshot time, the refit schedule, the lease). A spacecraft
// appears on its first valid frame. Size is what the memory target counts (design.md: < 4 KB per
// spacecraft; held samples only while held).
//
// Time plausibility (one frame must not move a spacecraft's time). The "time base" is
// newest_utime, the newest ACCEPTED sample; retention, the data clock and the UKF only ever see
// accepted samples. A valid sample is
//   on the base   when utime <= newest_utime + max_time_jump: it goes on to older_than_window /
//                 duplicate / store (older in-window samples are a recorder dump: accepted);
//   held          when it is further ahead, or when the spacecraft has no base yet (its first
//                 samples after a start with an empty database; a restart takes the base from
//                 the stored window).
// Held samples are resolved by what comes next:
//   corroborated  the newest held sample has kCorroborating others (distinct times) within
//                 max_time_jump of it, and they came in more than one frame (so one frame, even
//                 a whole mag_batch_t of consistently shifted samples, cannot set the time
//                 alone: a downlink packet with a corrupted time base is one frame). The base
//                 moves to the newest of them and every held sample is re-examined in arrival
//                 order (stored, rejected older_than_window, or held on).
//   contradicted  kCorroborating accepted samples advanced the old base after it was held:
//                 rejected as time_jump. A sample the old base has caught up with (within
//                 max_time_jump of it again) is accepted instead.
//   displaced     the hold is full: the oldest held sample is rejected as time_jump.
//   no base yet   a new spacecraft that sends too little to corroborate itself (one frame, or
//                 fewer than kCorroborating + 1 samples): nothing contradicts its samples, so
//                 after kFirstHoldMax_s of wall time (SampleIntake::release_first_holds), or at
//                 shutdown, the base is taken from them (likeliest_held_utime) and they are
//                 stored. A lone rogue among them is still outvoted.
//   shutdown      (with a base) rejected as time_jump_unconfirmed (SampleIntake::settle_held),
//                 never lost silently; a replay can re-send them. Storing them would let one
//                 frame move the stored time base, which a restart then starts from.
// Samples far in the past need no hold: they never move the base (older_than_window beyond it).
#pragma once

#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "pipeline/calibration_result.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/temperature_correction.hpp"
#include "schemas/magcal_messages.hpp"
#include "service/io/calibration_record.hpp"
#include "service/refit/refit_scheduler.hpp"

namespace magcal {

struct SpacecraftCounters;
struct DaemonCounters;

// A sample waiting for corroboration of its time (its sat_id is the tracker's, left empty).
struct HeldSample {
  mag_sample_t sample;
  int64_t receive_utime = 0;
  int64_t frame = 0;             // the worker's frame counter when it arrived
  int64_t advances_at_hold = 0;  // SpacecraftTracker::advances when it was held
};

// Missing samples implied by a stream's seq numbers: a forward gap counts once the following
// number confirms it (continues after the gap), so one corrupt seq implies nothing;
// out-of-order or repeated numbers, and jumps larger than kMaxSeqGap (a counter reset), imply
// none. A gap at the very end of a stream (never confirmed) is not counted.
struct SeqGapCounter {
  static constexpr int64_t kNone = std::numeric_limits<int64_t>::min();
  static constexpr int64_t kMaxSeqGap = 1'000'000;
  int64_t last_seq = kNone;  // none yet
  int64_t gap_seq = kNone;   // after an unconfirmed gap; none
  // The missing samples `seq` confirms; advances last_seq.
  int64_t observe(int64_t seq);
};

// What every station keeps of a spacecraft it receives (SampleIntake, sample_intake.hpp): its
// time base, the duplicate bound, the received seq numbers, the held samples and what its
// retention may delete. Only the intake writes these fields.
struct ReceivedSpacecraft {
  static constexpr int64_t kNoTime = std::numeric_limits<int64_t>::min();
  static constexpr int kCorroborating = 3;  // further samples that confirm or refute a time
  // Per spacecraft: room for a whole downlink packet (mag_batch_t stays under ~400 samples,
  // toolchain.md) and the frames that corroborate it; ~200 KB only while samples are held.
  static constexpr int kHeldCapacity = 1024;
  // A new spacecraft's first samples wait at most this long (wall time) for corroboration.
  static constexpr double kFirstHoldMax_s = 10.0;

  int64_t newest_utime = kNoTime;  // newest accepted sample (the time base); none yet
  // Newest time stored (restored) or pending for it: a sample after it is no duplicate.
  int64_t stored_bound_utime = kNoTime;
  // Seq gaps of the samples this station received (counted missing while it is the only live
  // station; in a fleet the owner counts the union's: OwnedSpacecraft::union_seq).
  SeqGapCounter received_seq;
  int64_t advances = 0;  // accepted samples that moved newest_utime forward
  // Wall time this station last received a valid sample of it (kNoTime: never): the owner side
  // prefers the spacecraft this station receives (decide_lease_round()).
  int64_t received_wall_utime = kNoTime;
  // Retention (SampleIntake::run_retention): the owner's filter time while this daemon owns
  // the spacecraft (kNoTime: not owned here, nothing is deleted), and a lower bound of what
  // is stored (kNoTime: unknown): a cutoff at or below it has nothing to delete.
  int64_t retention_edge_utime = kNoTime;
  int64_t retained_from_utime = kNoTime;
  bool retention_due = false;              // its edge advanced since the last retention pass
  std::vector<HeldSample> held;            // arrival order; at most kHeldCapacity, freed when empty
  SpacecraftCounters* counters = nullptr;  // its counters (DaemonCounters::spacecraft)

  // True when a sample at `utime` is on the time base (see the file comment), false when it
  // must be held. `utime` is plausible (pipeline/time_utc.hpp).
  bool on_time_base(int64_t utime, int64_t max_time_jump_utime) const;
  // The newest time of the held samples that corroborate the newest held one, or kNoTime while
  // they do not (yet).
  int64_t corroborated_utime(int64_t max_time_jump_utime) const;
  // For a spacecraft without a base: the newest time of the largest group of held samples
  // within max_time_jump of one another (ties: the newest group); kNoTime when nothing is held.
  int64_t likeliest_held_utime(int64_t max_time_jump_utime) const;
  // Copies `s` into the hold (sat_id left empty); the caller makes room first.
  void hold(const mag_sample_t& s, int64_t receive_utime, int64_t frame);
  bool holds_utime(int64_t utime) const;
  // A valid sample of it was received here at or after this wall time.
  bool received_since(int64_t wall_utime) const {
    return received_wall_utime != kNoTime && received_wall_utime >= wall_utime;
  }
};

// What the holder of a spacecraft's lease keeps of it (OwnedSpacecraftTracker,
// owned_spacecraft_tracker.hpp): the UKF over the union of all stations' stored samples, its
// snapshots, refit triggers and lease. Only the tracker writes these fields; on a daemon that
// does not own the spacecraft they stay at rest (owned false, a fresh filter).
struct OwnedSpacecraft {
  static constexpr int64_t kNoTime = std::numeric_limits<int64_t>::min();

  // `options`: the fleet's one copy (a filter's options are not per spacecraft).
  explicit OwnedSpacecraft(std::shared_ptr<const MagnetometerUkf::Options> options)
      : ukf(std::move(options)) {}

  MagnetometerUkf ukf;
  TemperatureCorrection temperature;  // of the refit anchor_calibration_id names
  // Seq gaps of the union the owner reads (counted missing in a fleet: a gap is missing only
  // when no station delivered the sample).
  SeqGapCounter union_seq;
  int64_t next_snapshot_utime = kNoTime;
  bool state_dirty = false;  // filter changed since its state was last written
  // A snapshot or a re-anchor changed what the filter means: its state goes into the next
  // commit, with the samples it includes (OwnedSpacecraftTracker::states_due_).
  bool state_due = false;
  int64_t anchor_calibration_id = 0;  // the refit it was last re-anchored on (0: none)
  // [refit] clock = "data": this spacecraft's scheduled refits, on its own data time (its
  // filter's time): a spacecraft backfilled behind the others gets the refits of its own days.
  std::optional<RefitScheduler> data_refits;
  // Early refits (EarlyRefitPlan, OwnedSpacecraftTracker::early_refit()): stored samples of
  // all stations the owner's filter has taken (at a takeover: the stored count up to its
  // state), and the count at which the next one is due (0 = none: its data span window_hours,
  // the schedule's business from then on).
  int64_t n_samples = 0;
  int64_t next_early_refit_samples = 0;

  bool owned = false;
  int64_t lease_epoch = 0;
  // The owner's filter has taken every stored sample up to this time (kNoTime: none yet); a
  // sample stored later with an older time is late for it (refits still use it).
  int64_t filtered_utime = kNoTime;
  // The newest stored time of any station seen by the owner, and when (wall) it last grew: the
  // union's reorder horizon.
  int64_t union_newest_utime = kNoTime;
  int64_t union_grew_wall_utime = 0;
  bool union_due = false;  // this station stored new samples: the owner reads the union now
  // An accepted refit the taken-over state lacks, applied once the filter passes its time.
  int64_t deferred_reanchor_id = 0;
  int64_t deferred_reanchor_utime = kNoTime;
  SpacecraftCounters* counters = nullptr;  // its counters (DaemonCounters::spacecraft)

  // The UKF update of one stored sample, temperature-corrected; false when the filter may not
  // use it (TemperatureCorrection).
  bool update_filter(const CalibrationSample& s) {
    Eigen::Vector3d b_sensor_nT;
    if (!temperature.correct(s, b_sensor_nT)) return false;
    ukf.update(b_sensor_nT, reference_norm_nT(s), s.utime);
    return true;
  }
};

// One spacecraft in the daemon: what the intake keeps of it and what its owner keeps. Each
// part of the worker takes only its own half (IngestWorker, ingest_worker.hpp).
struct SpacecraftTracker : ReceivedSpacecraft, OwnedSpacecraft {
  using ReceivedSpacecraft::kNoTime;
  explicit SpacecraftTracker(std::shared_ptr<const MagnetometerUkf::Options> options)
      : OwnedSpacecraft(std::move(options)) {}
};

// Every spacecraft this daemon receives or owns. Shared by the worker's two parts (one thread).
class SpacecraftFleet {
 public:
  // `counters`: the daemon's (nullptr: none, e.g. a memory benchmark of the trackers alone).
  explicit SpacecraftFleet(const MagnetometerUkf::Options& options,
                           DaemonCounters* counters = nullptr)
      : options_(std::make_shared<const MagnetometerUkf::Options>(options)), counters_(counters) {}

  // The filters' options, one copy shared by every spacecraft's UKF (memory per spacecraft).
  const std::shared_ptr<const MagnetometerUkf::Options>& options() const { return options_; }

  SpacecraftTracker* find(const std::string& sat_id);
  // Creates the tracker on first use (its counters looked up once, here: the per-sample path
  // uses the cached pointer; DaemonCounters::n_spacecraft follows); `created` (optional) tells
  // whether it did.
  SpacecraftTracker& get(const std::string& sat_id, bool* created = nullptr);
  size_t size() const { return trackers_.size(); }

  template <typename F>
  void for_each(F&& f) {
    for (auto& [sat, t] : trackers_) f(sat, t);
  }

  // Approximate resident bytes per spacecraft: the tracker, the map node and bucket share.
  static size_t approx_bytes_per_spacecraft();

 private:
  std::shared_ptr<const MagnetometerUkf::Options> options_;
  DaemonCounters* counters_;
  std::unordered_map<std::string, SpacecraftTracker> trackers_;
};

}  // namespace magcal
