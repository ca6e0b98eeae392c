// Mutation fuzzer of the ingest path (issue 11): valid encoded mag_sample_t and mag_batch_t
// frames are bit-flipped, truncated, extended, overwritten, given extreme field values
// (int64 limits in utime and seq, NaN/Inf in every double, huge or negative batch n, empty,
// non-UTF-8, 10 000-character and 3 000 random-character sat ids), then driven through the daemon's
// real path in-process: decode_frame (service/daemon/intake/lcm_ingest.cpp) with the receive side's
// accounting, then IngestWorker on a new database, SQLite and PostgreSQL
// (tests/storage/storage_backends.hpp; the PostgreSQL case is skipped without the server programs).
// CI runs it under ASan+UBSan: no crash, no sanitizer report, the worker never gives up on storage,
// and every frame is accounted for: received == stored + rejected (per reason, decode failures
// included), and the database holds exactly the stored samples.
#include <catch2/catch.hpp>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>

#include "service/daemon/ingest_worker.hpp"
#include "service/daemon/intake/lcm_ingest.hpp"
#include "tests/storage/storage_backends.hpp"

using namespace magcal;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

constexpr int kFrames = 200'000;
constexpr uint64_t kSeed = 0x6D616763616C;  // fixed: a failure reproduces
constexpr int64_t kT0 = 1704067200000000;   // 2024-01-01T00:00:00Z
constexpr int64_t kStep = 10'000'000;       // 10 s per spacecraft
constexpr int kSpacecraft = 4;

template <typename Msg>
std::vector<uint8_t> encode(const Msg& msg) {
  std::vector<uint8_t> b(static_cast<size_t>(msg.getEncodedSize()));
  REQUIRE(msg.encode(b.data(), 0, static_cast<int>(b.size())) == static_cast<int>(b.size()));
  return b;
}

class FrameMaker {
 public:
  explicit FrameMaker(std::mt19937_64& rng) : rng_(rng) {}

  // The next valid sample of spacecraft `sat` (its stream advances 10 s per sample).
  mag_sample_t next_sample(int sat) {
    const int64_t k = next_k_[static_cast<size_t>(sat)]++;
    mag_sample_t s{};
    s.utime = kT0 + k * kStep;
    s.sat_id = "FUZZ-" + std::to_string(sat);
    s.seq = k;
    const double a = 0.0021 * static_cast<double>(k), c = 0.0013 * static_cast<double>(k);
    const double h[3] = {30000.0 * std::cos(a) * std::cos(c), 30000.0 * std::sin(a) * std::cos(c),
                         30000.0 * std::sin(c)};
    for (int i = 0; i < 3; ++i) {
      s.h_body_nT[i] = h[i];
      s.b_sensor_nT[i] = h[i] + 500.0 * (i + 1) + noise_(rng_);
    }
    if (unit_(rng_) < 0.1) {  // some need IGRF (position + attitude) instead
      s.has_position = true;
      s.r_ecef_m[0] = 6.9e6 * std::cos(a);
      s.r_ecef_m[1] = 6.9e6 * std::sin(a);
      s.r_ecef_m[2] = 1.0e5;
      s.has_attitude = true;
      s.q_body_from_eci[0] = std::cos(c);
      s.q_body_from_eci[3] = std::sin(c);
    } else {
      s.has_reference = true;
    }
    s.temperature_C = 20.0f;
    return s;
  }

  // NaN, +-Inf, or a finite extreme.
  double special_double() {
    static const double kValues[] = {std::numeric_limits<double>::quiet_NaN(),
                                     std::numeric_limits<double>::infinity(),
                                     -std::numeric_limits<double>::infinity(),
                                     std::numeric_limits<double>::max(),
                                     -std::numeric_limits<double>::max(),
                                     std::numeric_limits<double>::denorm_min(),
                                     -0.0};
    return kValues[pick(std::size(kValues))];
  }
  int64_t special_int64() {
    static const int64_t kValues[] = {std::numeric_limits<int64_t>::min(),
                                      std::numeric_limits<int64_t>::min() + 1,
                                      std::numeric_limits<int64_t>::max(),
                                      std::numeric_limits<int64_t>::max() - 1,
                                      0,
                                      -1,
                                      kT0 + 20LL * 3600 * 1000000,
                                      kT0 - 20LL * 3600 * 1000000};
    const size_t i = pick(std::size(kValues) + 1);
    return i < std::size(kValues) ? kValues[i] : static_cast<int64_t>(rng_());
  }
  std::string special_sat_id() {
    switch (pick(4)) {
      case 0:
        return "";
      case 1: {
        if (pick(2) == 0) return std::string(10000, 'S');
        std::string s(3000, ' ');  // incompressible
        for (auto& ch : s) ch = static_cast<char>('A' + pick(26));
        return s;
      }
      case 2: {
        std::string s(1 + pick(40), ' ');
        for (auto& ch : s) ch = static_cast<char>(1 + pick(255));  // no NUL (LCM strings)
        return s;
      }
      default:
        return "FUZZ-" + std::to_string(pick(kSpacecraft + 2));  // maybe another one's
    }
  }

  // One structured extreme into `s`.
  void extreme_field(mag_sample_t& s) {
    double* doubles[] = {&s.b_sensor_nT[0],     &s.b_sensor_nT[1],     &s.b_sensor_nT[2],
                         &s.r_ecef_m[0],        &s.r_ecef_m[1],        &s.r_ecef_m[2],
                         &s.q_body_from_eci[0], &s.q_body_from_eci[1], &s.q_body_from_eci[2],
                         &s.q_body_from_eci[3], &s.h_body_nT[0],       &s.h_body_nT[1],
                         &s.h_body_nT[2]};
    switch (pick(7)) {
      case 0:
        s.utime = special_int64();
        break;
      case 1:
        s.seq = special_int64();
        break;
      case 2:
        *doubles[pick(std::size(doubles))] = special_double();
        break;
      case 3:  // every double at once
        for (double* d : doubles) *d = special_double();
        s.temperature_C = static_cast<float>(special_double());
        break;
      case 4:
        s.has_position = pick(2) != 0;
        s.has_attitude = pick(2) != 0;
        s.has_reference = pick(2) != 0;
        break;
      case 5:
        s.sat_id = special_sat_id();
        break;
      default:
        s.temperature_C = static_cast<float>(special_double());
        break;
    }
  }

  size_t pick(size_t n) { return std::uniform_int_distribution<size_t>(0, n - 1)(rng_); }
  double unit() { return unit_(rng_); }
  std::mt19937_64& rng() { return rng_; }

 private:
  std::mt19937_64& rng_;
  std::normal_distribution<double> noise_{0.0, 3.0};
  std::uniform_real_distribution<double> unit_{0.0, 1.0};
  std::array<int64_t, kSpacecraft> next_k_{};
};

// Byte-level mutations of an encoded frame.
void mutate_bytes(std::vector<uint8_t>& b, FrameMaker& m) {
  switch (m.pick(4)) {
    case 0:  // flip 1-8 bits
      for (size_t i = 0, n = 1 + m.pick(8); i < n && !b.empty(); ++i)
        b[m.pick(b.size())] ^= static_cast<uint8_t>(1u << m.pick(8));
      break;
    case 1:  // truncate
      b.resize(m.pick(b.size() + 1));
      break;
    case 2:  // extend with random bytes
      for (size_t i = 0, n = 1 + m.pick(64); i < n; ++i)
        b.push_back(static_cast<uint8_t>(m.pick(256)));
      break;
    default:  // overwrite a run
      if (!b.empty()) {
        const size_t at = m.pick(b.size());
        for (size_t i = at; i < std::min(b.size(), at + 1 + m.pick(16)); ++i)
          b[i] = static_cast<uint8_t>(m.pick(256));
      }
      break;
  }
}

// A batch frame's n field (big-endian int32 after the fingerprint and the batch sat_id).
void set_batch_n(std::vector<uint8_t>& b, const mag_batch_t& batch, int32_t n) {
  const size_t at = 8 + 4 + batch.sat_id.size() + 1;
  const auto u = static_cast<uint32_t>(n);
  for (int i = 0; i < 4; ++i)
    b[at + static_cast<size_t>(i)] = static_cast<uint8_t>(u >> (24 - 8 * i));
}

}  // namespace

TEMPLATE_TEST_CASE("mutated frames: no crash, every frame accounted for", "[ingest][fuzz]",
                   SqliteBackend, PostgresBackend) {
  TestType backend;
  DaemonConfig config;
  config.storage.db_path = backend.new_database();
  if (config.storage.db_path.empty()) return;  // skipped
  // Retention deletes nothing (the streams span days): the database holds every stored sample.
  config.storage.retention_margin_hours = 1e5;
  DaemonCounters counters;
  IngestWorker worker(config, counters, std::make_unique<ReferenceField>(), IngestWorker::Hooks{});
  std::mt19937_64 rng(kSeed);
  FrameMaker maker(rng);
  const int64_t receive_utime = kT0 + 365LL * 86400 * 1000000;

  int64_t frames_decoded = 0, frames_undecodable = 0, frames_mutated = 0;
  IngestItem item;
  const auto start = std::chrono::steady_clock::now();
  for (int f = 0; f < kFrames; ++f) {
    const int sat = static_cast<int>(maker.pick(kSpacecraft));
    const bool as_batch = maker.pick(2) == 0;
    std::vector<uint8_t> bytes;
    const double u = maker.unit();
    const bool structured = u < 0.25, byte_level = u >= 0.25 && u < 0.65;
    if (as_batch) {
      mag_batch_t batch;
      batch.sat_id = "FUZZ-" + std::to_string(sat);
      const size_t n = 1 + maker.pick(8);
      for (size_t i = 0; i < n; ++i) batch.samples.push_back(maker.next_sample(sat));
      if (structured) {
        if (maker.pick(5) == 0) {
          batch.sat_id = maker.special_sat_id();
        } else {
          maker.extreme_field(batch.samples[maker.pick(n)]);
        }
      }
      batch.n = static_cast<int32_t>(batch.samples.size());
      bytes = encode(batch);
      if (structured && maker.pick(4) == 0) {  // n that does not match the samples
        static const int32_t kNs[] = {std::numeric_limits<int32_t>::max(),
                                      std::numeric_limits<int32_t>::min(), -1, 0, 1 << 20};
        set_batch_n(
            bytes, batch,
            maker.pick(2) ? kNs[maker.pick(std::size(kNs))] : batch.n + (maker.pick(2) ? 1 : -1));
      }
    } else {
      mag_sample_t s = maker.next_sample(sat);
      if (structured) maker.extreme_field(s);
      bytes = encode(s);
    }
    if (byte_level) mutate_bytes(bytes, maker);
    frames_mutated += structured || byte_level;

    // What LcmIngest::on_frame does with a received frame.
    const auto outcome = decode_frame(bytes.data(), static_cast<int>(bytes.size()), as_batch, item);
    if (outcome != DecodeOutcome::kOk) {
      ++frames_undecodable;
      counters.received.fetch_add(1);
      counters.reject(outcome == DecodeOutcome::kWrongType ? RejectReason::kWrongType
                                                           : RejectReason::kDecodeError);
      continue;
    }
    ++frames_decoded;
    counters.received.fetch_add(static_cast<int64_t>(item.samples.size()));
    if (item.samples.empty()) continue;
    item.receive_utime = receive_utime;
    worker.process(item);
    if (f % 1000 == 999) worker.commit();
  }
  worker.settle_held();  // shutdown: what is still held is counted
  worker.commit();
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  std::string reasons;
  for (int r = 0; r < kRejectReasonCount; ++r) {
    const auto n = counters.rejected_count(static_cast<RejectReason>(r));
    if (n > 0)
      reasons +=
          " " + std::string(to_string(static_cast<RejectReason>(r))) + "=" + std::to_string(n);
  }
  const int64_t in_database =
      magcal::test::query_int(*backend.open_again(), "SELECT count(*) FROM samples");
  std::printf(
      "ingest fuzz (%s): %d frames (seed %#llx, %lld mutated): %lld decoded, %lld undecodable; "
      "%lld samples received, %lld stored, %lld rejected (%s ); %lld in the database; %zu "
      "spacecraft; %.1f s\n",
      TestType::kName, kFrames, static_cast<unsigned long long>(kSeed),
      static_cast<long long>(frames_mutated), static_cast<long long>(frames_decoded),
      static_cast<long long>(frames_undecodable), static_cast<long long>(counters.received.load()),
      static_cast<long long>(counters.stored.load()),
      static_cast<long long>(counters.rejected_total()), reasons.c_str(),
      static_cast<long long>(in_database), worker.n_spacecraft(), elapsed_s);
  std::fflush(stdout);

  CHECK(frames_decoded + frames_undecodable == kFrames);
  CHECK(worker.held_samples() == 0);
  CHECK(worker.pending_samples() == 0);
  CHECK(counters.received.load() == counters.stored.load() + counters.rejected_total());
  CHECK(in_database == counters.stored.load());
  CHECK(counters.storage_failures.load() == 0);
  // The fuzzer reached every stage: valid samples stored, each kind of rejection seen.
  CHECK(counters.stored.load() > kFrames / 2);
  for (const auto r :
       {RejectReason::kDecodeError, RejectReason::kWrongType, RejectReason::kNonFinite,
        RejectReason::kInvalidSatId, RejectReason::kBatchSatMismatch, RejectReason::kTimeOutOfRange,
        RejectReason::kTimeJump, RejectReason::kFutureTime, RejectReason::kOlderThanWindow}) {
    INFO(to_string(r));
    CHECK(counters.rejected_count(r) > 0);
  }
}

TEST_CASE("decode_frame: corrupt string lengths and batch counts are decode errors",
          "[ingest][fuzz]") {
  // lcmgen's decoders would throw std::length_error on a string length <= 0 and allocate
  // n samples before reading them; these are the frames the fuzzer first found.
  mag_batch_t batch;
  batch.sat_id = "SAT-1";
  mag_sample_t s{};
  s.utime = kT0;
  s.sat_id = "SAT-1";
  batch.samples = {s, s};
  batch.n = 2;
  const auto good = encode(batch);
  IngestItem item;
  REQUIRE(decode_frame(good.data(), static_cast<int>(good.size()), true, item) ==
          DecodeOutcome::kOk);
  CHECK(item.samples.size() == 2);
  for (const int32_t n :
       {std::numeric_limits<int32_t>::max(), std::numeric_limits<int32_t>::min(), -1, 1 << 20}) {
    auto b = good;
    set_batch_n(b, batch, n);
    INFO("n = " << n);
    CHECK(decode_frame(b.data(), static_cast<int>(b.size()), true, item) ==
          DecodeOutcome::kDecodeError);
    CHECK(item.samples.empty());
  }
  for (const int32_t len : {0, -1, std::numeric_limits<int32_t>::min()}) {
    INFO("string length " << len);
    auto b = good;  // the batch's sat_id length
    for (int i = 0; i < 4; ++i)
      b[8 + static_cast<size_t>(i)] =
          static_cast<uint8_t>(static_cast<uint32_t>(len) >> (24 - 8 * i));
    CHECK(decode_frame(b.data(), static_cast<int>(b.size()), true, item) ==
          DecodeOutcome::kDecodeError);
    auto one = encode(s);  // a sample's sat_id length, after its utime
    for (int i = 0; i < 4; ++i)
      one[16 + static_cast<size_t>(i)] =
          static_cast<uint8_t>(static_cast<uint32_t>(len) >> (24 - 8 * i));
    CHECK(decode_frame(one.data(), static_cast<int>(one.size()), false, item) ==
          DecodeOutcome::kDecodeError);
  }
}
