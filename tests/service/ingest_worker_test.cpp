// The daemon's worker in-process: storage of valid samples, rejection counts, sequence gaps,
// snapshot cadence in data time, and restart continuity (restored or re-run filter state gives
// the same estimate as an uninterrupted run).
#include <catch2/catch.hpp>

#include <unistd.h>
#include <filesystem>
#include <random>

#include "pipeline/rotation.hpp"
#include "service/calibration_record.hpp"
#include "service/ingest_worker.hpp"
#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"

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

// Truth: B = (I + D)^-1 (h + b) + noise, h a tumbling 30 000 nT field in the body frame.
std::vector<mag_sample_t> simulate(int n, uint32_t seed, const std::string& sat = "SAT-1") {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, kNoise_nT);
  const Eigen::Vector3d b(1000.0, -800.0, 900.0);
  Eigen::Matrix3d D;
  D << 0.01, 0.002, -0.001, 0.002, 0.02, 0.003, -0.001, 0.003, -0.01;
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + D).inverse();
  std::vector<mag_sample_t> out;
  for (int k = 0; k < n; ++k) {
    const double a = 0.0021 * k, c = 0.0013 * k;
    const Eigen::Vector3d h = 30000.0 * Eigen::Vector3d(std::cos(a) * std::cos(c),
                                                        std::sin(a) * std::cos(c), std::sin(c));
    const Eigen::Vector3d B = inv * (h + b) + Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    mag_sample_t s{};
    s.utime = kT0 + k * kStep;
    s.sat_id = sat;
    s.seq = k;
    for (int i = 0; i < 3; ++i) {
      s.b_sensor_nT[i] = B(i);
      s.h_body_nT[i] = h(i);
    }
    s.has_reference = true;
    s.temperature_C = std::nanf("");
    out.push_back(s);
  }
  return out;
}

DaemonConfig test_config(const std::string& db) {
  DaemonConfig c;
  c.storage.db_path = db;
  c.ukf.filter.sigma_nT = kNoise_nT;
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
  storage::SampleWindowStore store(db);
  CHECK(store.count("SAT-1") == 298);
  CHECK(store.count_in_window("SAT-1", s[51].utime, s[51].utime + 1) == 1);
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
  const auto s = simulate(361, 2);  // exactly one hour at 10 s
  feed(*w, s, 0, s.size());
  // First sample starts the clock; one snapshot per 600 s of data after it: 6 in an hour.
  CHECK(counters.snapshots == 6);
  CHECK(published == 6);
  storage::Database db(tmp.path());
  storage::CalibrationHistory history(db);
  storage::HistoryQuery q;
  q.sat_id = "SAT-1";
  q.method = "ukf";
  const auto rows = history.query(q);
  REQUIRE(rows.size() == 6);
  CHECK(rows.front().utime == kT0 + 600LL * 1000000);
  CHECK(rows.back().utime == kT0 + 3600LL * 1000000);
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

TEST_CASE("an unwritable database is an error at construction", "[ingest_worker]") {
  DaemonCounters counters;
  auto c = test_config("/nonexistent-dir/sub/m.db");
  CHECK_THROWS_AS(make_worker(c, counters), storage::StorageError);
}

TEST_CASE("stored filter state round trip is bit-exact, collecting and started",
          "[ingest_worker]") {
  // service/calibration_record.cpp (MCF2 blob): what the daemon saves and restores.
  std::mt19937_64 rng(9);
  std::normal_distribution<double> n(0.0, 1.0);
  MagnetometerUkf ukf;
  const Eigen::Vector3d b(1000.0, 800.0, 900.0);
  for (int k = 0; k < 400; ++k) {
    const Eigen::Vector3d h = 40000.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
    ukf.update(h + b + 3.0 * Eigen::Vector3d(n(rng), n(rng), n(rng)), 40000.0,
               kT0 + k * 10'000'000LL);
    if (k == 20 || k == 399) {
      INFO("sample " << k << ", started " << ukf.initialized());
      FilterState back;
      REQUIRE(filter_state_from_stored(stored_filter_state("SAT-1", "ukf", ukf.state()), back));
      CHECK(back == ukf.state());
    }
  }
  CHECK(ukf.initialized());
}
