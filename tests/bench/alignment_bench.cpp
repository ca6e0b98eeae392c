// Stage 2 alignment speed: Procrustes and small-angle LS on a 12 h window (4320 pairs), one
// linear-KF update, the gates on one result. Run: build/bin/alignment_bench
// --benchmark_format=json
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/alignment.hpp"

namespace {

std::vector<magcal::AlignmentPair> make_pairs(int n) {
  std::mt19937 rng(1);
  std::normal_distribution<double> g(0.0, 1.0);
  const Eigen::Matrix3d R = magcal::dcm_from_roll_pitch_yaw({0.017, 0.035, 0.017});
  std::vector<magcal::AlignmentPair> pairs;
  for (int k = 0; k < n; ++k) {
    const Eigen::Vector3d h = 40000.0 * Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized();
    pairs.push_back({R * h + 3.0 * Eigen::Vector3d(g(rng), g(rng), g(rng)), h});
  }
  return pairs;
}

void BM_Procrustes4320(benchmark::State& state) {
  const auto pairs = make_pairs(4320);
  for (auto _ : state) benchmark::DoNotOptimize(magcal::align_procrustes(pairs));
}
BENCHMARK(BM_Procrustes4320)->Unit(benchmark::kMicrosecond);

void BM_SmallAngleLs4320(benchmark::State& state) {
  const auto pairs = make_pairs(4320);
  for (auto _ : state) benchmark::DoNotOptimize(magcal::align_small_angle_ls(pairs));
}
BENCHMARK(BM_SmallAngleLs4320)->Unit(benchmark::kMicrosecond);

void BM_AlignmentKfUpdate(benchmark::State& state) {
  const auto pairs = make_pairs(4096);
  magcal::AlignmentKalmanFilter kf({.sigma_nT = 3.0, .relinearise_above_rad = 1e-3});
  std::size_t k = 0;
  for (auto _ : state) {
    const auto& p = pairs[k++ & 4095];
    benchmark::DoNotOptimize(kf.update(p.u_sensor_nT, p.h_body_nT));
  }
}
BENCHMARK(BM_AlignmentKfUpdate)->Unit(benchmark::kNanosecond);

void BM_EvaluateGates(benchmark::State& state) {
  magcal::CalibrationResult r, prev;
  r.status = magcal::CalibrationStatus::kOk;
  r.residual_rms_nT = 8.0;
  r.fisher_condition_number = 97.0;
  r.covariance = magcal::Matrix9d::Identity();
  prev = r;
  magcal::GateInputs in;
  in.min_coverage_eigenvalue = 0.04;
  in.previous_accepted = &prev;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::evaluate_gates(r, in));
}
BENCHMARK(BM_EvaluateGates)->Unit(benchmark::kNanosecond);

}  // namespace

BENCHMARK_MAIN();
