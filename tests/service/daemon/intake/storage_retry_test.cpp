// StorageRetry: transient storage errors are retried with bounded exponential backoff while the
// daemon reports storage unhealthy; permanent errors and outages past max_failure_s end in
// StorageOutage (the daemon's exit 3), and so do failures past a stop's deadline.
#include "service/daemon/intake/storage_retry.hpp"

#include <catch2/catch.hpp>

using magcal::DaemonCounters;
using magcal::StorageOutage;
using magcal::StorageRetry;
using magcal::storage::StorageError;

namespace {

using Condition = StorageError::Condition;
constexpr Condition kBusy = Condition::kBusy;
constexpr Condition kDiskFull = Condition::kDiskFull;
constexpr Condition kCorrupt = Condition::kCorrupt;

// Conditions, as each backend maps its own codes (storage/storage_error.cpp).
StorageError injected_error(Condition condition) {
  return StorageError(StorageError::Kind::kEngine, "injected", condition);
}

// Runs an operation that is always busy until `retry` gives up: its StorageOutage's message.
std::string outage_when_busy(StorageRetry& retry, int& calls) {
  try {
    retry.run_blocking([&] {
      ++calls;
      throw injected_error(kBusy);
    });
  } catch (const StorageOutage& e) {
    return e.what();
  }
  FAIL("no StorageOutage");
  return "";
}

}  // namespace

TEST_CASE("transient errors are retried with backoff until the operation succeeds",
          "[storage_retry]") {
  DaemonCounters counters;
  StorageRetry retry("commit", 10.0, counters);
  int calls = 0;
  const auto t0 = StorageRetry::Clock::now();
  const int result = retry.run_blocking([&] {
    ++calls;
    if (calls <= 3) throw injected_error(calls == 2 ? kDiskFull : kBusy);
    CHECK_FALSE(counters.storage_healthy());  // unhealthy while it is failing
    return 42;
  });
  const double waited_s = std::chrono::duration<double>(StorageRetry::Clock::now() - t0).count();
  CHECK(result == 42);
  CHECK(calls == 4);
  CHECK(counters.storage_failures.load() == 3);
  CHECK(counters.storage_retries.load() == 3);
  CHECK(counters.storage_healthy());
  CHECK_FALSE(retry.failing());
  // Backoff 0.05 + 0.1 + 0.2 s between the attempts.
  CHECK(waited_s >= 0.35);
  CHECK(waited_s < 5.0);
}

TEST_CASE("a permanent error ends in StorageOutage at once", "[storage_retry]") {
  DaemonCounters counters;
  StorageRetry retry("commit", 10.0, counters);
  int calls = 0;
  CHECK_THROWS_AS(retry.run_blocking([&] {
    ++calls;
    throw injected_error(kCorrupt);
  }),
                  StorageOutage);
  CHECK(calls == 1);
  CHECK_FALSE(counters.storage_healthy());
}

TEST_CASE("an outage longer than max_failure_s ends in StorageOutage on time", "[storage_retry]") {
  DaemonCounters counters;
  StorageRetry retry("commit", 0.5, counters);
  int calls = 0;
  const auto t0 = StorageRetry::Clock::now();
  CHECK_THAT(outage_when_busy(retry, calls), Catch::Contains("max_failure_s"));
  const double waited_s = std::chrono::duration<double>(StorageRetry::Clock::now() - t0).count();
  CHECK(waited_s >= 0.5);
  CHECK(waited_s < 1.5);  // the last retry is scheduled at the deadline, not past it
  CHECK(calls >= 4);      // 0.05, 0.1, 0.2, then the rest up to 0.5 s
  CHECK(counters.storage_failures.load() == calls);
}

TEST_CASE("a stop gives up at its deadline, whatever max_failure_s allows", "[storage_retry]") {
  DaemonCounters counters;
  magcal::StopDeadline stop;
  StorageRetry retry("commit", 3600.0, counters, "pg_max_failure_s", &stop);
  // Failing before the stop: retried as usual.
  retry.failed(injected_error(kBusy));
  CHECK(retry.failing());
  const auto t0 = StorageRetry::Clock::now();
  stop.start(0.3);
  CHECK(stop.at() > t0);
  int calls = 0;
  CHECK_THAT(outage_when_busy(retry, calls),
             Catch::Contains("after the stop ([storage] stop_max_failure_s = 0.3;"));
  const double waited_s = std::chrono::duration<double>(StorageRetry::Clock::now() - t0).count();
  CHECK(waited_s >= 0.3);
  CHECK(waited_s < 1.0);  // the last retry is scheduled at the deadline, not past the backoff
  CHECK(calls >= 2);
}

TEST_CASE("the non-blocking form schedules the next attempt and clears health on success",
          "[storage_retry]") {
  DaemonCounters counters;
  {
    StorageRetry retry("commit", 10.0, counters);
    CHECK(retry.due());
    retry.failed(injected_error(kBusy));
    CHECK(retry.failing());
    CHECK_FALSE(retry.due());
    CHECK(retry.due(retry.next_attempt()));
    CHECK_FALSE(counters.storage_healthy());
    retry.attempting();
    retry.succeeded();
    CHECK(counters.storage_healthy());
    retry.failed(injected_error(kBusy));
    CHECK_FALSE(counters.storage_healthy());
  }
  // A path that goes away while failing does not leave the daemon unhealthy for ever.
  CHECK(counters.storage_healthy());
}
