// RefitRunner's choice of the change-gate reference (issue 10): a refit on a short window (the
// first 8 h of a spacecraft, 2 881 samples) is judged on its own evidence and never becomes the
// reference of later full-window refits; with honest covariances every full-window refit of a
// paper-scenario day is accepted, and the evidence columns (schema 3) round-trip.
#include <cmath>

#include <catch2/catch.hpp>

#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"
#include "service/refit_runner.hpp"
#include "tests/service/cli_test_support.hpp"

using namespace magcal;

TEST_CASE("refits: the short first window is no reference, every full-window refit is accepted") {
  test::TempDir dir("magcal_refit_runner");
  DaemonConfig config;  // embedded defaults: 12 h window, min_samples 1000
  config.storage.db_path = dir.file("day.db");
  storage::Database db(config.storage.db_path);

  Scenario sc = *scenario_preset("paper");
  sc.seed = 11;
  sc.duration_s = 24.0 * 3600.0;
  Simulator sim(sc);
  const TruthParameters truth = sim.truth();
  std::vector<storage::StoredSample> rows;
  SimulatedSample s;
  int64_t seq = 0;
  while (sim.next(&s)) {
    const CalibrationSample c = s.calibration_sample();
    storage::StoredSample r;
    r.sat_id = "PAPER-1";
    r.utime = c.utime;
    r.seq = seq++;
    r.receive_utime = c.utime;
    r.b_sensor_nT = {c.b_sensor_nT.x(), c.b_sensor_nT.y(), c.b_sensor_nT.z()};
    r.has_direction = true;
    r.h_body_nT = {c.h_body_nT.x(), c.h_body_nT.y(), c.h_body_nT.z()};
    r.h_norm_nT = c.h_body_nT.norm();
    rows.push_back(r);
  }
  storage::SampleWindowStore(db).insert_batch(rows);

  RefitRunner runner(config, db);
  const int64_t t0 = sc.epoch_utime;
  const int64_t hour = 3'600'000'000LL;
  // The schedule: first refit after 8 h of data, then every 6 h.
  int full_refits = 0;
  for (const int h : {8, 14, 20, 24}) {
    const int64_t t_ref = t0 + h * hour - 10'000'000LL;
    const RefitOutcome out = runner.run("PAPER-1", t_ref, "scheduled", t_ref);
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
  storage::CalibrationHistory history(db);
  const auto last = history.latest_accepted_refit("PAPER-1");
  REQUIRE(last);
  CHECK(std::isfinite(last->noise_scale));
  CHECK(std::isfinite(last->residual_autocorrelation));
  CHECK(last->covariance_lag_window >= 0);
  CHECK(std::isfinite(last->residual_rms_all_nT));
  CHECK(last->has_nonlinearity == 1);
  CHECK(std::isfinite(last->k3[0]));
  CHECK(std::isnan(last->nis_mean));  // a refit has no innovations: NULL
  // The reference for a later full-window refit is a full-window one, not the 8 h refit.
  const auto reference =
      history.latest_accepted_refit("PAPER-1", static_cast<int64_t>(0.9 * 12 * hour), 1000);
  REQUIRE(reference);
  CHECK(reference->n_samples == 4320);
}
