#include "service/daemon/refit/refit_thread.hpp"

#include <algorithm>
#include <chrono>
#include <limits>
#include <utility>

#include <spdlog/spdlog.h>

#include "pipeline/time_utc.hpp"

namespace magcal {

RefitThread::RefitThread(Settings settings, Links links)
    : settings_(std::move(settings)), links_(std::move(links)) {}

int64_t RefitThread::floor_of(const RefitRequest& req) const {
  return *req.t_ref_utime - settings_.window_utime + 1;
}

void RefitThread::publish_floor_locked() {
  links_.set_retention_floor(floors_.empty() ? std::numeric_limits<int64_t>::max()
                                             : *floors_.begin());
}

void RefitThread::request(const std::string& sat_id, int64_t t_ref_utime,
                          storage::RefitTrigger trigger) {
  std::unique_lock lock(mutex_);
  RefitRequest req{sat_id, t_ref_utime, t_ref_utime, trigger};
  floors_.insert(floor_of(req));
  publish_floor_locked();
  queue_.push_back(std::move(req));
  wake_cv_.notify_one();
  if (settings_.replay) {
    idle_cv_.wait(lock, [this] { return (queue_.empty() && !busy_) || stop_; });
  }
}

void RefitThread::stop(bool drain) {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
    drain_ = drain;
  }
  wake_cv_.notify_all();
  idle_cv_.notify_all();
}

size_t RefitThread::queued() const {
  std::lock_guard lock(mutex_);
  return queue_.size();
}

void RefitThread::run_one_locked(std::unique_lock<std::mutex>& lock) {
  const RefitRequest req = queue_.front();
  queue_.pop_front();
  busy_ = true;
  lock.unlock();
  links_.run(req);  // what escapes ends the process, whose fail() calls stop()
  lock.lock();
  busy_ = false;
  if (req.t_ref_utime) {
    if (const auto it = floors_.find(floor_of(req)); it != floors_.end()) floors_.erase(it);
    publish_floor_locked();
  }
  idle_cv_.notify_all();
}

void RefitThread::run() {
  const auto& schedule = settings_.wall_schedule;
  int64_t next_wall = schedule ? next_scheduled_utime(*schedule, now_utime()) : 0;
  if (schedule) spdlog::info("next scheduled refit {}", format_iso8601_utc(next_wall));
  std::unique_lock lock(mutex_);
  // Nothing before the worker reached the database (unreachable at start: a stop meanwhile
  // must not wait for it here), and then whatever must precede the first refit (the jobs an
  // earlier run left running are ended, so that none of this run's is taken for one).
  while (!links_.database_reached() && !stop_) {
    wake_cv_.wait_for(lock, std::chrono::milliseconds(200));
  }
  if (!links_.database_reached()) return;
  lock.unlock();
  links_.before_first();
  lock.lock();
  while (true) {
    if (!queue_.empty() && !(stop_ && !drain_)) {
      run_one_locked(lock);
      continue;
    }
    if (stop_) break;
    if (schedule && now_utime() >= next_wall) {
      queue_.push_back({"", std::nullopt, next_wall});
      next_wall = next_scheduled_utime(*schedule, now_utime());
      continue;
    }
    const auto wait_ms =
        schedule ? std::clamp<int64_t>((next_wall - now_utime()) / 1000, 1, 1000) : int64_t{1000};
    wake_cv_.wait_for(lock, std::chrono::milliseconds(wait_ms));
  }
  if (!queue_.empty()) {
    spdlog::warn("{} scheduled refit(s) not run: shutting down", queue_.size());
  }
}

}  // namespace magcal
