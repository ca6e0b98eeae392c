// The `refit_jobs` statements whose SQL the two dialects share, written with SQLite's ?N
// (PostgreSQL runs them through dollar_params(), storage/postgres/pg_query.hpp). Internal to
// storage/.
#pragma once

#include <string>

#include "storage/refit_job_row.hpp"

namespace magcal::storage::refit_job_sql {

inline constexpr const char* kStart =
    "INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, started_utime, outcome) "
    "VALUES (?1, ?2, ?3, ?4, 'running') RETURNING id";
// DO NOTHING (no row returned) when another job holds the claim.
inline std::string claim() {
  return std::string(
             "INSERT INTO refit_jobs (sat_id, trigger_kind, scheduled_utime, started_utime, "
             "outcome, claimed_by) VALUES (?1, ?2, ?3, ?4, 'running', ?5) ON CONFLICT "
             "(sat_id, trigger_kind, scheduled_utime) WHERE ") +
         kHoldsRefitClaim + " DO NOTHING RETURNING id";
}
inline std::string claim_holder() {
  return row_codec::select_sql<RefitJobRow>(
      std::string("WHERE sat_id = ?1 AND trigger_kind = ?2 AND scheduled_utime = ?3 AND ") +
      kHoldsRefitClaim);
}
inline constexpr const char* kFinish =
    "UPDATE refit_jobs SET outcome = ?2, finished_utime = ?3, error = ?4, calibration_id = ?5 "
    "WHERE id = ?1 AND outcome = 'running'";
// ?3: the error the interrupted jobs are given.
inline constexpr const char* kInterruptStation =
    "UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = ?2, error = ?3 WHERE "
    "outcome = 'running' AND (claimed_by = ?1 OR claimed_by IS NULL)";
inline constexpr const char* kInterruptSpacecraft =
    "UPDATE refit_jobs SET outcome = 'interrupted', finished_utime = ?2, error = ?3 WHERE "
    "sat_id = ?1 AND outcome = 'running'";
inline constexpr const char* kNewestReanchor =
    "SELECT max(calibration_id) FROM refit_jobs WHERE sat_id = ?1 AND outcome = 'ok' AND "
    "trigger_kind <> 'manual'";
inline constexpr const char* kNewestScheduled =
    "SELECT max(scheduled_utime) FROM refit_jobs WHERE sat_id = ?1 AND trigger_kind = "
    "'scheduled' AND outcome NOT IN ('running', 'interrupted')";
inline std::string get() {
  return row_codec::select_sql<RefitJobRow>("WHERE id = ?1");
}
inline std::string recent() {
  return row_codec::select_sql<RefitJobRow>("WHERE sat_id = ?1 ORDER BY id DESC LIMIT ?2");
}

}  // namespace magcal::storage::refit_job_sql
