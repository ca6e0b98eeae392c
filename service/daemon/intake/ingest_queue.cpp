#include "service/daemon/intake/ingest_queue.hpp"

#include <chrono>

namespace magcal {

bool IngestQueue::push(IngestItem&& item) {
  const auto n = static_cast<int64_t>(item.samples.size());
  std::unique_lock lock(mutex_);
  if (block_) {
    // An item larger than the whole queue is still admitted into an empty queue.
    not_full_.wait(lock, [&] { return closed_ || depth_ == 0 || depth_ + n <= capacity_; });
  }
  if (closed_) return false;
  if (depth_ > 0 && depth_ + n > capacity_) {
    overflow_ += n;
    return false;
  }
  depth_ += n;
  items_.push_back(std::move(item));
  lock.unlock();
  not_empty_.notify_one();
  return true;
}

bool IngestQueue::pop_all(std::vector<IngestItem>& out, int timeout_ms) {
  std::unique_lock lock(mutex_);
  not_empty_.wait_for(lock, std::chrono::milliseconds(timeout_ms),
                      [&] { return closed_ || !items_.empty(); });
  if (items_.empty()) return !closed_;
  for (auto& item : items_) out.push_back(std::move(item));
  items_.clear();
  depth_ = 0;
  lock.unlock();
  not_full_.notify_all();
  return true;
}

void IngestQueue::close() {
  {
    std::lock_guard lock(mutex_);
    closed_ = true;
  }
  not_empty_.notify_all();
  not_full_.notify_all();
}

int64_t IngestQueue::depth_samples() const {
  std::lock_guard lock(mutex_);
  return depth_;
}

int64_t IngestQueue::overflow_samples() const {
  std::lock_guard lock(mutex_);
  return overflow_;
}

}  // namespace magcal
