// Time to simulate 24 h at 10 s (8640 samples) for the presets, and the cost per sample.
//   build-sim/bin/simulator_bench --benchmark_format=json
#include <benchmark/benchmark.h>

#include "pipeline/simulator.hpp"

namespace {

void simulate_24h(benchmark::State& state, const char* preset) {
  magcal::Scenario s = *magcal::scenario_preset(preset);
  s.duration_s = 24.0 * 3600.0;
  for (auto _ : state) {
    magcal::Simulator sim(s);
    magcal::SimulatedSample x;
    double sum = 0.0;
    while (sim.next(&x)) sum += x.b_sensor_nT.x();
    benchmark::DoNotOptimize(sum);
  }
  state.counters["samples"] = static_cast<double>(s.sample_count());
  state.counters["per_sample"] = benchmark::Counter(
      static_cast<double>(s.sample_count()),
      benchmark::Counter::kIsIterationInvariantRate | benchmark::Counter::kInvert);
}

void BM_Simulate24hPaper(benchmark::State& state) {
  simulate_24h(state, "paper");
}
void BM_Simulate24hTumbling(benchmark::State& state) {
  simulate_24h(state, "tumbling");
}

}  // namespace

BENCHMARK(BM_Simulate24hPaper)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Simulate24hTumbling)->Unit(benchmark::kMillisecond);

BENCHMARK_MAIN();
