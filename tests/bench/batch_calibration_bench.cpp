// Batch refit speed (design.md target: centered + LM on a 12 h window of 4320 samples < 2 ms).
// Data: the paper scenario (nadir LEO, 10 s sampling), simulated once per benchmark binary.
//   build-*/bin/batch_calibration_bench --benchmark_format=json
#include <limits>

#include <benchmark/benchmark.h>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/centered_solution.hpp"
#include "pipeline/crlb.hpp"
#include "pipeline/lm_refinement.hpp"
#include "pipeline/orbit_synchronous_bias.hpp"
#include "pipeline/scenario.hpp"
#include "pipeline/simulator.hpp"

namespace {

const magcal::SampleSet& paper_window() {
  static const magcal::SampleSet samples = [] {
    magcal::Scenario sc = *magcal::scenario_preset("paper");
    sc.duration_s = 12.0 * 3600.0;
    magcal::Simulator sim(sc);
    magcal::SampleSet s;
    magcal::SimulatedSample x;
    while (sim.next(&x)) s.push_back(x.calibration_sample());
    return s;
  }();
  return samples;
}

void BM_CenteredPlusLm_NoAlignmentNoGates(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window();
  magcal::BatchCalibrationOptions o;
  o.alignment = false;
  o.gates = false;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::calibrate_batch(s, o));
  state.counters["samples"] = static_cast<double>(s.size());
}
BENCHMARK(BM_CenteredPlusLm_NoAlignmentNoGates)->Unit(benchmark::kMillisecond);

void BM_FullRefitPipeline(benchmark::State& state) {  // + Fisher, Procrustes, gates
  const magcal::SampleSet& s = paper_window();
  magcal::BatchCalibrationOptions o;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::calibrate_batch(s, o));
}
BENCHMARK(BM_FullRefitPipeline)->Unit(benchmark::kMillisecond);

// The same window without a temperature channel: the refit adds the orbit-synchronous swing's
// term (pipeline/orbit_synchronous_bias.hpp); the term alone below.
const magcal::SampleSet& paper_window_without_temperature() {
  static const magcal::SampleSet samples = [] {
    magcal::SampleSet s = paper_window();
    for (magcal::CalibrationSample& c : s)
      c.temperature_C = std::numeric_limits<double>::quiet_NaN();
    return s;
  }();
  return samples;
}

void BM_FullRefitPipelineWithoutTemperature(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window_without_temperature();
  magcal::BatchCalibrationOptions o;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::calibrate_batch(s, o));
}
BENCHMARK(BM_FullRefitPipelineWithoutTemperature)->Unit(benchmark::kMillisecond);

void BM_OrbitSynchronousSwing(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window_without_temperature();
  const magcal::CalibrationResult fit =
      magcal::calibrate_batch(s, magcal::BatchCalibrationOptions{});
  for (auto _ : state) {
    benchmark::DoNotOptimize(magcal::unresolved_orbit_synchronous_bias_swing(s, fit, 3.0));
  }
}
BENCHMARK(BM_OrbitSynchronousSwing)->Unit(benchmark::kMillisecond);

void BM_FullRefitPipelineRobust(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window();
  magcal::BatchCalibrationOptions o;
  o.robust = true;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::calibrate_batch(s, o));
}
BENCHMARK(BM_FullRefitPipelineRobust)->Unit(benchmark::kMillisecond);

void BM_CenteredSolution(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window();
  for (auto _ : state) benchmark::DoNotOptimize(magcal::centered_solution(s));
}
BENCHMARK(BM_CenteredSolution)->Unit(benchmark::kMillisecond);

void BM_LmFromCentered(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window();
  const magcal::Vector9d theta0 = magcal::centered_solution(s).theta;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::refine_lm(s, theta0));
}
BENCHMARK(BM_LmFromCentered)->Unit(benchmark::kMillisecond);

void BM_Crlb(benchmark::State& state) {
  const magcal::SampleSet& s = paper_window();
  magcal::CalibrationParameters p;
  p.bias_nT << 1000, 800, 900;
  p.D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::compute_crlb(s, p, 3.0));
}
BENCHMARK(BM_Crlb)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
