// The receive -> worker queue: bounded in samples, overflow counted (live) or blocking (replay),
// close() drains.
#include <catch2/catch.hpp>

#include <sys/types.h>
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <string>
#include <thread>

#include "service/daemon/intake/ingest_queue.hpp"
#include "tests/process_support.hpp"

using magcal::IngestItem;
using magcal::IngestQueue;

namespace {
IngestItem item(int n) {
  IngestItem it;
  it.samples.resize(static_cast<size_t>(n));
  return it;
}

// Whether thread `tid` of this process sleeps in the kernel (state S in /proc): a thread that
// only pushes to the queue sleeps when its push waits for room, and at no other point.
bool thread_sleeps(pid_t tid) {
  std::ifstream stat("/proc/self/task/" + std::to_string(tid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  const size_t name_end = text.rfind(')');  // the name may hold spaces and parentheses
  return name_end != std::string::npos && name_end + 2 < text.size() && text[name_end + 2] == 'S';
}
}  // namespace

TEST_CASE("a full live queue drops and counts every sample", "[ingest_queue]") {
  IngestQueue q(1000, false);
  CHECK(q.push(item(600)));
  CHECK(q.push(item(400)));
  CHECK(q.depth_samples() == 1000);
  CHECK_FALSE(q.push(item(200)));
  CHECK(q.overflow_samples() == 200);
  std::vector<IngestItem> out;
  REQUIRE(q.pop_all(out, 0));
  CHECK(out.size() == 2);
  CHECK(q.depth_samples() == 0);
  CHECK(q.push(item(200)));
  CHECK(q.overflow_samples() == 200);
}

TEST_CASE("an item larger than the capacity still enters an empty queue", "[ingest_queue]") {
  IngestQueue q(1000, false);
  CHECK(q.push(item(1500)));
  CHECK_FALSE(q.push(item(1)));
  CHECK(q.overflow_samples() == 1);
}

TEST_CASE("a replay queue blocks instead of dropping", "[ingest_queue]") {
  IngestQueue q(1000, true);
  REQUIRE(q.push(item(1000)));
  std::atomic<pid_t> producer_tid{0};
  std::atomic<int> pushed{0};
  std::thread producer([&] {
    producer_tid = ::gettid();
    for (int i = 0; i < 10; ++i) pushed += q.push(item(500)) ? 1 : 0;
    q.close();
  });
  // The first push waits for room (the queue is full): nothing dropped while it does.
  REQUIRE(magcal::test::wait_until([&] { return producer_tid != 0 && thread_sleeps(producer_tid); },
                                   10));
  CHECK(pushed == 0);
  CHECK(q.depth_samples() == 1000);
  int64_t received = 0;
  std::vector<IngestItem> out;
  while (q.pop_all(out, 1000)) {
    for (const auto& it : out) received += static_cast<int64_t>(it.samples.size());
    out.clear();
  }
  producer.join();
  CHECK(received == 6000);
  CHECK(pushed == 10);
  CHECK(q.overflow_samples() == 0);
}

TEST_CASE("close drains, then pop_all reports the end, later pushes are refused, not overflow",
          "[ingest_queue]") {
  IngestQueue q(1000, false);
  q.push(item(3));
  q.close();
  std::vector<IngestItem> out;
  CHECK(q.pop_all(out, 0));
  CHECK(out.size() == 1);
  out.clear();
  CHECK_FALSE(q.pop_all(out, 0));
  // (magcald closes the queue when it stops on a fatal error: a frame pushed then was never
  // committed, and the daemon counts it so, as storage_error.)
  CHECK_FALSE(q.push(item(2)));
  CHECK(q.overflow_samples() == 0);
}

TEST_CASE("a replay push blocked on a full queue returns at close, not counted as overflow",
          "[ingest_queue]") {
  IngestQueue q(1000, true);
  REQUIRE(q.push(item(1000)));
  std::atomic<int> result{-1};
  std::atomic<pid_t> producer_tid{0};
  std::thread producer([&] {
    producer_tid = ::gettid();
    result = q.push(item(500)) ? 1 : 0;
  });
  // Blocked inside push before the close (a push begun after it would be refused all the same).
  REQUIRE(magcal::test::wait_until([&] { return producer_tid != 0 && thread_sleeps(producer_tid); },
                                   10));
  CHECK(result == -1);
  q.close();
  producer.join();
  CHECK(result == 0);
  CHECK(q.overflow_samples() == 0);
  CHECK(q.depth_samples() == 1000);
}
