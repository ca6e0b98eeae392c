// Nightly refit of a fleet (design.md target: 1 000 spacecraft with 12 h windows, 4 320 samples
// each, < 10 s on this 2-core machine): for every spacecraft, RefitRunner reads its window from
// SQLite, runs calibrate_batch (centered -> LM -> alignment -> gates, change gate against the
// previous accepted refit from the history), stores the result and the job rows — exactly the
// daemon's refit thread, sequentially on one connection. The database (4.3 M samples, one
// simulated tumbling-field day per spacecraft with its own bias) is built untimed.
//   build/bin/refit_fleet_bench --benchmark_format=json
#include <benchmark/benchmark.h>
#include <spdlog/spdlog.h>

#include <unistd.h>
#include <cmath>
#include <filesystem>
#include <random>

#include <Eigen/LU>

#include "service/refit/refit_runner.hpp"
#include "storage/sqlite/sqlite_stores.hpp"

using namespace magcal;

namespace {

constexpr int64_t kT0 = 1704067200000000;  // 2024-01-01
constexpr int64_t kStep = 10'000'000;
constexpr int kWindowSamples = 4320;  // 12 h at 10 s

void fill(storage::Database& db, int n_sats) {
  storage::SqliteSampleWindowStore store(db);
  std::mt19937 rng(11);
  std::normal_distribution<double> noise(0.0, 3.0);
  std::uniform_real_distribution<double> bias(-3000.0, 3000.0);
  std::vector<storage::StoredSample> rows(kWindowSamples);
  Eigen::Matrix3d D;
  D << 0.01, 0.002, -0.001, 0.002, 0.02, 0.003, -0.001, 0.003, -0.01;
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + D).inverse();
  for (int sat = 0; sat < n_sats; ++sat) {
    const Eigen::Vector3d b(bias(rng), bias(rng), bias(rng));
    for (int k = 0; k < kWindowSamples; ++k) {
      const double a = 0.0021 * k + sat, c = 0.0013 * k;
      const Eigen::Vector3d h =
          (25000.0 + 8000.0 * std::sin(0.004 * k)) *
          Eigen::Vector3d(std::cos(a) * std::cos(c), std::sin(a) * std::cos(c), std::sin(c));
      const Eigen::Vector3d B = inv * (h + b) + Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
      auto& r = rows[static_cast<size_t>(k)];
      r.sat_id = "SAT-" + std::to_string(sat);
      r.utime = kT0 + k * kStep;
      r.seq = k;
      r.b_sensor_nT = {B.x(), B.y(), B.z()};
      r.has_direction = true;
      r.h_body_nT = {h.x(), h.y(), h.z()};
      r.h_norm_nT = h.norm();
    }
    store.insert_batch(rows);
  }
}

void BM_NightlyRefitFleet(benchmark::State& state) {
  const int n_sats = static_cast<int>(state.range(0));
  const auto dir = std::filesystem::temp_directory_path() /
                   ("magcal_refit_fleet_bench_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  DaemonConfig config;
  config.storage.db_path = (dir / "fleet.db").string();
  int accepted = 0, computed = 0;
  {
    storage::Database db(config.storage.db_path);
    fill(db, n_sats);
    RefitRunner runner(config, db);
    const int64_t t_ref = kT0 + (kWindowSamples - 1) * kStep;
    for (auto _ : state) {
      accepted = computed = 0;
      for (const auto& sat : runner.spacecraft()) {
        const auto out = runner.run(sat, t_ref, storage::RefitTrigger::kScheduled, t_ref);
        computed += out.kind == RefitOutcome::Kind::kComputed;
        accepted += out.accepted();
      }
    }
  }
  state.counters["spacecraft"] = n_sats;
  state.counters["computed"] = computed;
  state.counters["accepted"] = accepted;
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) * n_sats);
  std::filesystem::remove_all(dir);
}
BENCHMARK(BM_NightlyRefitFleet)
    ->Arg(1000)
    ->Iterations(1)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace

// The daemon logs to stdout; keep the JSON on stdout clean.
int main(int argc, char** argv) {
  spdlog::set_level(spdlog::level::warn);
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
