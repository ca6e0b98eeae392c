// refit_jobs table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): lifecycle,
// crash recovery, foreign key to calibrations, the fleet's claims (alone and raced).
#include "storage/refit_job_log.hpp"

#include <algorithm>
#include <atomic>
#include <catch2/catch.hpp>
#include <chrono>
#include <numeric>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "storage/calibration_history.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

using SteadyClock = std::chrono::steady_clock;

// When a call was in flight.
struct ClaimSpan {
  SteadyClock::time_point begin;
  SteadyClock::time_point end;
};

// A calibrations row of SAT1 for a job to link to.
int64_t add_calibration(Connection& db) {
  CalibrationRecord r;
  r.sat_id = "SAT1";
  r.method = "twostep";
  return db.make_calibration_history()->append(r);
}

}  // namespace

TEMPLATE_TEST_CASE_METHOD(BackendTest, "a refit job runs, finishes and links its calibration",
                          "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  const int64_t id = jobs->start("SAT1", "scheduled", 1000, 1005);
  auto job = jobs->get(id);
  REQUIRE(job.has_value());
  CHECK(job->outcome == job_outcome::kRunning);
  CHECK(job->started_utime == 1005);
  CHECK_FALSE(job->finished_utime.has_value());
  CHECK_FALSE(job->calibration_id.has_value());

  const int64_t cal = add_calibration(*this->db);
  jobs->finish(id, job_outcome::kOk, 2000, "", cal);
  job = jobs->get(id);
  CHECK(job->outcome == "ok");
  CHECK(job->finished_utime == 2000);
  CHECK(job->calibration_id == cal);
  CHECK(job->trigger == "scheduled");
  CHECK(job->scheduled_utime == 1000);

  const int64_t failed = jobs->start("SAT1", "manual", 3000, 3000);
  jobs->finish(failed, job_outcome::kFailed, 3100, "too few samples: 12 < 1000");
  CHECK(jobs->latest("SAT1")->id == failed);
  CHECK(jobs->latest("SAT1")->error == "too few samples: 12 < 1000");
  CHECK(jobs->recent("SAT1", 10).size() == 2);
  CHECK_FALSE(jobs->latest("SAT2").has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest, "unknown job ids and dangling calibration ids are refused",
                          "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  CHECK_THROWS_AS(jobs->finish(999, job_outcome::kOk, 1), StorageError);
  const int64_t id = jobs->start("SAT1", "manual", 1, 1);
  CHECK_THROWS_AS(jobs->finish(id, job_outcome::kOk, 2, "", int64_t{12345}), StorageError);
  CHECK(jobs->get(id)->outcome == "running");
}

TEMPLATE_TEST_CASE_METHOD(
    BackendTest,
    "what a restart resumes from: the newest daemon refit accepted, the last scheduled run",
    "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  auto job = [&](const char* trigger, int64_t due, const char* outcome) {
    const int64_t id = jobs->start("SAT1", trigger, due, due);
    const bool stored =
        std::string(outcome) == job_outcome::kOk || std::string(outcome) == job_outcome::kRejected;
    const int64_t cal = stored ? add_calibration(*this->db) : 0;
    if (std::string(outcome) != job_outcome::kRunning)
      jobs->finish(id, outcome, due + 1, "", stored ? std::optional<int64_t>(cal) : std::nullopt);
    return cal;
  };
  CHECK_FALSE(jobs->newest_reanchor_calibration_id("SAT1").has_value());
  CHECK_FALSE(jobs->newest_finished_scheduled_utime("SAT1").has_value());
  const int64_t first = job("first", 100, job_outcome::kOk);
  job("scheduled", 200, job_outcome::kSkipped);
  CHECK(jobs->newest_reanchor_calibration_id("SAT1") == first);
  CHECK(jobs->newest_finished_scheduled_utime("SAT1") == 200);
  const int64_t scheduled = job("scheduled", 300, job_outcome::kOk);
  job("scheduled", 400, job_outcome::kRejected);
  job("manual", 450, job_outcome::kOk);  // the daemon never re-anchors on `magcal refit`
  job("scheduled", 500, job_outcome::kRunning);
  CHECK(jobs->newest_reanchor_calibration_id("SAT1") == scheduled);
  CHECK(jobs->newest_finished_scheduled_utime("SAT1") == 400);
  jobs->mark_station_running_interrupted("station-A", 600);
  CHECK(jobs->newest_finished_scheduled_utime("SAT1") == 400);  // 500 runs again
  CHECK_FALSE(jobs->newest_reanchor_calibration_id("SAT2").has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a restarting daemon interrupts the jobs it left running, not another "
                          "station's",
                          "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  const int64_t done = jobs->start("SAT1", "scheduled", 1, 2);
  jobs->finish(done, job_outcome::kOk, 3);
  const int64_t a = jobs->start("SAT1", "scheduled", 10, 11);
  const int64_t b = jobs->start("SAT2", "manual", 10, 12);
  const auto own = jobs->claim("SAT1", "scheduled", 20, 13, "station-A");
  const auto others = jobs->claim("SAT2", "scheduled", 20, 14, "station-B");
  REQUIRE(own.has_value());
  REQUIRE(others.has_value());
  // Its own claimed job and the unclaimed ones (a single daemon's): 3.
  CHECK(jobs->mark_station_running_interrupted("station-A", 99) == 3);
  CHECK(jobs->get(a)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(b)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(b)->finished_utime == 99);
  CHECK(jobs->get(b)->error == job_outcome::kProcessEnded);
  CHECK(jobs->get(*own)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(done)->outcome == job_outcome::kOk);
  // Station B's refit runs on: still running, still claimed, it can finish.
  CHECK(jobs->get(*others)->outcome == job_outcome::kRunning);
  CHECK_FALSE(jobs->claim("SAT2", "scheduled", 20, 100, "station-A").has_value());
  // Station A's claim is given up: the refit can be claimed again.
  CHECK(jobs->claim("SAT1", "scheduled", 20, 100, "station-A").has_value());
  jobs->finish(*others, job_outcome::kOk, 101);
  CHECK(jobs->mark_station_running_interrupted("station-B", 102) == 0);
  CHECK(jobs->mark_station_running_interrupted("station-A", 103) == 1);  // its new claim
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a claimed refit runs once: a second claim is refused until the first "
                          "is interrupted",
                          "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  const auto first = jobs->claim("SAT1", "scheduled", 1000, 1001, "station-A");
  REQUIRE(first.has_value());
  CHECK(jobs->get(*first)->claimed_by == "station-A");
  CHECK(jobs->get(*first)->outcome == job_outcome::kRunning);
  // Already claimed, running: refused, whoever asks; the holder says who has it.
  CHECK_FALSE(jobs->claim("SAT1", "scheduled", 1000, 1002, "station-B").has_value());
  CHECK_FALSE(jobs->claim("SAT1", "scheduled", 1000, 1002, "station-A").has_value());
  CHECK(jobs->claim_holder("SAT1", "scheduled", 1000)->id == *first);
  // Another key (spacecraft, trigger or time) is another claim; unclaimed jobs never collide.
  CHECK(jobs->claim("SAT2", "scheduled", 1000, 1002, "station-B").has_value());
  CHECK(jobs->claim("SAT1", "early", 1000, 1002, "station-B").has_value());
  CHECK(jobs->claim("SAT1", "scheduled", 2000, 1002, "station-B").has_value());
  jobs->start("SAT1", "scheduled", 1000, 1003);
  CHECK(jobs->get(jobs->start("SAT1", "manual", 1000, 1003))->claimed_by.empty());
  // Ended, with any outcome: still claimed (each refit runs once).
  jobs->finish(*first, job_outcome::kSkipped, 1010, "too few samples");
  CHECK_FALSE(jobs->claim("SAT1", "scheduled", 1000, 1020, "station-B").has_value());
  CHECK(jobs->claim_holder("SAT1", "scheduled", 1000)->outcome == job_outcome::kSkipped);
  CHECK_THROWS_AS(jobs->claim("SAT1", "scheduled", 3000, 1020, ""), StorageError);

  // The owner died while its refit ran: the next owner interrupts the spacecraft's running
  // jobs, which gives their claims up, and claims the refit again; the old job cannot finish.
  const auto lost = jobs->claim("SAT3", "scheduled", 1000, 1001, "station-A");
  REQUIRE(lost.has_value());
  const auto other = jobs->claim("SAT4", "scheduled", 1000, 1001, "station-A");
  CHECK(jobs->mark_running_interrupted("SAT3", 1100) == 1);
  CHECK(jobs->get(*lost)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(*lost)->error == job_outcome::kTakenOver);
  CHECK(jobs->get(*other)->outcome == job_outcome::kRunning);  // another spacecraft
  const auto again = jobs->claim("SAT3", "scheduled", 1000, 1101, "station-B");
  REQUIRE(again.has_value());
  CHECK(*again != *lost);
  CHECK(jobs->claim_holder("SAT3", "scheduled", 1000)->claimed_by == "station-B");
  CHECK_THROWS_AS(jobs->finish(*lost, job_outcome::kOk, 1200), StorageError);
  CHECK(jobs->get(*lost)->outcome == job_outcome::kInterrupted);
  jobs->finish(*again, job_outcome::kOk, 1200);
  CHECK(jobs->get(*again)->outcome == job_outcome::kOk);
}

TEMPLATE_TEST_CASE("daemons claiming the same refits at once: exactly one wins each", "[jobs]",
                   SqliteBackend, PostgresBackend) {
  TestType backend;
  const auto setup = backend.open();
  if (!setup) return;
  constexpr int kDaemons = 4;
  constexpr int kRefits = 30;
  std::vector<std::unique_ptr<Connection>> connections;
  std::vector<std::unique_ptr<RefitJobLog>> logs;
  std::vector<std::string> stations;
  for (int d = 0; d < kDaemons; ++d) {
    connections.push_back(backend.open_again());
    logs.push_back(connections.back()->make_refit_job_log());
    stations.push_back("station-" + std::to_string(d));
  }
  std::vector<std::vector<int64_t>> won(kDaemons);
  // Left to themselves the claims hardly overlap: on SQLite a claim is one statement of some
  // 20 us, and on two busy cores one daemon's claim has mostly ended before the next one's
  // starts. So for each refit another session holds the table's write lock until all the
  // daemons have sent their claim: the claims wait together and race for the row once it goes.
  const bool sqlite = std::string_view(TestType::kName) == "sqlite";
  const std::string lock_sql =
      sqlite ? "BEGIN IMMEDIATE" : "BEGIN; LOCK TABLE refit_jobs IN EXCLUSIVE MODE";
  std::atomic<int> locked_refit{-1};  // the lock is held for this refit's claims
  std::atomic<int> sent{0};           // claims begun (all refits)
  std::atomic<int> ended{0};          // claims returned (all refits)
  std::atomic<bool> stalled{false};   // a thread threw or waited past its deadline
  std::vector<ClaimSpan> spans(static_cast<size_t>(kDaemons * kRefits));
  std::vector<SteadyClock::time_point> released(kRefits);
  const auto await = [&](const auto& condition) {
    const auto deadline = SteadyClock::now() + std::chrono::seconds(10);
    while (!condition()) {
      if (stalled.load() || SteadyClock::now() > deadline) {
        stalled.store(true);
        return false;
      }
      // Sleeping, not spinning: the PostgreSQL server shares the cores.
      std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
    return true;
  };
  const auto errors = magcal::test::run_at_once(kDaemons + 1, [&](int d) {
    try {
      for (int r = 0; r < kRefits; ++r) {
        if (d == kDaemons) {  // the lock holder
          if (!await([&] { return ended.load() == r * kDaemons; })) return;
          setup->exec(lock_sql);
          locked_refit.store(r);
          const bool all_sent = await([&] { return sent.load() == (r + 1) * kDaemons; });
          released[static_cast<size_t>(r)] = SteadyClock::now();
          setup->exec("COMMIT");
          if (!all_sent) return;
          continue;
        }
        if (!await([&] { return locked_refit.load() == r; })) return;
        ClaimSpan& span = spans[static_cast<size_t>(r * kDaemons + d)];
        span.begin = SteadyClock::now();
        sent.fetch_add(1);
        const auto k = static_cast<size_t>(d);
        const bool claimed = logs[k]->claim("SAT1", "scheduled", r, 0, stations[k]).has_value();
        span.end = SteadyClock::now();
        ended.fetch_add(1);
        if (claimed) won[k].push_back(r);
      }
    } catch (...) {
      stalled.store(true);  // the others stop waiting for this one
      throw;
    }
  });
  CHECK_FALSE(stalled.load());
  CHECK(errors[kDaemons] == "");
  std::vector<int64_t> all;
  for (int d = 0; d < kDaemons; ++d) {
    CHECK(errors[static_cast<size_t>(d)] == "");
    all.insert(all.end(), won[static_cast<size_t>(d)].begin(), won[static_cast<size_t>(d)].end());
  }
  std::sort(all.begin(), all.end());
  std::vector<int64_t> each(kRefits);
  std::iota(each.begin(), each.end(), 0);
  CHECK(all == each);  // every refit claimed, none twice
  // The race happened: refits whose claims were all in flight when the lock went, none
  // returned before (each waited for the lock, as a daemon's claim waits for another's).
  int raced = 0;
  for (size_t r = 0; r < kRefits; ++r) {
    const auto begin = spans.begin() + static_cast<std::ptrdiff_t>(r * kDaemons);
    raced += std::all_of(begin, begin + kDaemons, [&](const ClaimSpan& span) {
      return span.begin < released[r] && released[r] < span.end;
    });
  }
  CHECK(raced == kRefits);
  CHECK(setup->make_refit_job_log()->recent("SAT1", 2 * kRefits).size() == kRefits);
}
