// Storage speed against the targets the daemon is sized for: batched sample inserts
// (>= 200 000 samples/s in batches of 200), reading a 12 h window of 4320 samples (< 3 ms), history
// queries.
//   build/bin/storage_bench --benchmark_format=json
// Databases are temporary files in WAL mode with the daemon's pragmas (not :memory:). The
// *Postgres benchmarks run the same on the PostgreSQL database MAGCAL_BENCH_PG_URI names (an
// empty one: its samples table is emptied first; skipped when the variable is unset).
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "storage/calibration_history.hpp"
#include "storage/connection.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_stores.hpp"

namespace fs = std::filesystem;
using namespace magcal::storage;

namespace {

constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kT0 = 1'767'225'600LL * kSecond;

struct TempDb {
  std::string path;
  explicit TempDb(const std::string& name) {
    path = (fs::temp_directory_path() /
            ("magcal_storage_bench_" + std::to_string(::getpid()) + "_" + name + ".db"))
               .string();
    remove();
  }
  ~TempDb() { remove(); }
  void remove() {
    for (const char* suffix : {"", "-wal", "-shm"}) fs::remove(path + suffix);
  }
};

// A full sample as the daemon stores it: reference direction, attitude, position, temperature.
StoredSample make_sample(const std::string& sat, int64_t utime, int64_t seq) {
  StoredSample s;
  s.sat_id = sat;
  s.utime = utime;
  s.seq = seq;
  s.receive_utime = utime + 2 * kSecond;
  const double a = 1e-3 * static_cast<double>(seq);
  s.b_sensor_nT = {2e4 * std::cos(a), 2e4 * std::sin(a), -3e4};
  s.has_direction = true;
  s.h_body_nT = {1.99e4 * std::cos(a), 1.99e4 * std::sin(a), -2.99e4};
  s.h_norm_nT = 3.6e4;
  s.has_attitude = true;
  s.q_body_from_eci = {std::cos(a), 0.0, 0.0, std::sin(a)};
  s.has_position = true;
  s.r_ecef_m = {7e6 * std::cos(a), 7e6 * std::sin(a), 1e5};
  s.temperature_C = 21.5;
  return s;
}

// The PostgreSQL database of the *Postgres benchmarks, emptied; nullptr (the benchmark skipped)
// when MAGCAL_BENCH_PG_URI is unset.
std::unique_ptr<Connection> bench_postgres(benchmark::State& state) {
  const char* uri = std::getenv("MAGCAL_BENCH_PG_URI");
  if (uri == nullptr || !is_postgres_uri(uri)) {
    state.SkipWithError("MAGCAL_BENCH_PG_URI (a postgresql:// URI) is not set");
    return nullptr;
  }
  auto db = open_database(uri);
  db->exec("TRUNCATE samples");
  return db;
}

void insert_batches(benchmark::State& state, SampleWindowStore& store) {
  const int batch_size = static_cast<int>(state.range(0));
  std::vector<StoredSample> batch(static_cast<size_t>(batch_size));
  int64_t seq = 0;
  for (auto _ : state) {
    state.PauseTiming();
    for (auto& s : batch) {
      s = make_sample("SAT-000" + std::to_string(seq % 4), kT0 + seq * kSecond, seq);
      ++seq;
    }
    state.ResumeTiming();
    const InsertStats stats = store.insert_batch(batch, nullptr, "station-A");
    benchmark::DoNotOptimize(stats);
  }
  state.SetItemsProcessed(state.iterations() * batch_size);  // items_per_second = samples/s
}

void BM_InsertBatch(benchmark::State& state) {
  TempDb tmp("insert");
  Database db(tmp.path);
  SqliteSampleWindowStore store(db);
  insert_batches(state, store);
}
BENCHMARK(BM_InsertBatch)->Arg(200)->Arg(4000)->Unit(benchmark::kMicrosecond);

void BM_InsertBatchPostgres(benchmark::State& state) {
  const auto db = bench_postgres(state);
  if (!db) return;
  insert_batches(state, *db->make_sample_window_store());
}
// Real time: the work is the server's, not this process's CPU.
BENCHMARK(BM_InsertBatchPostgres)
    ->Arg(200)
    ->Arg(4000)
    ->UseRealTime()
    ->Unit(benchmark::kMicrosecond);

void read_windows(benchmark::State& state, SampleWindowStore& store) {
  // 8 spacecraft x 14 h at 10 s: the 12 h window of one is 4320 of 40 320 rows.
  const int64_t step = 10 * kSecond;
  const int64_t n_per_sat = 14 * 360;
  for (int sat = 0; sat < 8; ++sat) {
    std::vector<StoredSample> rows;
    for (int64_t k = 0; k < n_per_sat; ++k) {
      rows.push_back(make_sample("SAT-00" + std::to_string(sat), kT0 + k * step, k));
    }
    store.insert_batch(rows);
  }
  const int64_t t1 = kT0 + n_per_sat * step;
  const int64_t t0 = t1 - 4320 * step;
  std::vector<StoredSample> window;
  for (auto _ : state) {
    store.read_window("SAT-003", t0, t1, window);
    benchmark::DoNotOptimize(window.data());
  }
  if (window.size() != 4320) state.SkipWithError("window does not hold 4320 samples");
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(window.size()));
}

void BM_ReadWindow4320(benchmark::State& state) {
  TempDb tmp("window");
  Database db(tmp.path);
  SqliteSampleWindowStore store(db);
  read_windows(state, store);
}
BENCHMARK(BM_ReadWindow4320)->Unit(benchmark::kMillisecond);

void BM_ReadWindow4320Postgres(benchmark::State& state) {
  const auto db = bench_postgres(state);
  if (!db) return;
  read_windows(state, *db->make_sample_window_store());
}
BENCHMARK(BM_ReadWindow4320Postgres)->UseRealTime()->Unit(benchmark::kMillisecond);

void BM_HistoryQuery(benchmark::State& state) {
  TempDb tmp("history");
  Database db(tmp.path);
  SqliteCalibrationHistory history(db);
  {
    // 4 spacecraft x 30 days of ukf snapshots every 10 min plus a daily refit: ~17 000 rows.
    Transaction tx(db);
    for (int sat = 0; sat < 4; ++sat) {
      for (int64_t k = 0; k < 30 * 144; ++k) {
        CalibrationRecord r;
        r.sat_id = "SAT-00" + std::to_string(sat);
        r.method = k % 144 == 12 ? "twostep" : "ukf";
        r.utime = kT0 + k * 600 * kSecond;
        r.bias_nT = {1.0 * k, 2.0, 3.0};
        for (int i = 0; i < 9; ++i) r.cov[cov_index(i, i)] = 1.0;
        r.created_utime = r.utime;
        history.append(r);
      }
    }
    tx.commit();
  }
  HistoryQuery q;
  q.sat_id = "SAT-002";
  q.method = state.range(0) ? "twostep" : "ukf";
  q.limit = 100;
  size_t rows = 0;
  for (auto _ : state) {
    const auto out = history.query(q);
    rows = out.size();
    benchmark::DoNotOptimize(out.data());
  }
  state.counters["rows"] = static_cast<double>(rows);
}
// Arg 0: the 100 newest ukf snapshots; arg 1: the (30) twostep refits.
BENCHMARK(BM_HistoryQuery)->Arg(0)->Arg(1)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
