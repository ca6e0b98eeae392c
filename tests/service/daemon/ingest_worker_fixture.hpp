// What the worker's tests share: a temporary database, simulated samples of a tumbling
// spacecraft, the worker fed in batches as the daemon feeds it, and an accepted refit.
#pragma once

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

namespace magcal::worker_test {

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
inline std::vector<mag_sample_t> simulate(int n, uint32_t seed, const std::string& sat = "SAT-1",
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

inline DaemonConfig test_config(const std::string& db) {
  DaemonConfig c;
  c.storage.db_path = db;
  c.ukf.filter.sigma_nT = kNoise_nT;
  // One station: its filter takes each committed sample at once (the reorder delay has its
  // own test).
  c.fleet.reorder_delay_s = 0.0;
  return c;
}

inline IngestItem batch(const std::vector<mag_sample_t>& all, size_t from, size_t to) {
  IngestItem it;
  it.from_batch = true;
  it.batch_sat_id = all.front().sat_id;
  it.samples.assign(all.begin() + static_cast<long>(from), all.begin() + static_cast<long>(to));
  it.receive_utime = kT0 + 365LL * 86400 * 1000000;
  return it;
}

inline void feed(IngestWorker& w, const std::vector<mag_sample_t>& all, size_t from, size_t to) {
  for (size_t i = from; i < to; i += 200) w.process(batch(all, i, std::min(to, i + 200)));
  w.commit();
}

inline std::unique_ptr<IngestWorker> make_worker(const DaemonConfig& c, DaemonCounters& counters) {
  return std::make_unique<IngestWorker>(c, counters, std::make_unique<ReferenceField>(),
                                        IngestWorker::Hooks{});
}

// An accepted refit of the first 1000 samples of `s` (near simulate()'s truth), as RefitRunner
// stores it and hands it to the worker.
inline CalibrationResult accepted_refit(const std::vector<mag_sample_t>& s) {
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
inline int64_t store_refit(const std::string& db, const CalibrationResult& refit) {
  storage::Database d(db);
  storage::SqliteCalibrationHistory history(d);
  storage::SqliteRefitJobLog jobs(d);
  const int64_t job = jobs.start("SAT-1", "scheduled", refit.utime, 1);
  const int64_t id = history.append(record_from_result("SAT-1", refit));
  jobs.finish(job, storage::job_outcome::kOk, 2, "", id);
  return id;
}

// The filter state of an uninterrupted run over `s`, re-anchored on `refit` after 1000 samples.
inline FilterState anchored_run(const std::vector<mag_sample_t>& s, const CalibrationResult& refit,
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

inline double relative_difference(const Vector9d& got, const Vector9d& want) {
  return (got - want).cwiseQuotient(want.cwiseAbs().cwiseMax(1e-3)).cwiseAbs().maxCoeff();
}

// One sample in a frame of its own, as a live mag_sample_t feed.
inline IngestItem single(const mag_sample_t& s) {
  IngestItem it;
  it.samples.push_back(s);
  it.receive_utime = kT0 + 365LL * 86400 * 1000000;
  return it;
}

// Samples of `sat` stored in the database at db_path.
inline int64_t stored_rows(const std::string& db_path, const std::string& sat = "SAT-1") {
  storage::Database db(db_path);
  storage::SqliteSampleWindowStore store(db);
  return store.count(sat);
}

}  // namespace magcal::worker_test
