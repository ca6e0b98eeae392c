// The daemon's worker in-process: storage of valid samples, rejection counts, sequence gaps,
// snapshot cadence in data time, and restart continuity (restored or re-run filter state gives
// the same estimate as an uninterrupted run).
#include <catch2/catch.hpp>

#include <unistd.h>
#include <cmath>
#include <filesystem>
#include <numbers>
#include <random>

#include "pipeline/rotation.hpp"
#include "service/daemon/ingest_worker.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/calibration_history.hpp"
#include "storage/refit_job_log.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/sqlite_stores.hpp"

using namespace magcal;

namespace {

constexpr int64_t kT0 = 1704067200000000;  // 2024-01-01T00:00:00Z
constexpr int64_t kStep = 10'000'000;      // 10 s
constexpr double kNoise_nT = 3.0;
constexpr double kStateTol = 1e-9;  // relative; restore is meant to be bit-exact

struct TempDb {
  std::filesystem::path dir;
  explicit TempDb(const std::string& name) {
    static int counter = 0;
    dir = std::filesystem::temp_directory_path() /
          ("magcal_worker_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++) +
           "_" + name);
    std::filesystem::remove_all(dir);
    std::filesystem::create_directories(dir);
  }
  ~TempDb() { std::filesystem::remove_all(dir); }
  std::string path() const { return (dir / "m.db").string(); }
};

constexpr double kThermalMean_C = 20.0;

// Truth: B = (I + D)^-1 (h + b) + noise, h a tumbling 30 000 nT field in the body frame.
// |h| is constant unless magnitude_variation > 0: then it swings by that fraction over ~2.5 h
// and the direction turns 10x faster (a tumbling spacecraft), which lets the filter start from
// data; with constant |h| that start never comes (bias and scale are degenerate).
// A non-zero k_T adds a thermal bias k_T (T - kThermalMean_C), T swinging +-15 degC every
// ~95 min, and the samples carry T (else their temperature is unknown).
std::vector<mag_sample_t> simulate(int n, uint32_t seed, const std::string& sat = "SAT-1",
                                   double magnitude_variation = 0.0,
                                   const Eigen::Vector3d& k_T = Eigen::Vector3d::Zero()) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, kNoise_nT);
  const Eigen::Vector3d b(1000.0, -800.0, 900.0);
  Eigen::Matrix3d D;
  D << 0.01, 0.002, -0.001, 0.002, 0.02, 0.003, -0.001, 0.003, -0.01;
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + D).inverse();
  std::vector<mag_sample_t> out;
  for (int k = 0; k < n; ++k) {
    const double rate = magnitude_variation > 0.0 ? 10.0 : 1.0;
    const double a = 0.0021 * rate * k, c = 0.0013 * rate * k;
    const Eigen::Vector3d h =
        30000.0 * (1.0 + magnitude_variation * std::sin(0.0007 * k)) *
        Eigen::Vector3d(std::cos(a) * std::cos(c), std::sin(a) * std::cos(c), std::sin(c));
    const double T = kThermalMean_C + 15.0 * std::sin(2.0 * std::numbers::pi * k / 570.0);
    const Eigen::Vector3d B = inv * (h + b + k_T * (T - kThermalMean_C)) +
                              Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    mag_sample_t s{};
    s.utime = kT0 + k * kStep;
    s.sat_id = sat;
    s.seq = k;
    for (int i = 0; i < 3; ++i) {
      s.b_sensor_nT[i] = B(i);
      s.h_body_nT[i] = h(i);
    }
    s.has_reference = true;
    s.temperature_C = k_T.isZero() ? std::nanf("") : static_cast<float>(T);
    out.push_back(s);
  }
  return out;
}

DaemonConfig test_config(const std::string& db) {
  DaemonConfig c;
  c.storage.db_path = db;
  c.ukf.filter.sigma_nT = kNoise_nT;
  // One station: its filter takes each committed sample at once (the reorder delay has its
  // own test).
  c.fleet.reorder_delay_s = 0.0;
  return c;
}

IngestItem batch(const std::vector<mag_sample_t>& all, size_t from, size_t to) {
  IngestItem it;
  it.from_batch = true;
  it.batch_sat_id = all.front().sat_id;
  it.samples.assign(all.begin() + static_cast<long>(from), all.begin() + static_cast<long>(to));
  it.receive_utime = kT0 + 365LL * 86400 * 1000000;
  return it;
}

void feed(IngestWorker& w, const std::vector<mag_sample_t>& all, size_t from, size_t to) {
  for (size_t i = from; i < to; i += 200) w.process(batch(all, i, std::min(to, i + 200)));
  w.commit();
}

std::unique_ptr<IngestWorker> make_worker(const DaemonConfig& c, DaemonCounters& counters) {
  return std::make_unique<IngestWorker>(c, counters, std::make_unique<ReferenceField>(),
                                        IngestWorker::Hooks{});
}

// An accepted refit of the first 1000 samples of `s` (near simulate()'s truth), as RefitRunner
// stores it and hands it to the worker.
CalibrationResult accepted_refit(const std::vector<mag_sample_t>& s) {
  CalibrationResult refit;
  refit.method = "twostep";
  refit.utime = refit.window_end_utime = s[999].utime;
  refit.window_start_utime = s[0].utime;
  refit.n_samples = 1000;
  Vector9d p;
  p << 1001.0, -799.0, 902.0, 0.01, 0.02, -0.01, 0.002, -0.001, 0.003;
  refit.parameters = CalibrationParameters::from_packed(p);
  Vector9d variance;
  variance << 4.0, 5.0, 6.0, 1e-6, 2e-6, 3e-6, 1e-6, 1e-6, 1e-6;
  refit.covariance = variance.asDiagonal();
  refit.model_error << 0.5, -0.3, 0.2, 1e-4, -2e-4, 1e-4, 3e-5, -1e-5, 2e-5;
  refit.residual_rms_nT = 3.3;
  refit.status = CalibrationStatus::kOk;
  refit.accepted = true;
  return refit;
}

// Stores `refit` with its finished job (what the restart's re-anchor looks up); returns its id.
int64_t store_refit(const std::string& db, const CalibrationResult& refit) {
  storage::Database d(db);
  storage::SqliteCalibrationHistory history(d);
  storage::SqliteRefitJobLog jobs(d);
  const int64_t job = jobs.start("SAT-1", "scheduled", refit.utime, 1);
  const int64_t id = history.append(record_from_result("SAT-1", refit));
  jobs.finish(job, storage::job_outcome::kOk, 2, "", id);
  return id;
}

// The filter state of an uninterrupted run over `s`, re-anchored on `refit` after 1000 samples.
FilterState anchored_run(const std::vector<mag_sample_t>& s, const CalibrationResult& refit,
                         double snapshot_every_s = DaemonConfig{}.ukf.snapshot_every_s) {
  TempDb tmp("anchored-run");
  DaemonConfig c = test_config(tmp.path());
  c.ukf.snapshot_every_s = snapshot_every_s;
  DaemonCounters counters;
  auto w = make_worker(c, counters);
  feed(*w, s, 0, 1000);
  w->post_reanchor("SAT-1", refit, store_refit(tmp.path(), refit));
  feed(*w, s, 1000, s.size());
  return w->fleet().find("SAT-1")->ukf.state();
}

double relative_difference(const Vector9d& got, const Vector9d& want) {
  return (got - want).cwiseQuotient(want.cwiseAbs().cwiseMax(1e-3)).cwiseAbs().maxCoeff();
}

}  // namespace

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
  // Issue 21: the daemon died after the refit was stored but before the re-anchored filter was;
  // the restart re-ran the stored samples without it (not_converged where the uninterrupted run
  // said ok). The filter here cannot start from data (constant |h|): only the re-anchor starts it.
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
  // Issue 20: samples after the anchor are corrected to the refit's T0; a restart that re-runs
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
  // not re-run them (found by a fresh-user trial: SIGTERM at 596 samples gave a start at n=1444).
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

// ---- time plausibility (issue 11): one frame cannot move a spacecraft's time ----

namespace {

constexpr int64_t kHour = 3600LL * 1000000;

IngestItem single(const mag_sample_t& s) {
  IngestItem it;
  it.samples.push_back(s);
  it.receive_utime = kT0 + 365LL * 86400 * 1000000;
  return it;
}

// One frame per sample, as a live mag_sample_t feed; then the shutdown step.
void feed_frames(IngestWorker& w, const std::vector<mag_sample_t>& frames) {
  for (const auto& s : frames) w.process(single(s));
  w.settle_held();
  w.commit();
}

int64_t stored_rows(const std::string& db_path, const std::string& sat = "SAT-1") {
  storage::Database db(db_path);
  storage::SqliteSampleWindowStore store(db);
  return store.count(sat);
}

}  // namespace

TEST_CASE("one rogue time tag is rejected and every valid sample kept", "[ingest_worker][time]") {
  const auto valid = simulate(400, 11);
  struct Case {
    const char* name;
    int64_t utime;
    RejectReason expect;
  };
  const int64_t mid = valid[200].utime;
  const Case cases[] = {
      {"20 h ahead", mid + 20 * kHour, RejectReason::kTimeJump},
      {"2 h ahead", mid + 2 * kHour, RejectReason::kTimeJump},
      {"20 h behind", mid - 20 * kHour, RejectReason::kOlderThanWindow},
      {"utime 0", 0, RejectReason::kTimeOutOfRange},
      {"int64 min", std::numeric_limits<int64_t>::min(), RejectReason::kTimeOutOfRange},
      {"int64 max", std::numeric_limits<int64_t>::max(), RejectReason::kTimeOutOfRange},
      {"past the wall clock", kT0 + 400LL * 86400 * 1000000, RejectReason::kFutureTime},
  };
  for (const auto& c : cases) {
    for (const size_t at : {size_t{0}, size_t{1}, size_t{200}, valid.size()}) {
      DYNAMIC_SECTION(c.name << " at frame " << at) {
        TempDb tmp("rogue");
        DaemonCounters counters;
        auto w = make_worker(test_config(tmp.path()), counters);
        auto frames = valid;
        auto rogue = valid[std::min(at, valid.size() - 1)];
        rogue.utime = c.utime;
        frames.insert(frames.begin() + static_cast<long>(at), rogue);
        feed_frames(*w, frames);
        const auto expect = at == valid.size() && c.expect == RejectReason::kTimeJump
                                ? RejectReason::kJumpUnconfirmed  // last: nothing followed
                                : c.expect;
        CHECK(counters.stored == static_cast<int64_t>(valid.size()));
        CHECK(counters.rejected_count(expect) == 1);
        CHECK(counters.rejected_total() == 1);
        CHECK(stored_rows(tmp.path()) == static_cast<int64_t>(valid.size()));
        CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
        CHECK(w->data_clock_utime() == valid.back().utime);
        CHECK(w->held_samples() == 0);
      }
    }
  }
}

TEST_CASE("a genuine gap is accepted once later samples corroborate it", "[ingest_worker][time]") {
  auto frames = simulate(300, 12);
  for (size_t k = 150; k < frames.size(); ++k) frames[k].utime += 3 * kHour;  // 3 h gap
  TempDb tmp("gap");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  for (size_t k = 0; k < 152; ++k) w->process(single(frames[k]));
  // The first two after the gap are held: not stored, not in the filter, not the time base.
  CHECK(w->held_samples() == 2);
  CHECK(w->fleet().find("SAT-1")->newest_utime == frames[149].utime);
  CHECK(w->data_clock_utime() == frames[149].utime);
  for (size_t k = 152; k < frames.size(); ++k) w->process(single(frames[k]));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 300);
  CHECK(counters.rejected_total() == 0);
  CHECK(w->fleet().find("SAT-1")->newest_utime == frames.back().utime);
  // Stored in order, each once.
  storage::Database db(tmp.path());
  storage::SqliteSampleWindowStore store(db);
  std::vector<storage::StoredSample> rows;
  store.read_window("SAT-1", frames.front().utime, frames.back().utime + 1, rows);
  REQUIRE(rows.size() == 300);
  for (size_t k = 0; k < rows.size(); ++k) CHECK(rows[k].utime == frames[k].utime);
}

TEST_CASE("a recorder dump of older in-window samples is accepted", "[ingest_worker][time]") {
  const auto s = simulate(600, 13);
  TempDb tmp("dump");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  std::vector<mag_sample_t> frames(s.begin() + 300, s.end());  // live first
  frames.insert(frames.end(), s.begin(), s.begin() + 300);     // then the recorder's dump
  feed_frames(*w, frames);
  CHECK(counters.stored == 600);
  CHECK(counters.rejected_total() == 0);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);
}

TEST_CASE("the first samples of a spacecraft need corroboration too", "[ingest_worker][time]") {
  const auto valid = simulate(100, 14);
  SECTION("a rogue first frame does not set the time base") {
    for (const int64_t offset : {20 * kHour, -20 * kHour, 400 * 24 * kHour}) {
      TempDb tmp("first");
      DaemonCounters counters;
      auto w = make_worker(test_config(tmp.path()), counters);
      auto frames = valid;
      auto rogue = valid[0];
      rogue.utime += offset;
      frames.insert(frames.begin(), rogue);
      feed_frames(*w, frames);
      INFO("offset " << offset / kHour << " h");
      CHECK(counters.stored == 100);
      CHECK(counters.rejected_total() == 1);
      CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
    }
  }
  SECTION("one batch frame cannot set it alone; the next frame confirms it") {
    TempDb tmp("batch");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 10));
    CHECK(w->held_samples() == 10);
    CHECK(counters.stored == 0);
    w->process(single(valid[10]));
    CHECK(w->held_samples() == 0);
    w->commit();
    CHECK(counters.stored == 11);
  }
  SECTION("a spacecraft that only ever sent one frame: stored at shutdown") {
    TempDb tmp("lonely");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 5));
    CHECK(w->held_samples() == 5);
    w->settle_held();
    w->commit();
    CHECK(counters.stored == 5);
    CHECK(counters.rejected_total() == 0);
    CHECK(stored_rows(tmp.path()) == 5);
    CHECK(w->fleet().find("SAT-1")->newest_utime == valid[4].utime);
  }
  SECTION("too few single frames to corroborate: stored at shutdown") {
    TempDb tmp("few");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    for (size_t k = 0; k < static_cast<size_t>(SpacecraftTracker::kCorroborating); ++k) {
      w->process(single(valid[k]));
    }
    CHECK(w->held_samples() == SpacecraftTracker::kCorroborating);
    w->settle_held();
    w->commit();
    CHECK(counters.stored == SpacecraftTracker::kCorroborating);
    CHECK(counters.rejected_total() == 0);
  }
  SECTION("held first samples are stored after kFirstHoldMax_s, without a shutdown") {
    TempDb tmp("bounded");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 3));
    const auto now = std::chrono::steady_clock::now();
    w->release_first_holds(now);  // not yet
    CHECK(w->held_samples() == 3);
    w->release_first_holds(
        now + std::chrono::duration_cast<std::chrono::nanoseconds>(
                  std::chrono::duration<double>(SpacecraftTracker::kFirstHoldMax_s + 0.1)));
    CHECK(w->held_samples() == 0);
    w->commit();
    CHECK(counters.stored == 3);
    // Later samples go on from that base as usual.
    for (size_t k = 3; k < valid.size(); ++k) w->process(single(valid[k]));
    w->settle_held();
    w->commit();
    CHECK(counters.stored == static_cast<int64_t>(valid.size()));
    CHECK(counters.rejected_total() == 0);
  }
  SECTION("at shutdown a lone rogue among uncorroborated first samples is outvoted") {
    for (const int64_t offset : {20 * kHour, -20 * kHour}) {
      TempDb tmp("outvoted");
      DaemonCounters counters;
      auto w = make_worker(test_config(tmp.path()), counters);
      auto rogue = valid[0];
      rogue.utime += offset;
      w->process(single(rogue));
      w->process(single(valid[0]));
      w->process(single(valid[1]));
      w->settle_held();
      w->commit();
      INFO("offset " << offset / kHour << " h");
      CHECK(counters.stored == 2);
      CHECK(counters.rejected_total() == 1);
      CHECK(counters.rejected_count(offset > 0 ? RejectReason::kJumpUnconfirmed
                                               : RejectReason::kOlderThanWindow) == 1);
      CHECK(w->fleet().find("SAT-1")->newest_utime == valid[1].utime);
    }
  }
}

TEST_CASE("a whole downlink packet with a shifted time base cannot move the time",
          "[ingest_worker][time]") {
  // One mag_batch_t of 200 samples, all consistently 20 h ahead (a corrupted packet time base):
  // one frame, however many samples, never corroborates itself.
  const auto s = simulate(1000, 17);
  TempDb tmp("packet");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  feed(*w, s, 0, 400);
  auto shifted = batch(s, 400, 600);
  for (auto& x : shifted.samples) x.utime += 20 * kHour;
  w->process(shifted);
  CHECK(w->held_samples() == 200);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s[399].utime);
  for (size_t k = 400; k < s.size(); k += 200) w->process(batch(s, k, k + 200));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 1000);
  CHECK(counters.rejected_count(RejectReason::kTimeJump) == 200);
  CHECK(stored_rows(tmp.path()) == 1000);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);
}

TEST_CASE("a shifted batch frame cannot move the time, the hold stays bounded",
          "[ingest_worker][time]") {
  const auto s = simulate(400, 15);
  TempDb tmp("shifted");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  // Frame by frame: a new spacecraft's time base needs samples from more than one frame.
  for (size_t k = 0; k < 200; ++k) w->process(single(s[k]));
  REQUIRE(w->held_samples() == 0);
  auto shifted = batch(s, 200, 220);  // 20 consistent samples, all 20 h ahead
  for (auto& x : shifted.samples) x.utime += 20 * kHour;
  w->process(shifted);
  CHECK(w->held_samples() == 20);
  // Repeated rogues are duplicates of what is held, not corroboration.
  w->process(shifted);
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 20);
  for (size_t k = 200; k < s.size(); ++k) w->process(single(s[k]));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 400);
  CHECK(counters.rejected_count(RejectReason::kTimeJump) == 20);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);

  // Many mutually inconsistent rogues: the hold never exceeds its capacity.
  for (int k = 0; k < 100; ++k) {
    auto r = s.back();
    r.utime += (2 + 2 * k) * kHour;  // 2 h apart: none corroborates another
    w->process(single(r));
    CHECK(w->held_samples() <= SpacecraftTracker::kHeldCapacity);
  }
  w->settle_held();
  CHECK(counters.rejected_count(RejectReason::kTimeJump) +
            counters.rejected_count(RejectReason::kJumpUnconfirmed) ==
        120);
}

TEST_CASE("random rogue frames never cost a valid sample", "[ingest_worker][time]") {
  const auto valid = simulate(300, 16);
  std::mt19937_64 rng(20261130);
  std::uniform_int_distribution<size_t> position(0, valid.size());
  std::uniform_int_distribution<int> n_rogues(1, SpacecraftTracker::kCorroborating);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const int64_t window = DaemonConfig{}.window_utime();
  const int64_t jump = DaemonConfig{}.max_time_jump_utime();
  for (int draw = 0; draw < 40; ++draw) {
    auto frames = valid;
    const int n = n_rogues(rng);
    int64_t previous = 0;
    for (int r = 0; r < n; ++r) {
      auto rogue = valid[std::min(position(rng), valid.size() - 1)];
      // Ahead by more than the jump, behind by more than the window, or garbage; rogues far
      // apart from each other (fewer than kCorroborating + 1 can never corroborate anyway).
      const double u = unit(rng);
      if (u < 0.45) {
        rogue.utime = std::max(previous, valid.back().utime) + jump + 1 +
                      static_cast<int64_t>(unit(rng) * 1e4 * 3.6e9);
        previous = rogue.utime + jump + 1;
      } else if (u < 0.9) {
        rogue.utime =
            valid.front().utime - window - 1 - static_cast<int64_t>(unit(rng) * 1e4 * 3.6e9);
      } else {
        rogue.utime = static_cast<int64_t>(rng());
      }
      frames.insert(frames.begin() + static_cast<long>(position(rng)), rogue);
    }
    TempDb tmp("draw");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    feed_frames(*w, frames);
    INFO("draw " << draw << ": " << n << " rogues");
    CHECK(counters.stored == static_cast<int64_t>(valid.size()));
    CHECK(counters.rejected_total() == n);
    CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
  }
}

TEST_CASE("sequence numbers at the int64 limits do not overflow", "[ingest_worker][time]") {
  SpacecraftTracker t(std::make_shared<const MagnetometerUkf::Options>());
  constexpr int64_t kMax = std::numeric_limits<int64_t>::max();
  constexpr int64_t kMin = std::numeric_limits<int64_t>::min();
  CHECK(t.received_seq.observe(kMin + 1) == 0);
  CHECK(t.received_seq.observe(kMax) == 0);  // a reset, not 2^64 missing
  CHECK(t.received_seq.last_seq == kMax);
  CHECK(t.received_seq.observe(kMin + 1) == 0);
  CHECK(t.received_seq.observe(kMin + 4) == 0);  // a gap of 2, not yet confirmed
  CHECK(t.received_seq.observe(kMin + 5) == 2);  // confirmed
  CHECK(t.received_seq.observe(kMin) == 0);      // older: the edge stays
  CHECK(t.received_seq.last_seq == kMin + 5);
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
    std::string trigger;
  };
  std::vector<Due> due;
  IngestWorker::Hooks hooks;
  hooks.on_refit_due = [&](const std::string&, int64_t t_ref, const char* trigger) {
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
    CHECK(due[k].trigger == (k == 0 ? "first" : "early"));
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
    feed(*w, s, 0, n);
    const SpacecraftTracker& t = *w->fleet().find("SAT-1");
    CHECK(t.filtered_utime == s[n - 2].utime);
    std::this_thread::sleep_for(std::chrono::milliseconds(1300));
    w->commit_if_due();  // nothing new to commit: the poll finds the quiet tail
    CHECK(t.filtered_utime == s[n - 1].utime);
    CHECK(counters.ukf_updates == static_cast<int64_t>(n));
  }
}
