// IGRF-14 (degree 13) evaluation and Earth-orientation costs.
//   build/bin/igrf_bench --benchmark_format=json
// Target (design.md): IGRF-14 degree-13 field evaluation < 5 us per call.
#include <benchmark/benchmark.h>

#include <random>
#include <vector>

#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/reference_field.hpp"

namespace {

using namespace magcal;

constexpr int64_t kStart = 1764547200LL * kMicrosPerSecond;  // 2025-12-01T00:00:00Z

// LEO positions spread over the globe, so no branch or cache favours one point.
std::vector<Eigen::Vector3d> leo_positions() {
  std::mt19937_64 rng(5);
  std::normal_distribution<double> n(0.0, 1.0);
  std::vector<Eigen::Vector3d> out;
  for (int i = 0; i < 1024; ++i)
    out.push_back(Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized() * 6871e3);
  return out;
}

void BM_IgrfFieldGeocentric(benchmark::State& state) {
  IgrfModel model;
  model.set_date(2025.9);
  std::vector<GeocentricPosition> points;
  for (const auto& r : leo_positions()) points.push_back(geocentric_from_ecef(r));
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(model.field_geocentric(points[i++ & 1023]));
  }
}
BENCHMARK(BM_IgrfFieldGeocentric);

void BM_IgrfFieldEcef(benchmark::State& state) {
  IgrfModel model;
  model.set_date(2025.9);
  const auto points = leo_positions();
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(model.field_ecef_nT(points[i++ & 1023]));
  }
}
BENCHMARK(BM_IgrfFieldEcef);

void BM_IgrfSetDate(benchmark::State& state) {
  IgrfModel model;
  double year = 2000.0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(model.set_date(year));
    year = year > 2029.0 ? 2000.0 : year + 0.01;
  }
}
BENCHMARK(BM_IgrfSetDate);

void BM_GcrsFromItrfDirect(benchmark::State& state) {
  int64_t t = kStart;
  for (auto _ : state) {
    benchmark::DoNotOptimize(gcrs_from_itrf(t));
    t += 100'000;  // 10 Hz samples
  }
}
BENCHMARK(BM_GcrsFromItrfDirect);

void BM_GcrsFromItrfCached(benchmark::State& state) {
  EarthOrientationCache cache;
  int64_t t = kStart;
  for (auto _ : state) {
    benchmark::DoNotOptimize(cache.gcrs_from_itrf(t));
    t += 100'000;  // 10 Hz samples: precession-nutation recomputed once per 10 calls
  }
}
BENCHMARK(BM_GcrsFromItrfCached);

// What the daemon pays per sample with IGRF from position: field in the body frame.
void BM_ReferenceFieldBody(benchmark::State& state) {
  ReferenceField field;
  const auto points = leo_positions();
  const QuaternionWxyz q = QuaternionWxyz(0.7, -0.2, 0.4, 0.1).normalized();
  int64_t t = kStart;
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(field.field_body_nT(t, points[i++ & 1023], q));
    t += 100'000;
  }
}
BENCHMARK(BM_ReferenceFieldBody);

}  // namespace

BENCHMARK_MAIN();
