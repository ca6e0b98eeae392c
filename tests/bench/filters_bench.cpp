// Online filter cost per sample (issue 10 targets: square-root UKF <= 0.5 us, EKF <= 0.5 us), with
// sizeof of the per-spacecraft state reported as counters. BM_Update: default filter (data
// start: the first ~60-300 samples of the first pass are collected and the batch start solved,
// then every sample is a filter update); BM_UpdateStarted: a filter initialized at the truth,
// so every iteration is a measurement update. Run from a Release build:
//   build/bin/filters_bench --benchmark_format=json
#include <benchmark/benchmark.h>

#include <Eigen/LU>

#include <cmath>
#include <random>
#include <vector>

#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"

namespace {

using magcal::Vector9d;

struct Sample {
  int64_t utime;
  Eigen::Vector3d b_sensor_nT;
  double h_norm_nT;
};

// 12 h of 10 s samples from the estimation model (random directions, |h| 20-50 uT, 3 nT noise).
const std::vector<Sample>& samples() {
  static const std::vector<Sample> data = [] {
    std::mt19937_64 rng(42);
    std::normal_distribution<double> n(0.0, 1.0);
    Vector9d p;
    p << 1000.0, 800.0, 900.0, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
    const auto truth = magcal::CalibrationParameters::from_packed(p);
    const Eigen::Matrix3d IpD_inv = (Eigen::Matrix3d::Identity() + truth.D).inverse();
    std::vector<Sample> out;
    for (int k = 0; k < 4320; ++k) {
      const double h_norm = 35000.0 + 15000.0 * std::cos(k * 0.011);
      const Eigen::Vector3d h = h_norm * Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
      const Eigen::Vector3d eps(n(rng), n(rng), n(rng));
      out.push_back({1577836800LL * 1000000 + k * 10'000'000LL,
                     IpD_inv * (h + truth.bias_nT + 3.0 * eps), h_norm});
    }
    return out;
  }();
  return data;
}

template <class Filter>
void run_updates(benchmark::State& state, Filter& f) {
  const auto& data = samples();
  size_t k = 0;
  int64_t t_offset = 0;
  for (auto _ : state) {
    const Sample& s = data[k];
    benchmark::DoNotOptimize(f.update(s.b_sensor_nT, s.h_norm_nT, s.utime + t_offset));
    if (++k == data.size()) {
      k = 0;
      t_offset += 12LL * 3600 * 1000000;  // keep time increasing
    }
  }
  state.SetItemsProcessed(state.iterations());
  state.counters["sizeof_bytes"] = sizeof(Filter);
  state.counters["sizeof_state_bytes"] = sizeof(magcal::FilterState);
  state.counters["accepted"] = static_cast<double>(f.state().n_accepted);
}

template <class Filter>
void BM_Update(benchmark::State& state) {
  typename Filter::Options o;
  if (state.range(0) != 0) o.process_noise_per_sqrt_hour.setConstant(1e-3);
  Filter f(o);
  run_updates(state, f);
}

template <class Filter>
void BM_UpdateStarted(benchmark::State& state) {
  typename Filter::Options o;
  if (state.range(0) != 0) o.process_noise_per_sqrt_hour.setConstant(1e-3);
  Filter f(o);
  Vector9d p;
  p << 1000.0, 800.0, 900.0, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  Vector9d d;
  d << 4.0, 4.0, 4.0, 1e-8, 1e-8, 1e-8, 1e-8, 1e-8, 1e-8;
  f.initialize(p, d.asDiagonal());
  run_updates(state, f);
}

}  // namespace

// Arg 0: Q = 0 (static state); Arg 1: Q > 0 (prediction step included).
BENCHMARK_TEMPLATE(BM_Update, magcal::MagnetometerUkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_Update, magcal::MagnetometerEkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_UpdateStarted, magcal::MagnetometerUkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_UpdateStarted, magcal::MagnetometerEkf)->Arg(0)->Arg(1);

BENCHMARK_MAIN();
