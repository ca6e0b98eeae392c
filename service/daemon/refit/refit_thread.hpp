// magcald's refit thread and its queue. The worker asks for a refit when a spacecraft's data
// clock passes a scheduled time (or its first or an early refit is due); on the wall clock the
// thread's own timer asks for every spacecraft at the scheduled times. Requests run one at a
// time, in order, on the thread that calls run(); what running one means (the refit, its log
// line, the re-anchoring) is the caller's Links::run, so this class holds only the order, the
// waits and the retention floor.
//
// Retention floor: a due refit needs the samples of its window, which the worker's retention
// must not delete before the refit has read them. Each data-clock request holds its window
// start (t_ref - window + 1) until it has run; the floor is the oldest one held (INT64_MAX when
// none), given to Links::set_retention_floor each time it changes.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <optional>
#include <set>
#include <string>

#include "service/refit/refit_scheduler.hpp"
#include "storage/refit_job_log.hpp"

namespace magcal {

struct RefitRequest {
  std::string sat_id;                  // data clock: that spacecraft; "" (wall clock): every one
  std::optional<int64_t> t_ref_utime;  // nullopt: each spacecraft's newest sample (wall clock)
  int64_t scheduled_utime = 0;
  storage::RefitTrigger trigger = storage::RefitTrigger::kScheduled;
};

class RefitThread {
 public:
  struct Settings {
    int64_t window_utime = 0;  // the refit window: a request's floor is t_ref - window + 1
    // Wall clock: the schedule of the thread's own timer; nullopt: the data clock (requests
    // from the worker only).
    std::optional<RefitSchedule> wall_schedule;
    // A replay's request() waits until the refit has run: a replay has no live source to fall
    // behind, and its re-anchoring then lands at the same point of the data every time
    // (deterministic backfill). Live ingestion never waits for refits.
    bool replay = false;
  };
  // What the thread calls; each from run()'s thread, set_retention_floor also from request()'s
  // (under the queue's lock, so floors arrive in order).
  struct Links {
    // The database was reached (the worker restored from it): nothing runs before.
    std::function<bool()> database_reached;
    // Once, after the database was reached and before the first request.
    std::function<void()> before_first;
    std::function<void(const RefitRequest&)> run;
    std::function<void(int64_t floor_utime)> set_retention_floor;
  };

  RefitThread(Settings settings, Links links);

  // The worker thread: a refit of sat's window ending at t_ref is due and its samples are
  // committed. In a replay, returns once the queue is empty and idle (or at a stop).
  void request(const std::string& sat_id, int64_t t_ref_utime, storage::RefitTrigger trigger);

  // The thread's body: runs requests (and the wall-clock schedule) until stop(). Returns at
  // once if stopped before the database was reached. Exceptions of Links::run escape.
  void run();

  // Ends run(): with `drain`, after the queued requests have run (a replay's end); without,
  // after the running one (a signal, a fatal error). Any thread; a later call overrides the
  // drain. Wakes a replay's request().
  void stop(bool drain);

  size_t queued() const;  // requests waiting (not the running one)

 private:
  int64_t floor_of(const RefitRequest& req) const;
  void publish_floor_locked();
  // Runs one request (popped under `lock`, which is released while it runs).
  void run_one_locked(std::unique_lock<std::mutex>& lock);

  const Settings settings_;
  const Links links_;

  mutable std::mutex mutex_;
  std::condition_variable wake_cv_;  // a request or a stop
  std::condition_variable idle_cv_;  // the queue emptied, or a stop
  std::deque<RefitRequest> queue_;
  std::multiset<int64_t> floors_;  // window starts of due, unfinished refits
  bool busy_ = false;
  bool stop_ = false;
  bool drain_ = false;
};

}  // namespace magcal
