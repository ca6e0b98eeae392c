// The refit thread's queue (service/daemon/refit/refit_thread.hpp) without LCM or a database:
// each request runs once and in order, the retention floor holds the oldest due window until
// its refit ran, a replay's request waits for its refit, a stop with drain finishes the queue
// and one without only the running refit.
#include <catch2/catch.hpp>

#include <chrono>
#include <condition_variable>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "service/daemon/refit/refit_thread.hpp"

using magcal::RefitRequest;
using magcal::RefitThread;
using magcal::storage::RefitTrigger;

namespace {

constexpr int64_t kWindow_utime = 100;
constexpr int64_t kNoFloor = std::numeric_limits<int64_t>::max();
constexpr auto kDeadline = std::chrono::seconds(10);

// What the thread called, and a gate that holds each refit until the test lets it finish.
class Recorder {
 public:
  RefitThread::Links links(bool reached = true) {
    return {[reached] { return reached; },
            [this] {
              std::lock_guard lock(mutex_);
              state_.before_first_calls++;
              cv_.notify_all();
            },
            [this](const RefitRequest& req) { run(req); },
            [this](int64_t floor_utime) {
              std::lock_guard lock(mutex_);
              state_.floors.push_back(floor_utime);
            }};
  }
  // Lets `n` refits (the running one or later ones) finish.
  void release(int n) {
    std::lock_guard lock(mutex_);
    permits_ += n;
    cv_.notify_all();
  }
  // Waits until `n` refits have started; false past the deadline.
  bool wait_started(size_t n) {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, kDeadline, [&] { return state_.started.size() >= n; });
  }
  // What the thread called so far.
  struct State {
    std::vector<RefitRequest> started;
    size_t finished = 0;
    std::vector<int64_t> floors;  // each retention floor it set, in order
    int before_first_calls = 0;
    bool ran_before_first = false;  // a refit started before before_first
  };
  State state() {
    std::lock_guard lock(mutex_);
    return state_;
  }

 private:
  void run(const RefitRequest& req) {
    std::unique_lock lock(mutex_);
    // The database part (before_first) comes first.
    if (state_.before_first_calls != 1) state_.ran_before_first = true;
    state_.started.push_back(req);
    cv_.notify_all();
    cv_.wait(lock, [this] { return permits_ > 0; });
    --permits_;
    ++state_.finished;
  }

  std::mutex mutex_;
  std::condition_variable cv_;
  int permits_ = 0;
  State state_;
};

RefitThread::Settings data_clock(bool replay = false) {
  return {kWindow_utime, /*wall_schedule=*/std::nullopt, replay};
}

}  // namespace

TEST_CASE("a request is run once, as asked", "[refit_thread]") {
  Recorder rec;
  rec.release(1);
  RefitThread refits(data_clock(), rec.links());
  std::thread thread([&] { refits.run(); });
  refits.request("SAT-A", 5000, RefitTrigger::kFirst);
  REQUIRE(rec.wait_started(1));
  refits.stop(/*drain=*/true);
  thread.join();
  const auto started = rec.state().started;
  REQUIRE(started.size() == 1);
  CHECK(started[0].sat_id == "SAT-A");
  REQUIRE(started[0].t_ref_utime.has_value());
  CHECK(*started[0].t_ref_utime == 5000);
  CHECK(started[0].scheduled_utime == 5000);
  CHECK(started[0].trigger == RefitTrigger::kFirst);
  CHECK(rec.state().finished == 1);
  CHECK(rec.state().before_first_calls == 1);
  CHECK_FALSE(rec.state().ran_before_first);
}

TEST_CASE("the retention floor holds the oldest due window until its refit ran", "[refit_thread]") {
  Recorder rec;
  RefitThread refits(data_clock(), rec.links());
  std::thread thread([&] { refits.run(); });
  refits.request("SAT-A", 1000, RefitTrigger::kScheduled);
  REQUIRE(rec.wait_started(1));  // A runs (held by the gate); B waits in the queue
  refits.request("SAT-B", 500, RefitTrigger::kEarly);
  CHECK(refits.queued() == 1);
  rec.release(1);  // A finishes: B's older window still holds the floor
  REQUIRE(rec.wait_started(2));
  rec.release(1);  // B finishes: nothing is due, nothing held
  refits.stop(/*drain=*/true);
  thread.join();
  // Each change, in order: A's window start, then B's (older), again after A ran, none.
  CHECK(rec.state().floors == std::vector<int64_t>{1000 - kWindow_utime + 1,
                                                   500 - kWindow_utime + 1, 500 - kWindow_utime + 1,
                                                   kNoFloor});
}

TEST_CASE("a replay's request returns once its refit has run", "[refit_thread]") {
  Recorder rec;
  RefitThread refits(data_clock(/*replay=*/true), rec.links());
  std::thread thread([&] { refits.run(); });
  // The refit finishes only when this helper lets it, after it has started: a request() that
  // returned before its refit ran would find none finished.
  bool started = false;
  std::thread releaser([&] {
    started = rec.wait_started(1);
    rec.release(1);
  });
  refits.request("SAT-A", 1000, RefitTrigger::kScheduled);
  CHECK(rec.state().finished == 1);
  releaser.join();
  CHECK(started);
  refits.stop(/*drain=*/false);
  thread.join();
}

TEST_CASE("a stop with drain runs every queued request, one without only the running one",
          "[refit_thread]") {
  const bool drain = GENERATE(true, false);
  CAPTURE(drain);
  Recorder rec;
  RefitThread refits(data_clock(), rec.links());
  std::thread thread([&] { refits.run(); });
  refits.request("SAT-A", 1000, RefitTrigger::kScheduled);
  REQUIRE(rec.wait_started(1));
  refits.request("SAT-B", 2000, RefitTrigger::kScheduled);
  refits.request("SAT-C", 3000, RefitTrigger::kScheduled);
  REQUIRE(refits.queued() == 2);
  refits.stop(drain);
  rec.release(3);
  thread.join();
  std::vector<std::string> sats;
  for (const auto& r : rec.state().started) sats.push_back(r.sat_id);
  if (drain) {
    CHECK(sats == std::vector<std::string>{"SAT-A", "SAT-B", "SAT-C"});
    CHECK(refits.queued() == 0);
  } else {
    CHECK(sats == std::vector<std::string>{"SAT-A"});
    CHECK(refits.queued() == 2);  // left (and logged as not run)
  }
}

TEST_CASE("nothing runs before the database was reached, and a stop then ends the thread",
          "[refit_thread]") {
  Recorder rec;
  RefitThread refits(data_clock(), rec.links(/*reached=*/false));
  std::thread thread([&] { refits.run(); });
  refits.request("SAT-A", 1000, RefitTrigger::kScheduled);
  refits.stop(/*drain=*/true);
  thread.join();
  CHECK(rec.state().started.empty());
  CHECK(rec.state().before_first_calls == 0);
}
