// refit_jobs table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): lifecycle,
// crash recovery, foreign key to calibrations.
#include "storage/refit_job_log.hpp"

#include <catch2/catch.hpp>
#include <optional>
#include <string>

#include "storage/calibration_history.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

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
  jobs->mark_running_interrupted(600);
  CHECK(jobs->newest_finished_scheduled_utime("SAT1") == 400);  // 500 runs again
  CHECK_FALSE(jobs->newest_reanchor_calibration_id("SAT2").has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest, "jobs running when the process died become interrupted",
                          "[jobs]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto jobs = this->db->make_refit_job_log();
  const int64_t done = jobs->start("SAT1", "scheduled", 1, 2);
  jobs->finish(done, job_outcome::kOk, 3);
  const int64_t a = jobs->start("SAT1", "scheduled", 10, 11);
  const int64_t b = jobs->start("SAT2", "manual", 10, 12);
  CHECK(jobs->mark_running_interrupted(99) == 2);
  CHECK(jobs->get(a)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(b)->outcome == job_outcome::kInterrupted);
  CHECK(jobs->get(b)->finished_utime == 99);
  CHECK(jobs->get(done)->outcome == job_outcome::kOk);
  CHECK(jobs->mark_running_interrupted(100) == 0);
}
