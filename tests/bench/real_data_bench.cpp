// Real-recording fit speed (service/analysis/real_data_fit.hpp) on ../shared/data/real: the ISS
// Astro Pi file with time-offset estimation (13 703 samples, 40 s grid over +-1000 s + refinement)
// and the BROAD file with the sphere fit, 9-parameter fit and joint stage 2 (53 240 samples).
// Reading the CSV is outside the timed loop. Skipped (error message) when the files are absent.
// Run: build/bin/real_data_bench --benchmark_format=json
#include <filesystem>
#include <string>

#include <benchmark/benchmark.h>

#include "service/analysis/real_data_fit.hpp"

namespace {

const std::string kDir = std::string(MAGCAL_SHARED_DATA_DIR) + "/real/";

void BM_IssFitWithOffsetEstimate(benchmark::State& state) {
  magcal::FieldRecordingOptions ro;
  ro.field_unit = magcal::FieldUnit::kMicroTesla;
  ro.altitude_km = 420.0;
  ro.skip_first = 20;
  std::string error;
  const auto rec = magcal::read_field_recording(
      kDir + "astropi_mk2_ir_commissioning_2022-01-31.csv", ro, &error);
  if (!rec) {
    state.SkipWithError(("ISS recording absent: " + error).c_str());
    return;
  }
  magcal::RecordingFitOptions o;
  o.estimate_time_offset = true;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::fit_recording(*rec, o, &error));
}
BENCHMARK(BM_IssFitWithOffsetEstimate)->Unit(benchmark::kMillisecond);

void BM_BroadAutoMagnitudeAndStage2(benchmark::State& state) {
  std::string error;
  const auto rec = magcal::read_field_recording(
      kDir + "broad_02_undisturbed_slow_rotation_B_mag_quat.csv", {}, &error);
  if (!rec) {
    state.SkipWithError(("BROAD recording absent: " + error).c_str());
    return;
  }
  magcal::RecordingFitOptions o;
  o.reference_magnitude_auto = true;
  for (auto _ : state) benchmark::DoNotOptimize(magcal::fit_recording(*rec, o, &error));
}
BENCHMARK(BM_BroadAutoMagnitudeAndStage2)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
