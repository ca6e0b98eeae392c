// RefitRunner's choice of the change-gate reference: a refit on a short window (the
// first 8 h of a spacecraft, 2 881 samples) is judged on its own evidence and never becomes the
// reference of later full-window refits; with honest covariances every full-window refit of a
// paper-scenario day is accepted, and the evidence columns (schema 3) round-trip.
#include <algorithm>
#include <cmath>

#include <catch2/catch.hpp>

#include <chrono>
#include <thread>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
#include "service/io/calibration_record.hpp"
#include "service/refit/refit_runner.hpp"
#include "storage/calibration_history.hpp"
#include "storage/postgres/pg_database.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal;

namespace {

// Simulates `sc` and stores every sample as the daemon would (reference direction and |h|);
// returns the simulator's truth. `seq` continues across calls.
TruthParameters store_simulation(storage::Connection& db, const Scenario& sc,
                                 const std::string& sat, int64_t* seq) {
  Simulator sim(sc);
  std::vector<storage::StoredSample> rows;
  SimulatedSample s;
  while (sim.next(&s)) {
    const CalibrationSample c = s.calibration_sample();
    storage::StoredSample r;
    r.sat_id = sat;
    r.utime = c.utime;
    r.seq = (*seq)++;
    r.receive_utime = c.utime;
    r.b_sensor_nT = {c.b_sensor_nT.x(), c.b_sensor_nT.y(), c.b_sensor_nT.z()};
    r.has_direction = true;
    r.h_body_nT = {c.h_body_nT.x(), c.h_body_nT.y(), c.h_body_nT.z()};
    r.h_norm_nT = c.h_body_nT.norm();
    r.temperature_C = s.temperature_C;
    rows.push_back(r);
  }
  db.make_sample_window_store()->insert_batch(rows);
  return sim.truth();
}

// An accepted full-window (12 h) twostep refit ending at end_utime with the true D and the given
// bias, with a full window's variances: the change gate's reference.
CalibrationResult full_window_reference(const TruthParameters& truth,
                                        const Eigen::Vector3d& bias_nT, int64_t end_utime) {
  CalibrationResult reference;
  reference.method = "twostep";
  reference.utime = reference.window_end_utime = end_utime;
  reference.window_start_utime = end_utime - 12 * 3'600'000'000LL;
  reference.n_samples = 4320;
  Vector9d p;
  const Eigen::Matrix3d& D = truth.D;
  p << bias_nT, D(0, 0), D(1, 1), D(2, 2), D(0, 1), D(0, 2), D(1, 2);
  reference.parameters = CalibrationParameters::from_packed(p);
  Vector9d variance;
  variance << 0.8, 9.0, 0.5, 1e-8, 1e-8, 1e-8, 1e-8, 1e-8, 1e-8;
  reference.covariance = variance.asDiagonal();
  reference.residual_rms_nT = 3.0;
  reference.status = CalibrationStatus::kOk;
  reference.accepted = true;
  reference.converged = true;
  return reference;
}

Scenario paper_scenario(uint64_t seed, double hours) {
  Scenario sc = *scenario_preset("paper");
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  return sc;
}

// PostgreSQL: a transaction that stores a refit result commits synchronously (a trigger sets
// synchronous_commit), so with an absent synchronous standby its COMMIT waits for good; the job
// claim before it does not.
void hold_result_commits(storage::Connection& db) {
  db.exec(
      "CREATE FUNCTION hold_commit() RETURNS trigger AS $$ BEGIN "
      "PERFORM set_config('synchronous_commit', 'on', true); RETURN NEW; END $$ "
      "LANGUAGE plpgsql; "
      "CREATE TRIGGER hold_commit BEFORE INSERT ON calibrations "
      "FOR EACH ROW EXECUTE FUNCTION hold_commit();");
}

}  // namespace

TEST_CASE("refits: the short first window is no reference, every full-window refit is accepted") {
  test::TempDir dir("magcal_refit_runner");
  DaemonConfig config;  // embedded defaults: 12 h window, min_samples 1000
  config.storage.db_path = dir.file("day.db");
  storage::Database db(config.storage.db_path);

  const Scenario sc = paper_scenario(11, 24.0);
  int64_t seq = 0;
  const TruthParameters truth = store_simulation(db, sc, "PAPER-1", &seq);

  RefitRunner runner(config, db);
  const int64_t t0 = sc.epoch_utime;
  const int64_t hour = 3'600'000'000LL;
  // A new spacecraft's schedule: first refit after 8 h of data, then every 6 h.
  int full_refits = 0;
  for (const int h : {8, 14, 20, 24}) {
    const int64_t t_ref = t0 + h * hour - 10'000'000LL;
    const RefitOutcome out = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
    REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
    const CalibrationResult& r = out.result;
    const Eigen::Vector3d err = r.parameters.bias_nT - truth.bias_nT;
    INFO(h << " h: n " << r.n_samples << " err " << err.transpose() << " sigma "
           << r.bias_sigma_nT().transpose() << " "
           << (r.rejection_reasons.empty() ? "" : r.rejection_reasons[0]));
    CHECK(out.accepted());
    // The sigma it is accepted with covers its error.
    CHECK(err.cwiseQuotient(r.bias_sigma_nT()).cwiseAbs().maxCoeff() < 5.0);
    if (h == 8) CHECK(r.n_samples == 2880);
    if (h > 8) {
      CHECK(r.n_samples == 4320);
      ++full_refits;
    }
  }
  CHECK(full_refits == 3);

  // The evidence is stored with the result (schema 3) and read back.
  storage::SqliteCalibrationHistory history(db);
  const auto last = history.latest_accepted_refit("PAPER-1");
  REQUIRE(last);
  CHECK(std::isfinite(last->noise_scale));
  CHECK(std::isfinite(last->residual_autocorrelation));
  // The HAC covariance's lag window is the one the refit's own residuals give (here 0: with
  // white sensor noise their lag-1 autocorrelation is below 3 / sqrt(n)); stored, not NULL (-1).
  INFO("lag window " << last->covariance_lag_window << ", lag-1 autocorrelation "
                     << last->residual_autocorrelation << ", n " << last->n_samples);
  CHECK(last->covariance_lag_window ==
        bartlett_lag_window(last->residual_autocorrelation, last->n_samples));
  CHECK(std::isfinite(last->residual_rms_all_nT));
  CHECK(last->has_nonlinearity == 1);
  CHECK(std::isfinite(last->k3[0]));
  CHECK(std::isnan(last->nis_mean));  // a refit has no innovations: NULL
  // The field error it leaves on its window (schema 12): hundredths of a degree (noise and the
  // hysteresis no table removes), far below the raw field's degrees; its magnitude error is the
  // residual rms, the same |B_cal| - |h| over the same samples.
  CHECK(last->field_direction_error_rms_deg > 0.0);
  CHECK(last->field_direction_error_rms_deg < 0.1);
  CHECK(last->field_direction_error_worst_deg >= last->field_direction_error_rms_deg);
  CHECK(last->field_magnitude_error_rms_nT == Approx(last->residual_rms_nT).epsilon(1e-6));
  // The reference for a later full-window refit is a full-window one, not the 8 h refit.
  const auto reference =
      history.latest_accepted_refit("PAPER-1", static_cast<int64_t>(0.9 * 12 * hour), 1000);
  REQUIRE(reference);
  CHECK(reference->n_samples == 4320);
}

TEST_CASE("refits: a real bias change is accepted once two windows corroborate it") {
  // A bias step of 60 nT on x (as a fielded sensor can show after a magnetic event): every
  // later refit differs from the last accepted one by many of its sigmas, so the change gate
  // alone would reject every refit from then on and leave operators without a calibration.
  test::TempDir dir("magcal_refit_step");
  DaemonConfig config;
  config.storage.db_path = dir.file("step.db");
  storage::Database db(config.storage.db_path);
  const int64_t hour = 3'600'000'000LL;
  const Eigen::Vector3d step_nT(60.0, 0.0, 0.0);

  const Scenario sc = paper_scenario(1, 24.0);  // the seed is set per day below
  const int64_t t0 = sc.epoch_utime;
  Eigen::Vector3d b0 = Eigen::Vector3d::Zero();
  int64_t seq = 0;
  for (int day = 0; day < 2; ++day) {
    Scenario d = sc;
    d.seed = 5 + day;
    d.epoch_utime = t0 + day * 24 * hour;
    if (day == 1) d.sensor.bias_nT += step_nT;
    const TruthParameters truth = store_simulation(db, d, "STEP-1", &seq);
    if (day == 0) b0 = truth.bias_nT;
  }

  RefitRunner runner(config, db);
  int rejected_in_a_row = 0, max_rejected_in_a_row = 0, corroborated = 0;
  bool last_accepted = false;
  for (int h = 12; h <= 48; h += 6) {
    const int64_t t_ref = t0 + h * hour - 10'000'000LL;
    const RefitOutcome out = runner.run("STEP-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
    REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
    const CalibrationResult& r = out.result;
    INFO(h << " h: bias " << r.parameters.bias_nT.transpose() << " sigma "
           << r.bias_sigma_nT().transpose() << " "
           << (r.rejection_reasons.empty() ? r.message : r.rejection_reasons[0]));
    last_accepted = out.accepted();
    if (out.accepted()) {
      rejected_in_a_row = 0;
      if (r.message.find("corroborated") != std::string::npos) ++corroborated;
      // Windows wholly before or after the step: the accepted estimate covers its truth.
      if (h <= 24 || h >= 36) {
        const Eigen::Vector3d truth = h <= 24 ? b0 : Eigen::Vector3d(b0 + step_nT);
        const Eigen::Vector3d err = r.parameters.bias_nT - truth;
        CHECK(err.cwiseQuotient(r.bias_sigma_nT()).cwiseAbs().maxCoeff() < 5.0);
      }
    } else {
      ++rejected_in_a_row;
    }
    max_rejected_in_a_row = std::max(max_rejected_in_a_row, rejected_in_a_row);
  }
  WARN("bias step of 60 nT: " << corroborated << " refit(s) accepted by corroboration, at most "
                              << max_rejected_in_a_row << " rejected in a row");
  CHECK(corroborated >= 1);
  CHECK(max_rejected_in_a_row <= 2);  // the straddling window and the first one after it
  CHECK(last_accepted);
}

TEST_CASE("refits: a reference with a temperature model is compared at this window's temperature") {
  // The sensor sits at 30 degC for the whole window (a season, a heater); the accepted reference
  // refit modelled b(T) = b0 + k_T (T - 20 degC) with the truth. This window's bias is
  // b(30 degC): 10 degC x k_T = (10, -5, 15) nT from the reference's bias at its T0, beyond the
  // change gate's 10 nT floor, and no change of the sensor.
  const Eigen::Vector3d k_T(1.0, -0.5, 1.5);
  for (const bool modelled : {true, false}) {
    DYNAMIC_SECTION((modelled ? "the reference has the model" : "the reference has none")) {
      test::TempDir dir("magcal_refit_thermal");
      DaemonConfig config;
      config.storage.db_path = dir.file("thermal.db");
      storage::Database db(config.storage.db_path);
      Scenario sc = paper_scenario(3, 12.0);
      sc.sensor.temperature_coefficient_nT_per_C = k_T;
      sc.sensor.reference_temperature_C = 20.0;
      sc.sensor.temperature_mean_C = 30.0;
      int64_t seq = 0;
      const TruthParameters truth = store_simulation(db, sc, "WARM-1", &seq);
      const int64_t hour = 3'600'000'000LL;
      const int64_t t_ref = sc.epoch_utime + 12 * hour - 10'000'000LL;

      // An accepted full-window refit of the day before.
      CalibrationResult reference = full_window_reference(truth, truth.bias_nT, t_ref - 24 * hour);
      if (modelled) {
        reference.has_temperature_model = true;
        reference.reference_temperature_C = 20.0;
        reference.temperature_coefficient_nT_per_C = k_T;
        reference.temperature_coefficient_covariance = Eigen::Matrix3d::Identity() * 4e-4;
      }
      storage::SqliteCalibrationHistory(db).append(record_from_result("WARM-1", reference));

      RefitRunner runner(config, db);
      const RefitOutcome out =
          runner.run("WARM-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
      REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
      const CalibrationResult& r = out.result;
      std::string reasons;
      for (const auto& reason : r.rejection_reasons) reasons += reason + "; ";
      INFO("bias " << r.parameters.bias_nT.transpose() << " sigma " << r.bias_sigma_nT().transpose()
                   << " reasons: " << reasons);
      const bool change_gate = reasons.find("bias_change") != std::string::npos;
      // Without the model the reference is the bias at another temperature: the 15 nT offset
      // is (rightly, for all it knows) a change.
      CHECK(change_gate != modelled);
      if (modelled) CHECK(out.accepted());
    }
  }
}

TEST_CASE("refits: a reference with a bias rate is moved by it to this window's end") {
  // The bias drifts (1.5, -2, 1) nT/h; the accepted reference refit of the day before modelled
  // the rate and published the bias at its window's end. This window's bias at its end is 24 h
  // of drift, (36, -48, 24) nT, from the reference's: beyond the change gate's 10 nT floor, and
  // no jump of the sensor.
  const Eigen::Vector3d rate_nT_per_h(1.5, -2.0, 1.0);
  for (const bool modelled : {true, false}) {
    DYNAMIC_SECTION((modelled ? "the reference has the rate" : "the reference has none")) {
      test::TempDir dir("magcal_refit_drift");
      DaemonConfig config;
      config.storage.db_path = dir.file("drift.db");
      storage::Database db(config.storage.db_path);
      Scenario sc = paper_scenario(3, 12.0);
      sc.sensor.drift_nT_per_day = 24.0 * rate_nT_per_h;
      int64_t seq = 0;
      const TruthParameters truth = store_simulation(db, sc, "DRIFT-1", &seq);
      const int64_t hour = 3'600'000'000LL;
      const int64_t t_ref = sc.epoch_utime + 12 * hour - 10'000'000LL;

      // An accepted full-window refit of the day before; b0 is the bias at the scenario epoch,
      // and the reference's window ended 12 h before it.
      CalibrationResult reference =
          full_window_reference(truth, truth.bias_nT - 12.0 * rate_nT_per_h, t_ref - 24 * hour);
      if (modelled) {
        reference.has_bias_rate = true;
        reference.bias_rate_nT_per_h = rate_nT_per_h;
        reference.bias_rate_covariance = Eigen::Matrix3d::Identity() * 0.01;
      }
      storage::SqliteCalibrationHistory(db).append(record_from_result("DRIFT-1", reference));

      RefitRunner runner(config, db);
      const RefitOutcome out =
          runner.run("DRIFT-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
      REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
      const CalibrationResult& r = out.result;
      std::string reasons;
      for (const auto& reason : r.rejection_reasons) reasons += reason + "; ";
      INFO("bias " << r.parameters.bias_nT.transpose() << " sigma " << r.bias_sigma_nT().transpose()
                   << " rate " << r.bias_rate_nT_per_h.transpose() << " reasons: " << reasons);
      CHECK(r.has_bias_rate);  // this window's own fit sees the drift
      const bool change_gate = reasons.find("bias_change") != std::string::npos;
      // Without the rate the reference is the bias of a day before: 48 nT is (rightly, for all
      // it knows) a change.
      CHECK(change_gate != modelled);
      if (modelled) CHECK(out.accepted());
    }
  }
}

TEST_CASE("the first 3 h of a spacecraft: early and short-window refits") {
  test::TempDir dir("magcal_refit_runner_early");
  DaemonConfig config;
  config.storage.db_path = dir.file("early.db");
  storage::Database db(config.storage.db_path);
  int64_t seq = 0;
  store_simulation(db, paper_scenario(3, 3.0), "PAPER-1", &seq);
  storage::SqliteSampleWindowStore samples(db);
  const int64_t t_ref = *samples.utime_at_rank("PAPER-1", config.refit.min_samples - 1);
  RefitRunner runner(config, db);

  SECTION("an early refit runs once: the same key again is skipped without a job row") {
    const RefitOutcome first = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kFirst, t_ref);
    REQUIRE(first.kind == RefitOutcome::Kind::kComputed);
    CHECK(first.result.n_samples == config.refit.min_samples);  // keyed by its count
    const RefitOutcome again = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kFirst, t_ref);
    CHECK(again.kind == RefitOutcome::Kind::kSkipped);
    CHECK(again.job_id == first.job_id);
    CHECK_THAT(again.message, Catch::Contains("already ran"));
    storage::SqliteRefitJobLog jobs(db);
    CHECK(jobs.recent("PAPER-1", 10).size() == 1);
    // A scheduled refit of the same end is not an early one: it runs.
    CHECK(runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref).kind ==
          RefitOutcome::Kind::kComputed);
  }

  SECTION("a window short of [refit] min_samples is skipped with its count, as skip_reason says") {
    const auto skipped = [&](const std::string& sat, std::optional<int64_t> t_end) {
      const std::string why = runner.skip_reason(sat, t_end);
      const RefitOutcome out =
          runner.run(sat, t_end, storage::RefitTrigger::kManual, t_end.value_or(0));
      CHECK(out.kind == RefitOutcome::Kind::kSkipped);
      CHECK(out.job_outcome == storage::job_outcome::kSkipped);
      CHECK(out.message == why);
      return out.message;
    };
    const int64_t t_short = *samples.utime_at_rank("PAPER-1", config.refit.min_samples - 2);
    CHECK(skipped("PAPER-1", t_short) ==
          std::to_string(config.refit.min_samples - 1) + " samples in the window, " +
              std::to_string(config.refit.min_samples) + " needed ([refit] min_samples)");
    CHECK_THAT(skipped("NOPE", std::nullopt), Catch::Contains("no stored samples for 'NOPE'"));
    // One sample more (t_ref) is enough.
    CHECK(runner.skip_reason("PAPER-1", t_ref).empty());
    CHECK(runner.run("PAPER-1", t_ref, storage::RefitTrigger::kManual, t_ref).kind ==
          RefitOutcome::Kind::kComputed);
  }
}

TEST_CASE("a daemon's refit runs once for the fleet: claimed under its station, never twice") {
  test::TempDir dir("magcal_refit_runner_claims");
  DaemonConfig config;
  config.storage.db_path = dir.file("claims.db");
  config.station.id = "station-A";
  storage::Database db(config.storage.db_path);
  int64_t seq = 0;
  store_simulation(db, paper_scenario(5, 4.0), "PAPER-1", &seq);
  const int64_t t_ref = *storage::SqliteSampleWindowStore(db).newest_utime("PAPER-1");
  storage::SqliteRefitJobLog jobs(db);
  storage::SqliteCalibrationHistory history(db);
  const auto refit_rows = [&] {
    storage::HistoryQuery q;
    q.sat_id = "PAPER-1";
    q.method = "twostep";
    return history.query(q).size();
  };
  RefitRunner runner(config, db);

  // Station B (live: its heartbeat runs) holds the claim (running, then ended): nothing runs
  // here, whatever it became.
  const int64_t now = std::chrono::duration_cast<std::chrono::microseconds>(
                          std::chrono::system_clock::now().time_since_epoch())
                          .count();
  storage::SqliteLeaseStore(db).heartbeat("station-B", "b1", {}, now, 3'600'000'000LL);
  const auto b_job = jobs.claim("PAPER-1", "scheduled", t_ref, 1, "station-B");
  REQUIRE(b_job.has_value());
  RefitOutcome out = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
  CHECK(out.kind == RefitOutcome::Kind::kClaimedElsewhere);
  CHECK(out.job_id == *b_job);
  CHECK_THAT(out.message, Catch::Contains("station-B") && Catch::Contains("running"));
  jobs.finish(*b_job, storage::job_outcome::kFailed, 2, "whatever it was");
  CHECK(runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref).kind ==
        RefitOutcome::Kind::kClaimedElsewhere);
  CHECK(refit_rows() == 0);
  CHECK(jobs.recent("PAPER-1", 10).size() == 1);

  // Station B's job interrupted (its spacecraft taken over): the claim is free, this one runs.
  const int64_t t_early = t_ref - 600'000'000;
  const auto lost = jobs.claim("PAPER-1", "early", t_early, 1, "station-B");
  REQUIRE(lost.has_value());
  jobs.mark_running_interrupted("PAPER-1", 3);
  out = runner.run("PAPER-1", t_early, storage::RefitTrigger::kEarly, t_early);
  REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
  CHECK(jobs.get(out.job_id)->claimed_by == "station-A");
  CHECK(refit_rows() == 1);

  // A claim still running by a station that is no longer live (it died mid-refit; this daemon
  // took its spacecraft over): given up, and the refit runs here.
  const int64_t t_dead = t_ref - 900'000'000;
  const auto dead = jobs.claim("PAPER-1", "scheduled", t_dead, 1, "station-C");
  REQUIRE(dead.has_value());
  out = runner.run("PAPER-1", t_dead, storage::RefitTrigger::kScheduled, t_dead);
  REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
  CHECK(jobs.get(*dead)->outcome == storage::job_outcome::kInterrupted);
  CHECK(jobs.get(out.job_id)->claimed_by == "station-A");
  CHECK(refit_rows() == 2);

  // This station's own job left running (an attempt whose end a storage failure kept from
  // being written) is carried on by the next attempt; once ended, the refit does not run again.
  const int64_t t_sched = t_ref - 300'000'000;
  const auto own = jobs.claim("PAPER-1", "scheduled", t_sched, 1, "station-A");
  REQUIRE(own.has_value());
  out = runner.run("PAPER-1", t_sched, storage::RefitTrigger::kScheduled, t_sched);
  REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
  CHECK(out.job_id == *own);
  CHECK(jobs.get(*own)->calibration_id == out.calibration_id);
  out = runner.run("PAPER-1", t_sched, storage::RefitTrigger::kScheduled, t_sched);
  CHECK(out.kind == RefitOutcome::Kind::kSkipped);
  CHECK_THAT(out.message, Catch::Contains("already ran"));
  CHECK(refit_rows() == 3);

  // `magcal refit` is not claimed: it runs whenever asked.
  for (int i = 0; i < 2; ++i) {
    out = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kManual, t_ref);
    REQUIRE(out.kind == RefitOutcome::Kind::kComputed);
    CHECK(jobs.get(out.job_id)->claimed_by.empty());
  }
  CHECK(refit_rows() == 5);
}

TEST_CASE("a transient storage error ends a claimed refit's job interrupted: the retry claims it") {
  test::PostgresBackend backend;  // its errors carry a SQLSTATE a trigger can raise
  const auto db = backend.open();
  if (!db) return;
  DaemonConfig config;
  config.station.id = "station-A";
  int64_t seq = 0;
  store_simulation(*db, paper_scenario(7, 4.0), "PAPER-1", &seq);
  const int64_t t_ref = *db->make_sample_window_store()->newest_utime("PAPER-1");
  // The next result insert fails as a serialization failure does (SQLSTATE 40001: transient).
  // A sequence counts the inserts: unlike a row, its nextval survives the rollback.
  db->exec(
      "CREATE SEQUENCE inserts_seen; "
      "CREATE FUNCTION fail_first_insert() RETURNS trigger AS $$ BEGIN "
      "IF nextval('inserts_seen') = 1 THEN "
      "RAISE EXCEPTION 'injected conflict' USING ERRCODE = '40001'; END IF; "
      "RETURN NEW; END $$ LANGUAGE plpgsql; "
      "CREATE TRIGGER fail_first BEFORE INSERT ON calibrations "
      "FOR EACH ROW EXECUTE FUNCTION fail_first_insert();");
  RefitRunner runner(config, *db);
  const auto jobs = db->make_refit_job_log();

  const RefitOutcome failed =
      runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
  REQUIRE(failed.kind == RefitOutcome::Kind::kError);
  REQUIRE(failed.storage_error.has_value());
  CHECK(failed.storage_error->transient());
  CHECK(failed.job_outcome == storage::job_outcome::kInterrupted);
  CHECK(jobs->get(failed.job_id)->outcome == storage::job_outcome::kInterrupted);
  CHECK_FALSE(jobs->get(failed.job_id)->calibration_id.has_value());
  CHECK_FALSE(jobs->claim_holder("PAPER-1", "scheduled", t_ref).has_value());  // given up

  // The daemon's retry (StorageRetry) runs it again: claimed anew, computed once.
  const RefitOutcome retried =
      runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
  REQUIRE(retried.kind == RefitOutcome::Kind::kComputed);
  CHECK(retried.job_id != failed.job_id);
  CHECK(jobs->claim_holder("PAPER-1", "scheduled", t_ref)->id == retried.job_id);
  CHECK(jobs->get(retried.job_id)->calibration_id == retried.calibration_id);

  // `magcal refit` holds no claim to give up: its failure stays 'failed', as before.
  db->exec("ALTER SEQUENCE inserts_seen RESTART WITH 1");
  const RefitOutcome manual = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kManual, t_ref);
  REQUIRE(manual.kind == RefitOutcome::Kind::kError);
  CHECK(jobs->get(manual.job_id)->outcome == storage::job_outcome::kFailed);
}

TEST_CASE("a refit whose COMMIT gets no reply is not run twice: the retry finds it done") {
  // The result and its job's outcome in one transaction whose COMMIT a synchronous standby that
  // is down holds (PostgreSQL): the commit is in doubt, and the job row is left as that commit
  // leaves it; not given up as interrupted, which would have the retry compute a second result.
  test::PostgresBackend backend;
  const std::string uri = backend.new_database();
  if (uri.empty()) return;
  // No reply within the deadline (the connection set aside), or the connection lost while the
  // COMMIT waits (its session terminated: the server then commits it locally).
  const bool terminated = GENERATE(false, true);
  storage::OpenOptions quick;
  quick.busy_timeout_ms = 200;
  quick.reply_timeout_ms = terminated ? 0 : 500;
  const auto db = backend.open_again(quick);
  DaemonConfig config;
  config.station.id = "station-A";
  int64_t seq = 0;
  store_simulation(*db, paper_scenario(7, 4.0), "PAPER-1", &seq);
  const int64_t t_ref = *db->make_sample_window_store()->newest_utime("PAPER-1");
  RefitRunner runner(config, *db);
  const auto observer = backend.open_again();  // (its sessions' commits never wait: it reads)
  const auto jobs = observer->make_refit_job_log();

  hold_result_commits(*db);
  test::set_absent_synchronous_standby(uri, true);
  std::thread terminator;
  if (terminated) {
    terminator = std::thread([&] {
      const auto admin = backend.open_again();
      test::wait_until(
          [&] {
            return dynamic_cast<storage::PgDatabase&>(*admin)
                       .execute(
                           "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                           "WHERE wait_event = 'SyncRep'")
                       .get_int64(0, 0) > 0;
          },
          30);
    });
  }
  const RefitOutcome held = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
  if (terminator.joinable()) terminator.join();
  REQUIRE(held.kind == RefitOutcome::Kind::kError);
  REQUIRE(held.storage_error.has_value());
  INFO(held.message);
  CHECK(held.storage_error->transient());
  CHECK(held.storage_error->in_doubt_transaction() != 0);
  test::set_absent_synchronous_standby(uri, false);

  // The held commit completes: the job is done, with its result. The daemon's retry finds the
  // refit done by this station and computes nothing.
  REQUIRE(test::wait_until(
      [&] {
        const auto job = jobs->get(held.job_id);
        return job && job->outcome != storage::job_outcome::kRunning;
      },
      10));
  const auto done = jobs->get(held.job_id);
  CHECK(done->outcome != storage::job_outcome::kInterrupted);
  CHECK(done->calibration_id.has_value());
  RefitOutcome retried;
  REQUIRE(test::wait_until(
      [&] {
        retried = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kScheduled, t_ref);
        return retried.kind != RefitOutcome::Kind::kError;  // (the connection set aside first)
      },
      10));
  CHECK(retried.kind != RefitOutcome::Kind::kComputed);
  storage::HistoryQuery q;
  q.sat_id = "PAPER-1";
  const auto rows = observer->make_calibration_history()->query(q);
  CHECK(std::count_if(rows.begin(), rows.end(),
                      [](const auto& r) { return storage::is_refit_method(r.method); }) == 1);
}

TEST_CASE("a manual refit whose COMMIT gets no reply leaves no job running when it lands") {
  // `magcal refit` owns no claim that a daemon would interrupt: its job row is written with its
  // end, so a COMMIT held for an absent synchronous standby (in doubt when the CLI exits) lands
  // with a finished job, never a 'running' row for good.
  test::PostgresBackend backend;
  const std::string uri = backend.new_database();
  if (uri.empty()) return;
  storage::OpenOptions quick;
  quick.busy_timeout_ms = 200;
  quick.reply_timeout_ms = 500;
  const auto db = backend.open_again(quick);
  int64_t seq = 0;
  store_simulation(*db, paper_scenario(7, 4.0), "PAPER-1", &seq);
  const int64_t t_ref = *db->make_sample_window_store()->newest_utime("PAPER-1");
  const DaemonConfig config;
  RefitRunner runner(config, *db);
  const auto observer = backend.open_again();
  const auto jobs = observer->make_refit_job_log();
  hold_result_commits(*db);
  test::set_absent_synchronous_standby(uri, true);
  const RefitOutcome held = runner.run("PAPER-1", t_ref, storage::RefitTrigger::kManual, t_ref);
  REQUIRE(held.kind == RefitOutcome::Kind::kError);
  REQUIRE(held.storage_error.has_value());
  CHECK(held.storage_error->in_doubt_transaction() != 0);
  // While the commit is held, no job of it is visible (the CLI has exited with its error).
  CHECK(jobs->recent("PAPER-1", 8).empty());
  test::set_absent_synchronous_standby(uri, false);

  REQUIRE(test::wait_until([&] { return !jobs->recent("PAPER-1", 8).empty(); }, 10));
  const auto landed = jobs->recent("PAPER-1", 8);
  REQUIRE(landed.size() == 1);
  CHECK(landed[0].trigger == "manual");
  CHECK(landed[0].outcome != storage::job_outcome::kRunning);
  CHECK(landed[0].calibration_id.has_value());
}
