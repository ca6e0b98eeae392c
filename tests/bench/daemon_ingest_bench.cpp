// Daemon ingest throughput (design.md targets): mag_batch_t frames of 200 samples through the
// daemon's own worker pipeline, in-process: decode_frame (what the LCM handler does) ->
// IngestWorker::process (validate -> reference field -> UKF update -> pending row; snapshot
// rows every 60 s of data) -> batched SQLite commits (one transaction per 4000 samples) and
// retention, on a WAL database file in /tmp. Frames are pre-encoded; each iteration is one
// frame. items_per_second = samples/s.
//   BM_Ingest/<spacecraft>/<0: h_body in the frame | 1: IGRF from position + attitude>
//     /<1: the UKF's start attempted every 30 samples without the pre-check, the schedule
//     before (filter_common.hpp), for an A/B in the same run>
// Targets: >= 100 000 samples/s with the reference in the frame, >= 50 000 with IGRF.
//   build/bin/daemon_ingest_bench --benchmark_format=json
// Also: BM_TrackerMemory, resident memory per tracked spacecraft (target < 4 KB).
//
// BM_DaemonReplayHttp/<rounds>: the whole magcald (magcal::Daemon: LCM file:// provider at
// speed=0 -> receive thread -> queue -> worker -> SQLite, refit thread idle) over a log of the
// same 400 000 samples (10 spacecraft), in paired rounds: operations server off, on (at
// 127.0.0.1:0, metrics counted), and on with a client on another thread fetching /metrics and
// /api/v1/history?sat=SAT-0 in a loop for the whole replay (issue 12: drop < 10 %). Throughput
// = stored samples / (open() + run()), median per variant; any run with stored != received is
// an error. http_failed counts answers other than 200 (and 400 before SAT-0 exists).
//   build/bin/daemon_ingest_bench --benchmark_filter=DaemonReplay --benchmark_format=json
#include <benchmark/benchmark.h>
#include <spdlog/spdlog.h>

#include <malloc.h>
#include <unistd.h>
#include <array>
#include <cmath>
#include <filesystem>
#include <limits>
#include <random>
#include <thread>
#include <tuple>

#include <lcm/lcm-cpp.hpp>

#include "service/daemon/daemon.hpp"
#include "service/daemon/ingest_worker.hpp"
#include "service/daemon/intake/lcm_ingest.hpp"
#include "service/daemon/ownership/spacecraft_tracker.hpp"
#include "service/io/reference_field.hpp"

// Last: <httplib.h> pulls in <resolv.h>, whose `_res` macro breaks Eigen's headers.
#include <httplib.h>

using namespace magcal;

namespace {

constexpr int kBatch = 200;
constexpr int64_t kT0 = 1704067200000000;  // 2024-01-01
constexpr int64_t kStep = 10'000'000;      // 10 s per spacecraft
constexpr int kSamplesPerRun = 400'000;

std::vector<std::vector<uint8_t>> make_frames(int n_sats, bool igrf) {
  ReferenceField field;
  std::mt19937 rng(7);
  std::normal_distribution<double> noise(0.0, 3.0);
  const int per_sat = std::max(kBatch, kSamplesPerRun / n_sats / kBatch * kBatch);
  std::vector<std::vector<uint8_t>> frames;
  for (int round = 0; round < per_sat / kBatch; ++round) {
    for (int sat = 0; sat < n_sats; ++sat) {
      mag_batch_t b;
      b.sat_id = "SAT-" + std::to_string(sat);
      for (int i = 0; i < kBatch; ++i) {
        const int k = round * kBatch + i;
        mag_sample_t s{};
        s.utime = kT0 + k * kStep;
        s.sat_id = b.sat_id;
        s.seq = k;
        const double u = 2.0 * M_PI * k * 10.0 / 5700.0 + sat;  // argument of latitude
        const double inc = 1.7;
        const Eigen::Vector3d r =
            6.921e6 *
            Eigen::Vector3d(std::cos(u), std::sin(u) * std::cos(inc), std::sin(u) * std::sin(inc));
        const Eigen::Vector4d q =
            Eigen::Vector4d(std::cos(0.001 * k), 0.0, std::sin(0.001 * k), 0.0);
        Eigen::Vector3d h;
        if (igrf) {
          s.has_position = s.has_attitude = true;
          for (int j = 0; j < 3; ++j) s.r_ecef_m[j] = r(j);
          for (int j = 0; j < 4; ++j) s.q_body_from_eci[j] = q(j);
          h = *field.field_body_nT(s.utime, r, q);
        } else {
          s.has_reference = true;
          h = 30000.0 *
              Eigen::Vector3d(std::cos(u), std::sin(u) * std::cos(0.3 * u), std::sin(0.3 * u))
                  .normalized();
          for (int j = 0; j < 3; ++j) s.h_body_nT[j] = h(j);
        }
        for (int j = 0; j < 3; ++j) s.b_sensor_nT[j] = h(j) + 1000.0 * (j + 1) + noise(rng);
        s.temperature_C = std::nanf("");
        b.samples.push_back(s);
      }
      b.n = kBatch;
      std::vector<uint8_t> bytes(static_cast<size_t>(b.getEncodedSize()));
      b.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
      frames.push_back(std::move(bytes));
    }
  }
  return frames;
}

void BM_Ingest(benchmark::State& state) {
  const int n_sats = static_cast<int>(state.range(0));
  const bool igrf = state.range(1) != 0;
  const auto frames = make_frames(n_sats, igrf);
  const auto dir = std::filesystem::temp_directory_path() /
                   ("magcal_ingest_bench_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  DaemonConfig config;
  config.storage.db_path = (dir / "bench.db").string();
  if (state.range(2) != 0) {
    config.ukf.filter.start_attempt_gap_fraction = 1e-9;
    config.ukf.filter.start.precheck_margin = std::numeric_limits<double>::infinity();
  }
  DaemonCounters counters;
  int64_t samples = 0;
  {
    IngestWorker worker(config, counters, std::make_unique<ReferenceField>(), {});
    IngestItem item;
    size_t next = 0;
    for (auto _ : state) {
      const auto& f = frames[next++ % frames.size()];
      if (decode_frame(f.data(), static_cast<int>(f.size()), true, item) != DecodeOutcome::kOk) {
        state.SkipWithError("decode failed");
        break;
      }
      worker.process(item);
      worker.commit_if_due();
      samples += static_cast<int64_t>(item.samples.size());
    }
    worker.commit();  // the last batch is part of the work
  }
  state.SetItemsProcessed(samples);
  state.counters["stored"] = static_cast<double>(counters.stored.load());
  state.counters["rejected"] = static_cast<double>(counters.rejected_total());
  state.counters["snapshots"] = static_cast<double>(counters.snapshots.load());
  std::filesystem::remove_all(dir);
}
// One pass over the pre-encoded frames (400 000 samples): sustained, with commits and retention.
BENCHMARK(BM_Ingest)
    ->Args({1, 0, 0})
    ->Args({10, 0, 0})
    ->Args({1000, 0, 0})
    ->Args({1, 1, 0})
    ->Args({10, 1, 0})
    ->Args({1000, 1, 0})
    ->Args({1, 0, 1})
    ->Args({1000, 0, 1})
    ->Args({1000, 1, 1})
    ->Iterations(kSamplesPerRun / kBatch)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// The frames of make_frames(10, false) as an LCM log (MAGCAL_BATCH), written once per process
// and removed at its exit (55 MB in the temporary directory).
struct ReplayLogFile {
  std::string path;
  ~ReplayLogFile() {
    std::error_code ignored;
    std::filesystem::remove(path, ignored);
  }
};
const std::string& replay_log() {
  static const ReplayLogFile log{[] {
    const auto file = std::filesystem::temp_directory_path() /
                      ("magcal_replay_bench_" + std::to_string(::getpid()) + ".lcm");
    lcm::LogFile out(file.string(), "w");
    int64_t event = 0;
    for (auto& f : make_frames(10, false)) {
      lcm::LogEvent e;
      e.eventnum = event;
      e.timestamp = kT0 + event * 1000;
      e.channel = "MAGCAL_BATCH";
      e.datalen = static_cast<int32_t>(f.size());
      e.data = f.data();
      out.writeEvent(&e);
      ++event;
    }
    return file.string();
  }()};
  return log.path;
}

// One replay of replay_log() through a whole Daemon; samples/s from open() to the end of run().
struct ReplayRun {
  double samples_per_s = 0.0;
  int64_t received = 0, stored = 0;
  std::array<int64_t, 2> requests{}, failed_requests{};  // /metrics, /api/v1/history
  std::array<double, 2> request_s{};                     // summed latency
  int last_failed_status = 0;                            // -1: no answer
  std::string error;
};
ReplayRun replay_once(bool server, bool hammer, const std::filesystem::path& dir) {
  ReplayRun out;
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  DaemonConfig config;
  config.storage.db_path = (dir / "bench.db").string();
  config.lcm.url = "file://" + replay_log() + "?speed=0";
  config.http.listen = server ? "127.0.0.1:0" : "";
  const auto t0 = std::chrono::steady_clock::now();
  Daemon daemon(config);
  if (auto error = daemon.open(); !error.empty()) {
    out.error = error;
    return out;
  }
  std::atomic<bool> done{false};
  std::thread client;
  if (hammer) {
    client = std::thread([&, port = daemon.http_port()] {
      httplib::Client http("127.0.0.1", port);
      while (!done.load()) {
        for (const size_t i : {0, 1}) {
          const auto t = std::chrono::steady_clock::now();
          const auto reply = http.Get(i == 0 ? "/metrics" : "/api/v1/history?sat=SAT-0");
          out.request_s[i] +=
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
          ++out.requests[i];
          // 400: SAT-0 has no history yet (the first seconds of the replay).
          if (!reply || (reply->status != 200 && reply->status != 400)) {
            ++out.failed_requests[i];
            out.last_failed_status = reply ? reply->status : -1;
          }
        }
      }
    });
  }
  const std::atomic<bool> stop{false};
  const int rc = daemon.run(stop);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  done.store(true);
  if (client.joinable()) client.join();
  out.received = daemon.counters().received.load();
  out.stored = daemon.counters().stored.load();
  out.samples_per_s = static_cast<double>(out.stored) / seconds;
  if (rc != 0) out.error = "magcald exit code " + std::to_string(rc);
  return out;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

// Paired rounds (server off, on, on + client) so that load from elsewhere on the machine hits
// the three alike; medians over the rounds.
void BM_DaemonReplayHttp(benchmark::State& state) {
  const int rounds = static_cast<int>(state.range(0));
  const auto dir = std::filesystem::temp_directory_path() /
                   ("magcal_replay_bench_" + std::to_string(::getpid()));
  std::vector<double> off, on, hammered;
  int64_t sent = 0, stored = 0;
  std::array<int64_t, 2> requests{}, failed{};
  std::array<double, 2> request_s{};
  int last_failed_status = 0;
  for (auto _ : state) {
    for (int r = 0; r < rounds; ++r) {
      for (const auto& [server, hammer, into] :
           {std::tuple{false, false, &off}, {true, false, &on}, {true, true, &hammered}}) {
        const ReplayRun run = replay_once(server, hammer, dir);
        if (!run.error.empty() || run.stored != run.received) {
          state.SkipWithError(run.error.empty() ? "samples lost: stored != received"
                                                : run.error.c_str());
          std::filesystem::remove_all(dir);
          return;
        }
        into->push_back(run.samples_per_s);
        sent += run.received;
        stored += run.stored;
        for (size_t i = 0; i < 2; ++i) {
          requests[i] += run.requests[i];
          failed[i] += run.failed_requests[i];
          request_s[i] += run.request_s[i];
        }
        if (run.last_failed_status != 0) last_failed_status = run.last_failed_status;
      }
    }
  }
  std::filesystem::remove_all(dir);
  const double m_off = median(off), m_on = median(on), m_hammered = median(hammered);
  state.SetItemsProcessed(sent);
  state.counters["samples_per_s_server_off"] = m_off;
  state.counters["samples_per_s_server_on"] = m_on;
  state.counters["samples_per_s_server_on_client_hammering"] = m_hammered;
  state.counters["drop_with_server_pct"] = 100.0 * (1.0 - m_on / m_off);
  state.counters["drop_with_client_pct"] = 100.0 * (1.0 - m_hammered / m_on);
  state.counters["sent"] = static_cast<double>(sent);
  state.counters["stored"] = static_cast<double>(stored);
  for (size_t i = 0; i < 2; ++i) {
    const std::string path = i == 0 ? "metrics" : "history";
    state.counters[path + "_requests"] = static_cast<double>(requests[i]);
    state.counters[path + "_failed"] = static_cast<double>(failed[i]);
    state.counters[path + "_mean_latency_s"] =
        requests[i] > 0 ? request_s[i] / static_cast<double>(requests[i]) : 0.0;
  }
  state.counters["http_last_failed_status"] = last_failed_status;
}
BENCHMARK(BM_DaemonReplayHttp)->Arg(5)->Iterations(1)->Unit(benchmark::kSecond)->UseRealTime();

// Heap bytes in use (glibc): RSS deltas are hidden by memory the allocator already holds.
double heap_bytes() {
  return static_cast<double>(mallinfo2().uordblks);
}

// Memory per tracked spacecraft: heap growth over N trackers (each with an initialised UKF),
// i.e. map nodes, buckets and id strings included, and the structural estimate (sizeof tracker
// + map node + bucket).
void BM_TrackerMemory(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  double bytes_per = 0.0;
  for (auto _ : state) {
    const double before = heap_bytes();
    auto fleet = std::make_unique<SpacecraftFleet>(MagnetometerUkf::Options{});
    for (int i = 0; i < n; ++i) {
      auto& t = fleet->get("SAT-" + std::to_string(i));
      t.ukf.update(Eigen::Vector3d(20000.0, 1000.0, 30000.0), 36000.0, kT0);
    }
    bytes_per = (heap_bytes() - before) / n;
    benchmark::DoNotOptimize(fleet.get());
  }
  state.counters["heap_bytes_per_spacecraft"] = bytes_per;
  state.counters["sizeof_bytes_per_spacecraft"] =
      static_cast<double>(SpacecraftFleet::approx_bytes_per_spacecraft());
}
BENCHMARK(BM_TrackerMemory)->Arg(1000)->Arg(10000)->Iterations(1)->Unit(benchmark::kMillisecond);

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
