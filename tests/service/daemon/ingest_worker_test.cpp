// The daemon's worker in-process: storage of valid samples, rejection counts, sequence gaps,
// snapshot cadence in data time, and restart continuity (restored or re-run filter state gives
// the same estimate as an uninterrupted run).
#include <catch2/catch.hpp>

#include "pipeline/time_utc.hpp"
#include "tests/process_support.hpp"
#include "tests/service/daemon/ingest_worker_fixture.hpp"

using namespace magcal;
using namespace magcal::worker_test;

TEST_CASE("valid samples are stored, bad ones counted per reason", "[ingest_worker]") {
  TempDb tmp("counts");
  const auto c = test_config(tmp.path());
  DaemonCounters counters;
  auto w = make_worker(c, counters);
  auto s = simulate(300, 1);
  // seq 50..52 never arrive: 3 missing.
  std::vector<mag_sample_t> stream(s.begin(), s.begin() + 50);
  stream.insert(stream.end(), s.begin() + 53, s.end());
  feed(*w, stream, 0, stream.size());
  CHECK(counters.stored == 297);
  CHECK(counters.missing_by_seq == 3);

  IngestItem bad;
  bad.batch_sat_id = "SAT-1";
  bad.from_batch = true;
  bad.samples.push_back(s[10]);  // duplicate
  auto older = s[299];
  older.utime -= 13LL * 3600 * 1000000;  // older than the 12 h window
  bad.samples.push_back(older);
  auto nan = s[299];
  nan.utime += kStep;
  nan.b_sensor_nT[0] = std::nan("");
  bad.samples.push_back(nan);
  auto mismatch = s[299];
  mismatch.sat_id = "SAT-9";
  bad.samples.push_back(mismatch);
  bad.samples.push_back(s[51]);  // late, out of order, inside the window: stored
  auto future = s[299];
  future.utime = kT0 + 10LL * 365 * 86400 * 1000000;
  bad.samples.push_back(future);
  w->process(bad);
  w->commit();
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 1);
  CHECK(counters.rejected_count(RejectReason::kOlderThanWindow) == 1);
  CHECK(counters.rejected_count(RejectReason::kNonFinite) == 1);
  CHECK(counters.rejected_count(RejectReason::kBatchSatMismatch) == 1);
  CHECK(counters.rejected_count(RejectReason::kFutureTime) == 1);
  CHECK(counters.rejected_total() == 5);
  CHECK(counters.stored == 298);

  storage::Database db(tmp.path());
  storage::SqliteSampleWindowStore store(db);
  CHECK(store.count("SAT-1") == 298);
  CHECK(store.count_in_window("SAT-1", s[51].utime, s[51].utime + 1) == 1);
}

TEST_CASE("per-spacecraft counters equal the worker's counts and the stored rows",
          "[ingest_worker][metrics]") {
  TempDb tmp("metrics");
  auto c = test_config(tmp.path());
  c.storage.commit_every_samples = 150;  // several transactions per spacecraft
  DaemonCounters counters;
  IngestWorker w(c, counters, std::make_unique<ReferenceField>(), IngestWorker::Hooks{});
  auto a = simulate(500, 3, "SAT-A");
  auto b = simulate(400, 4, "SAT-B");
  std::vector<mag_sample_t> a_gaps(a.begin(), a.begin() + 100);  // seq 100..104 never arrive
  a_gaps.insert(a_gaps.end(), a.begin() + 105, a.end());
  // Interleaved frames of the two spacecraft, then a repeat of a stored frame (duplicates).
  for (size_t i = 0; i < 400; i += 100) {
    w.process(batch(a_gaps, i, i + 100));
    w.process(batch(b, i, i + 100));
  }
  w.process(batch(a_gaps, 400, a_gaps.size()));
  w.process(batch(b, 100, 200));
  w.commit();
  storage::Database db(tmp.path());
  storage::SqliteSampleWindowStore store(db);
  const SpacecraftCounters& ca = counters.spacecraft.spacecraft("SAT-A");
  const SpacecraftCounters& cb = counters.spacecraft.spacecraft("SAT-B");
  CHECK(ca.stored.load() == store.count("SAT-A"));
  CHECK(cb.stored.load() == store.count("SAT-B"));
  CHECK(store.count("SAT-A") == 495);
  CHECK(ca.stored.load() + cb.stored.load() == counters.stored.load());
  CHECK(ca.missing.load() == 5);
  CHECK(cb.missing.load() == 0);
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 100);
  // One observation per transaction: 895 samples in chunks of 150 at least 6.
  int64_t commits = 0;
  for (const int64_t n : counters.commit_seconds.bucket_counts()) commits += n;
  CHECK(commits >= 6);
}

TEST_CASE("UKF snapshots follow the data clock", "[ingest_worker]") {
  TempDb tmp("snap");
  auto c = test_config(tmp.path());
  c.ukf.snapshot_every_s = 600.0;
  DaemonCounters counters;
  int published = 0;
  auto w = std::make_unique<IngestWorker>(
      c, counters, std::make_unique<ReferenceField>(),
      IngestWorker::Hooks{[&](const std::string&, const CalibrationResult&) { ++published; }, {}});
  const auto s = simulate(2161, 2, "SAT-1", 0.3);  // exactly six hours at 10 s
  feed(*w, s, 0, s.size());
  storage::Database db(tmp.path());
  storage::SqliteCalibrationHistory history(db);
  storage::HistoryQuery q;
  q.sat_id = "SAT-1";
  q.method = "ukf";
  const auto rows = history.query(q);
  {
    auto snap = w->fleet().find("SAT-1")->ukf.snapshot();
    INFO("status " << to_string(snap.status) << " " << snap.message);
    CHECK(w->fleet().find("SAT-1")->ukf.state().initialized);
  }
  // Nothing while the filter collects for its start from data (it has no estimate yet); from
  // its start, one snapshot per 600 s of data, on the grid set by the first sample.
  REQUIRE(rows.size() >= 2);
  CHECK(counters.snapshots == static_cast<int64_t>(rows.size()));
  CHECK(published == static_cast<int>(rows.size()));
  for (const auto& r : rows) CHECK((r.utime - kT0) % (600LL * 1000000) == 0);
  for (size_t k = 1; k < rows.size(); ++k)
    CHECK(rows[k].utime - rows[k - 1].utime == 600LL * 1000000);
  CHECK(rows.back().utime == kT0 + 21600LL * 1000000);
  CHECK(rows.size() < 36);  // not from the first sample: the start needed data
}

TEST_CASE("restart resumes the filter without a jump", "[ingest_worker]") {
  const auto s = simulate(2000, 3);
  Vector9d reference_x;
  Matrix9d reference_P;
  {
    TempDb tmp("ref");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    feed(*w, s, 0, s.size());
    reference_x = w->fleet().find("SAT-1")->ukf.x();
    reference_P = w->fleet().find("SAT-1")->ukf.P();
  }
  for (const bool saved_state : {true, false}) {
    DYNAMIC_SECTION((saved_state ? "from the stored filter state" : "re-run over stored samples")) {
      TempDb tmp(saved_state ? "saved" : "rerun");
      const auto c = test_config(tmp.path());
      DaemonCounters counters;
      {
        auto w = make_worker(c, counters);
        feed(*w, s, 0, 1000);
        if (saved_state) w->save_filter_states();  // else: a crash after the commit
      }
      auto w = make_worker(c, counters);
      w->restore();
      REQUIRE(w->n_spacecraft() == 1);
      feed(*w, s, 1000, s.size());
      const auto& ukf = w->fleet().find("SAT-1")->ukf;
      CHECK(counters.stored == 2000);
      CHECK(counters.rejected_total() == 0);
      CHECK(counters.missing_by_seq == 0);
      const double dx = (ukf.x() - reference_x)
                            .cwiseQuotient(reference_x.cwiseAbs().cwiseMax(1e-3))
                            .cwiseAbs()
                            .maxCoeff();
      CHECK(dx < kStateTol);
      CHECK((ukf.P() - reference_P).norm() <= kStateTol * reference_P.norm());
    }
  }
}

TEST_CASE("a refit accepted just before a crash is re-anchored on at the restart",
          "[ingest_worker]") {
  // The daemon dies after the refit is stored but before the re-anchored filter is: a restart
  // that re-ran the stored samples without it would say not_converged where the uninterrupted
  // run says ok. The filter here cannot start from data (constant |h|): only the re-anchor starts
  // it.
  const auto s = simulate(2000, 7);
  const CalibrationResult refit = accepted_refit(s);
  // Uninterrupted: re-anchored before the samples after the refit's.
  const FilterState want = anchored_run(s, refit);
  REQUIRE(want.initialized);
  REQUIRE(want.model_error_known);
  for (const bool stored : {false, true}) {
    DYNAMIC_SECTION((stored ? "the re-anchored state was stored" : "it was not")) {
      TempDb tmp(stored ? "reanchor-stored" : "reanchor-lost");
      const auto c = test_config(tmp.path());
      DaemonCounters counters;
      {
        auto w = make_worker(c, counters);
        feed(*w, s, 0, 1000);
        w->post_reanchor("SAT-1", refit, store_refit(tmp.path(), refit));
        if (stored) w->commit_if_due();  // applies it; the state goes into the next commit
      }                                  // killed: nothing more is written
      auto w = make_worker(c, counters);
      w->restore();
      feed(*w, s, 1000, s.size());
      const FilterState& got = w->fleet().find("SAT-1")->ukf.state();
      CHECK(got.initialized);
      CHECK(got.model_error_known);
      CHECK(got.n_accepted == want.n_accepted);
      CHECK((got.model_error_covariance - want.model_error_covariance).norm() <=
            kStateTol * want.model_error_covariance.norm());
      CHECK(relative_difference(got.x, want.x) < kStateTol);
      CHECK((got.S - want.S).norm() <= kStateTol * want.S.norm());
    }
  }
}

TEST_CASE("the anchor refit's temperature model: snapshots carry it, a restart re-runs with it",
          "[ingest_worker]") {
  // Samples after the anchor are corrected to the refit's T0; a restart that re-runs
  // stored samples must correct them the same way (the model comes back from the history).
  const Eigen::Vector3d k_T(1.5, -1.0, 2.0);
  const auto s = simulate(2000, 13, "SAT-1", 0.0, k_T);
  CalibrationResult refit = accepted_refit(s);
  refit.has_temperature_model = true;
  refit.reference_temperature_C = kThermalMean_C;
  refit.temperature_coefficient_nT_per_C = k_T + Eigen::Vector3d(0.01, -0.02, 0.01);
  refit.temperature_coefficient_covariance = Eigen::Vector3d(4e-4, 4e-4, 4e-4).asDiagonal();

  SECTION("snapshots after the anchor report its model and name the refit") {
    TempDb tmp("thermal-snapshots");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    feed(*w, s, 0, 1000);  // constant |h|: no start from data, no snapshot before the anchor
    const int64_t id = store_refit(tmp.path(), refit);
    w->post_reanchor("SAT-1", refit, id);
    feed(*w, s, 1000, 1100);
    REQUIRE(w->fleet().find("SAT-1")->temperature.active);
    storage::Database d(tmp.path());
    storage::HistoryQuery q;
    q.sat_id = "SAT-1";
    q.method = "ukf";
    const auto rows = storage::SqliteCalibrationHistory(d).query(q);
    REQUIRE(rows.size() >= 10);
    for (const auto& r : rows) {
      CHECK(r.has_temperature_model == 1);
      CHECK(r.temperature_model_refit_id == id);
      CHECK(r.reference_temperature_C == kThermalMean_C);
      CHECK(r.temperature_coefficient_nT_per_C[2] == refit.temperature_coefficient_nT_per_C(2));
    }
  }

  SECTION("a crash after the anchored state was stored: the re-run is corrected too") {
    // No snapshots (they store the state with every commit): the stored state stays at the
    // anchor's commit and the restart re-runs everything after it.
    constexpr double kNoSnapshots_s = 1e7;
    const FilterState want = anchored_run(s, refit, kNoSnapshots_s);
    TempDb tmp("thermal-crash");
    DaemonConfig c = test_config(tmp.path());
    c.ukf.snapshot_every_s = kNoSnapshots_s;
    DaemonCounters counters;
    int64_t id = 0;
    {
      auto w = make_worker(c, counters);
      feed(*w, s, 0, 1000);
      id = store_refit(tmp.path(), refit);
      w->post_reanchor("SAT-1", refit, id);
      feed(*w, s, 1000, 1200);  // the re-anchored state goes in with this commit
      feed(*w, s, 1200, s.size());
    }  // killed: the last 800 samples are stored, the state is not
    {
      storage::Database d(c.storage.db_path);
      const auto stored = storage::SqliteFilterStateStore(d).load("SAT-1", "ukf");
      REQUIRE(stored);
      REQUIRE(stored->last_utime == s[1199].utime);
      CHECK(stored->anchor_calibration_id == id);
    }
    auto w = make_worker(c, counters);
    w->restore();
    w->commit_if_due();  // the owner's filter reads the stored samples after its state
    const SpacecraftTracker& t = *w->fleet().find("SAT-1");
    CHECK(t.temperature.active);
    CHECK(t.temperature.refit_id == id);
    CHECK(t.ukf.state().n_accepted == want.n_accepted);
    CHECK(relative_difference(t.ukf.state().x, want.x) < kStateTol);
    CHECK((t.ukf.state().S - want.S).norm() <= kStateTol * want.S.norm());
  }
}

TEST_CASE("restart while the filter still collects for its start: no sample counted twice",
          "[ingest_worker]") {
  // A state saved before the start holds its samples in the start's moments: the restart must
  // not re-run them (else a SIGTERM at 596 samples would restart at n=1444).
  const auto s = simulate(2000, 5);
  TempDb ref_db("collect-ref");
  DaemonCounters ref_counters;
  auto reference = make_worker(test_config(ref_db.path()), ref_counters);
  feed(*reference, s, 0, s.size());
  const FilterState& want = reference->fleet().find("SAT-1")->ukf.state();

  TempDb tmp("collect");
  const auto c = test_config(tmp.path());
  DaemonCounters counters;
  {
    auto w = make_worker(c, counters);
    feed(*w, s, 0, 400);
    REQUIRE(counters.stored == 400);
    REQUIRE(w->fleet().find("SAT-1")->ukf.state().moments.n == 400);
    REQUIRE_FALSE(w->fleet().find("SAT-1")->ukf.initialized());  // still collecting
    w->save_filter_states();
  }
  auto w = make_worker(c, counters);
  w->restore();
  REQUIRE(w->fleet().find("SAT-1") != nullptr);
  CHECK(w->fleet().find("SAT-1")->ukf.state().moments.n == 400);
  feed(*w, s, 400, s.size());
  const FilterState& got = w->fleet().find("SAT-1")->ukf.state();
  CHECK(got.moments.n == want.moments.n);
  CHECK(got.n_accepted == want.n_accepted);
  CHECK((got.x - want.x).cwiseQuotient(want.x.cwiseAbs().cwiseMax(1e-3)).cwiseAbs().maxCoeff() <
        kStateTol);
}

TEST_CASE("an unwritable database is an error at construction", "[ingest_worker]") {
  DaemonCounters counters;
  auto c = test_config("/nonexistent-dir/sub/m.db");
  CHECK_THROWS_AS(make_worker(c, counters), storage::StorageError);
}

TEST_CASE("one corrupt sequence number implies no missing samples", "[ingest_worker]") {
  // Random draws: a steady sequence with one corrupted seq (bit flips, +1e6, garbage) in it,
  // and real gaps elsewhere; only the real gaps count.
  std::mt19937_64 rng(7);
  for (int draw = 0; draw < 200; ++draw) {
    SpacecraftTracker t(std::make_shared<const MagnetometerUkf::Options>());
    int64_t seq = static_cast<int64_t>(rng() % 1000);
    int64_t missing = 0, real_gaps = 0;
    for (int k = 0; k < 60; ++k) {
      if (k == 30) {
        const int64_t corrupt[] = {seq + 1'000'000, seq ^ (int64_t{1} << (rng() % 62)),
                                   static_cast<int64_t>(rng()),
                                   seq + 2 + static_cast<int64_t>(rng() % 50)};
        missing += t.received_seq.observe(corrupt[draw % 4]);
        continue;  // the corrupt frame replaced this sample; the stream goes on
      }
      if (k % 17 == 5) {  // a real gap of 1..5 samples
        const int64_t gap = 1 + static_cast<int64_t>(rng() % 5);
        seq += gap;
        real_gaps += gap;
      }
      missing += t.received_seq.observe(++seq);
    }
    INFO("draw " << draw);
    CHECK(missing == real_gaps);
  }
}

TEST_CASE("stored filter state round trip is bit-exact, collecting and started",
          "[ingest_worker]") {
  // service/io/calibration_record.cpp (MCF2 blob): what the daemon saves and restores.
  std::mt19937_64 rng(9);
  std::normal_distribution<double> n(0.0, 1.0);
  MagnetometerUkf ukf;
  const Eigen::Vector3d b(1000.0, 800.0, 900.0);
  Vector9d model_error;  // a refit's p_9 - p (reanchor), in the blob since session 5
  model_error << 1.2, -4.2, 0.1, 1e-5, 2e-5, -3e-5, 4e-6, -5e-5, 6e-6;
  for (int k = 0; k < 400; ++k) {
    const Eigen::Vector3d h = 40000.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    ukf.update(h + b + 3.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)), 40000.0,
               kT0 + k * 10'000'000LL);
    if (k == 200) ukf.reanchor(ukf.x(), ukf.P(), model_error * model_error.transpose());
    if (k == 20 || k == 399) {
      INFO("sample " << k << ", started " << ukf.initialized());
      FilterState back;
      REQUIRE(filter_state_from_stored(stored_filter_state("SAT-1", "ukf", ukf.state()), back) ==
              "");
      CHECK(back == ukf.state());
    }
  }
  CHECK(ukf.initialized());
}

TEST_CASE("duplicates are found in the pending batch and in the store, per spacecraft",
          "[ingest_worker]") {
  // Two spacecraft on interleaved time grids (B a third of a step after A), one sample per
  // frame, nothing committed yet: repeats must be found among the pending rows, a sample of A
  // at one of B's times is new, and after the commit the repeats are found in the store.
  TempDb tmp("dups");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  const auto a = simulate(200, 21, "SAT-A");
  auto b = simulate(200, 22, "SAT-B");
  for (auto& s : b) s.utime += kStep / 3;
  for (size_t k = 0; k < a.size(); ++k) {
    w->process(single(a[k]));
    w->process(single(b[k]));
  }
  REQUIRE(w->pending_samples() == 400);  // nothing committed: the checks below hit the batch
  for (size_t k = 100; k < 150; ++k) w->process(single(a[k]));
  for (size_t k = 0; k < 50; ++k) w->process(single(b[k]));
  auto a_at_b_time = a[120];
  a_at_b_time.utime = b[120].utime;
  w->process(single(a_at_b_time));
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 100);
  w->commit();
  for (size_t k = 0; k < 50; ++k) w->process(single(a[k]));
  w->process(single(a_at_b_time));
  w->commit();
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 151);
  CHECK(counters.rejected_total() == 151);
  CHECK(counters.stored == 401);
  CHECK(stored_rows(tmp.path(), "SAT-A") == 201);
  CHECK(stored_rows(tmp.path(), "SAT-B") == 200);
}

TEST_CASE(
    "a new spacecraft's early refits: due by stored count, keyed by it, once across a restart",
    "[ingest_worker][refit]") {
  TempDb tmp("early");
  const auto c = test_config(tmp.path());
  const EarlyRefitPlan plan = c.early_refits();
  // 12 h at 10 s: the stored span reaches window_hours at sample 4321.
  const auto s = simulate(6000, 5, "SAT-1", 0.05);
  const int64_t full_window_samples = c.window_utime() / kStep + 1;
  std::vector<int64_t> expected;  // the plan's counts below a full window
  for (int64_t n = plan.next_after(0); n > 0 && n < full_window_samples; n = plan.next_after(n)) {
    expected.push_back(n);
  }
  REQUIRE(expected.size() >= 3);

  struct Due {
    int64_t t_ref;
    storage::RefitTrigger trigger;
  };
  std::vector<Due> due;
  IngestWorker::Hooks hooks;
  hooks.on_refit_due = [&](const std::string&, int64_t t_ref, storage::RefitTrigger trigger) {
    due.push_back({t_ref, trigger});
  };
  DaemonCounters counters;
  const size_t split = static_cast<size_t>(expected[2]) + 300;  // after the third
  {
    IngestWorker w(c, counters, std::make_unique<ReferenceField>(), hooks);
    w.restore();
    feed(w, s, 0, split);
  }
  REQUIRE(due.size() == 3);
  // The refit thread ran the first two only (the third was lost with the process).
  {
    storage::Database db(c.storage.db_path);
    storage::SqliteCalibrationHistory history(db);
    for (int k = 0; k < 2; ++k) {
      CalibrationResult r;
      r.method = "twostep";
      r.utime = due[static_cast<size_t>(k)].t_ref;
      r.n_samples = static_cast<int>(expected[static_cast<size_t>(k)]);
      history.append(record_from_result("SAT-1", r));
    }
  }
  {
    IngestWorker w(c, counters, std::make_unique<ReferenceField>(), hooks);
    w.restore();
    feed(w, s, split, s.size());
  }
  // The third again (its result is not in the database), then the rest, and none after the
  // stored span reached window_hours.
  REQUIRE(due.size() == expected.size() + 1);
  std::vector<int64_t> counts;
  for (size_t k = 0; k < due.size(); ++k) {
    INFO("request " << k);
    CHECK(due[k].trigger ==
          (k == 0 ? storage::RefitTrigger::kFirst : storage::RefitTrigger::kEarly));
    // Keyed by the count: its window ends at the N-th stored sample.
    counts.push_back((due[k].t_ref - kT0) / kStep + 1);
  }
  std::vector<int64_t> want = expected;
  want.insert(want.begin() + 3, expected[2]);
  CHECK(counts == want);
}

TEST_CASE(
    "the owner's filter stays the reorder delay behind the newest stored sample, and takes "
    "the end of a pass once it has been quiet that long",
    "[ingest_worker]") {
  const auto s = simulate(300, 17);
  const size_t n = s.size();
  SECTION("25 s of data time: the samples within 25 s of the newest (three, 10 s apart) wait") {
    TempDb tmp("reorder");
    DaemonConfig c = test_config(tmp.path());
    c.fleet.reorder_delay_s = 25.0;
    DaemonCounters counters;
    auto w = make_worker(c, counters);
    feed(*w, s, 0, n);
    const SpacecraftTracker& t = *w->fleet().find("SAT-1");
    REQUIRE(t.owned);  // alone: this daemon owns what it receives
    CHECK(t.filtered_utime == s[n - 4].utime);
    CHECK(counters.ukf_updates == static_cast<int64_t>(n) - 3);
  }
  SECTION("no more samples come (the pass is over): taken after the delay in wall time") {
    TempDb tmp("reorder-quiet");
    DaemonConfig c = test_config(tmp.path());
    c.fleet.reorder_delay_s = 1.0;  // the last sample waits (its predecessor is 10 s older)
    DaemonCounters counters;
    auto w = make_worker(c, counters);
    // The worker's own clock (wall time): the tail's last growth came after this.
    const int64_t fed_utime = now_utime();
    feed(*w, s, 0, n);
    const SpacecraftTracker& t = *w->fleet().find("SAT-1");
    CHECK(t.filtered_utime == s[n - 2].utime);
    // Polled as the worker's thread does (nothing new to commit): the poll finds the quiet tail,
    // and not before the delay has passed.
    REQUIRE(magcal::test::wait_until(
        [&] {
          w->commit_if_due();
          return t.filtered_utime == s[n - 1].utime;
        },
        10));
    CHECK(now_utime() - fed_utime >= c.reorder_delay_utime());
    CHECK(counters.ukf_updates == static_cast<int64_t>(n));
  }
}
