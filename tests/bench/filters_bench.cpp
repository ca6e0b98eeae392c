// Online filter cost per sample (issue 10 targets: square-root UKF <= 0.5 us, EKF <= 0.5 us), with
// sizeof of the per-spacecraft state reported as counters. BM_Update: default filter (data
// start: the first ~60-300 samples of the first pass are collected and the batch start solved,
// then every sample is a filter update); BM_UpdateStarted: a filter initialized at the truth,
// so every iteration is a measurement update. BM_StartFromData / BM_CollectUnobservable: the
// cost per sample while a filter collects for its start from data (paper scenario until the
// start; a yaw-only capture that never starts), Arg 0 = the attempt schedule with its
// pre-check (filter_common.hpp), Arg 1 = an attempt every 30 samples (the schedule before).
// Run from a Release build:
//   build/bin/filters_bench --benchmark_format=json
#include <benchmark/benchmark.h>

#include <Eigen/Geometry>
#include <Eigen/LU>

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "pipeline/magnetometer_ekf.hpp"
#include "pipeline/magnetometer_ukf.hpp"
#include "pipeline/simulator.hpp"

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

// The first 3 h of the paper scenario (the filter starts after ~2.25 h).
const std::vector<Sample>& paper_samples() {
  static const std::vector<Sample> data = [] {
    magcal::Scenario sc = *magcal::scenario_preset("paper");
    sc.duration_s = 3.0 * 3600.0;
    magcal::Simulator sim(sc);
    std::vector<Sample> out;
    magcal::SimulatedSample s;
    while (sim.next(&s)) out.push_back({s.utime, s.b_sensor_nT, s.h_body_reported_nT.norm()});
    return out;
  }();
  return data;
}

// A yaw-only capture in a constant 48 uT field (b3 unobservable: never starts), 1 s samples.
const std::vector<Sample>& yaw_only_samples() {
  static const std::vector<Sample> data = [] {
    std::mt19937_64 rng(31);
    std::normal_distribution<double> n(0.0, 30.0);
    const Eigen::Vector3d b(-1500.0, 2500.0, 3200.0), h0(24000.0, 0.0, -41569.2);
    std::vector<Sample> out;
    for (int k = 0; k < 4000; ++k) {
      const Eigen::Vector3d h =
          Eigen::AngleAxisd(-6.283185307179586 * k / 400.0, Eigen::Vector3d::UnitZ()) * h0;
      out.push_back({1577836800LL * 1000000 + k * 1'000'000LL,
                     h + b + Eigen::Vector3d(n(rng), n(rng), n(rng)), 48000.0});
    }
    return out;
  }();
  return data;
}

magcal::MagnetometerUkf::Options collecting_options(bool every_30, double sigma_nT) {
  magcal::MagnetometerUkf::Options o;
  o.sigma_nT = sigma_nT;
  if (every_30) {  // the schedule before: every start_attempt_every samples, no pre-check
    o.start_attempt_gap_fraction = 1e-9;
    o.start.precheck_margin = std::numeric_limits<double>::infinity();
  }
  return o;
}

// Each iteration: a fresh filter fed the paper scenario until it starts.
void BM_StartFromData(benchmark::State& state) {
  const auto& data = paper_samples();
  const auto o = collecting_options(state.range(0) != 0, 3.0);
  int64_t samples = 0;
  for (auto _ : state) {
    magcal::MagnetometerUkf f(o);
    for (const Sample& s : data) {
      ++samples;
      if (f.update(s.b_sensor_nT, s.h_norm_nT, s.utime).started) break;
    }
    benchmark::DoNotOptimize(f.x());
  }
  state.SetItemsProcessed(samples);
  state.counters["samples_to_start"] = static_cast<double>(samples) / state.iterations();
}

// Each iteration: a fresh filter fed 4000 samples that never observe p.
void BM_CollectUnobservable(benchmark::State& state) {
  const auto& data = yaw_only_samples();
  const auto o = collecting_options(state.range(0) != 0, 30.0);
  for (auto _ : state) {
    magcal::MagnetometerUkf f(o);
    for (const Sample& s : data) f.update(s.b_sensor_nT, s.h_norm_nT, s.utime);
    benchmark::DoNotOptimize(f.x());
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(data.size()));
}

}  // namespace

BENCHMARK(BM_StartFromData)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_CollectUnobservable)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// Arg 0: Q = 0 (static state); Arg 1: Q > 0 (prediction step included).
BENCHMARK_TEMPLATE(BM_Update, magcal::MagnetometerUkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_Update, magcal::MagnetometerEkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_UpdateStarted, magcal::MagnetometerUkf)->Arg(0)->Arg(1);
BENCHMARK_TEMPLATE(BM_UpdateStarted, magcal::MagnetometerEkf)->Arg(0)->Arg(1);

BENCHMARK_MAIN();
