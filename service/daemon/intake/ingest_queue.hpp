// The bounded hand-off between the LCM receive thread and the worker (design.md "Daemon data
// flow"). Capacity is counted in samples (a batch of 200 takes 200). When full, a live source
// drops the frame and counts every sample in it as overflow (never silent); a replay source
// (file://) blocks instead, because a log can wait and nothing should be lost.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <mutex>
#include <string>
#include <vector>

#include "schemas/magcal_messages.hpp"

namespace magcal {

// One decoded frame: a mag_sample_t (batch_sat_id empty) or a mag_batch_t's samples.
struct IngestItem {
  bool from_batch = false;
  std::string batch_sat_id;
  std::vector<mag_sample_t> samples;
  int64_t receive_utime = 0;  // wall clock when the frame arrived
};

class IngestQueue {
 public:
  explicit IngestQueue(int64_t capacity_samples, bool block_when_full = false)
      : capacity_(capacity_samples), block_(block_when_full) {}

  // false: the item was not queued. When the queue was full (and not blocking) its samples are
  // counted in overflow_samples(); when it was closed (magcald stops on a fatal error, and a
  // blocked replay push returns) they are not: the daemon counts what it received and did not
  // commit as storage_error, and that frame is such.
  bool push(IngestItem&& item);

  // Waits up to timeout_ms for items; moves everything queued into `out` (appended).
  // Returns false when the queue is closed and empty (the worker's signal to finish).
  bool pop_all(std::vector<IngestItem>& out, int timeout_ms);

  // No more pushes; pop_all drains what is left, then returns false.
  void close();

  int64_t depth_samples() const;
  int64_t capacity_samples() const { return capacity_; }
  int64_t overflow_samples() const;

 private:
  const int64_t capacity_;
  const bool block_;
  mutable std::mutex mutex_;
  std::condition_variable not_empty_;
  std::condition_variable not_full_;
  std::deque<IngestItem> items_;
  int64_t depth_ = 0;
  int64_t overflow_ = 0;
  bool closed_ = false;
};

}  // namespace magcal
