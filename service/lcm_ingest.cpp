#include "service/lcm_ingest.hpp"

#include <chrono>
#include <stdexcept>

#include "schemas/magcal_messages.hpp"

namespace magcal {
namespace {

int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// The fingerprint LCM writes in front of every encoded message (big-endian int64).
bool has_fingerprint(const void* data, int size, int64_t hash) {
  if (size < 8) return false;
  const auto* b = static_cast<const uint8_t*>(data);
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | b[i];
  return static_cast<int64_t>(v) == hash;
}

int32_t read_int32_be(const uint8_t* b) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v = (v << 8) | b[i];
  return static_cast<int32_t>(v);
}

// The smallest encoded mag_sample_t: utime, sat_id (int32 length + one NUL), seq, the fixed
// doubles, booleans and the float.
constexpr int64_t kMinEncodedSampleBytes =
    8 + 4 + 1 + 8 + 3 * 8 + 1 + 3 * 8 + 1 + 4 * 8 + 1 + 3 * 8 + 4;

// lcmgen's mag_batch_t decoder resizes `samples` to the frame's n before reading them: a
// corrupt n of 2^31 - 1 would allocate hundreds of GB. n must fit in the bytes that follow.
bool plausible_batch_header(const uint8_t* b, int size) {
  int64_t pos = 8;  // fingerprint
  if (size < pos + 4) return false;
  const int32_t sat_len = read_int32_be(b + pos);
  pos += 4;
  if (sat_len < 1 || sat_len > size - pos) return false;
  pos += sat_len;
  if (size < pos + 4) return false;
  const int32_t n = read_int32_be(b + pos);
  pos += 4;
  return n >= 0 && n <= (size - pos) / kMinEncodedSampleBytes;
}

}  // namespace

bool is_file_url(const std::string& url) {
  return url.rfind("file://", 0) == 0;
}

DecodeOutcome decode_frame(const void* data, int size, bool expect_batch, IngestItem& out) {
  if (size < 8) return DecodeOutcome::kDecodeError;
  out.from_batch = expect_batch;
  out.samples.clear();
  out.batch_sat_id.clear();
  // lcmgen's decoders call std::string::assign(p, length - 1) with an unchecked string length
  // of 0 or less, which throws std::length_error: a corrupt frame, not a daemon failure.
  try {
    if (expect_batch) {
      if (!has_fingerprint(data, size, mag_batch_t::getHash())) return DecodeOutcome::kWrongType;
      if (!plausible_batch_header(static_cast<const uint8_t*>(data), size)) {
        return DecodeOutcome::kDecodeError;
      }
      mag_batch_t batch;
      if (batch.decode(data, 0, size) != size) return DecodeOutcome::kDecodeError;
      out.batch_sat_id = std::move(batch.sat_id);
      out.samples = std::move(batch.samples);
      return DecodeOutcome::kOk;
    }
    if (!has_fingerprint(data, size, mag_sample_t::getHash())) return DecodeOutcome::kWrongType;
    out.samples.resize(1);
    if (out.samples[0].decode(data, 0, size) != size) {
      out.samples.clear();
      return DecodeOutcome::kDecodeError;
    }
    return DecodeOutcome::kOk;
  } catch (const std::length_error&) {
    out.samples.clear();
    out.batch_sat_id.clear();
    return DecodeOutcome::kDecodeError;
  }
}

LcmIngest::LcmIngest(lcm::LCM& lcm, const std::string& samples_channel,
                     const std::string& batch_channel, IngestQueue& queue, DaemonCounters& counters)
    : lcm_(lcm), queue_(queue), counters_(counters) {
  samples_sub_ = lcm_.subscribeFunction(samples_channel, &LcmIngest::on_samples, this);
  batch_sub_ = lcm_.subscribeFunction(batch_channel, &LcmIngest::on_batch, this);
  // Unbounded inside LCM (its default of 30 drops silently); IngestQueue is the bound.
  samples_sub_->setQueueCapacity(0);
  batch_sub_->setQueueCapacity(0);
}

LcmIngest::~LcmIngest() {
  lcm_.unsubscribe(samples_sub_);
  lcm_.unsubscribe(batch_sub_);
}

void LcmIngest::on_samples(const lcm::ReceiveBuffer* rbuf, const std::string&, LcmIngest* self) {
  self->on_frame(rbuf, false);
}
void LcmIngest::on_batch(const lcm::ReceiveBuffer* rbuf, const std::string&, LcmIngest* self) {
  self->on_frame(rbuf, true);
}

void LcmIngest::on_frame(const lcm::ReceiveBuffer* rbuf, bool batch) {
  IngestItem item;
  const auto outcome = decode_frame(rbuf->data, static_cast<int>(rbuf->data_size), batch, item);
  if (outcome != DecodeOutcome::kOk) {
    // One undecodable frame = one received, one rejected (its sample count is unknowable).
    counters_.received.fetch_add(1, std::memory_order_relaxed);
    counters_.reject(outcome == DecodeOutcome::kWrongType ? RejectReason::kWrongType
                                                          : RejectReason::kDecodeError);
    return;
  }
  counters_.received.fetch_add(static_cast<int64_t>(item.samples.size()),
                               std::memory_order_relaxed);
  if (item.samples.empty()) return;
  item.receive_utime = wall_utime();
  queue_.push(std::move(item));  // overflow is counted by the queue
}

LcmIngest::End LcmIngest::run(const std::atomic<bool>& stop, bool is_file_provider,
                              const std::atomic<bool>* abort) {
  auto stopped = [&] {
    return stop.load(std::memory_order_relaxed) ||
           (abort && abort->load(std::memory_order_relaxed));
  };
  int failures = 0;
  while (!stopped()) {
    const int rc = lcm_.handleTimeout(100);
    if (rc >= 0) {
      failures = 0;
      continue;
    }
    if (stopped()) break;  // a signal interrupted the wait
    if (is_file_provider) return End::kEndOfLog;
    // Live provider: an interrupted wait (EINTR) is harmless; a provider that keeps failing
    // is not.
    if (++failures >= 10) return End::kError;
  }
  return End::kStopped;
}

}  // namespace magcal
