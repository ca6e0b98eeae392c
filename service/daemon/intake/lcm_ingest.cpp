#include "service/daemon/intake/lcm_ingest.hpp"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <sstream>

#include "pipeline/time_utc.hpp"
#include "schemas/magcal_messages.hpp"
#include "service/io/sample_checks.hpp"

namespace magcal {
namespace {

// The fingerprint LCM writes in front of every encoded message (big-endian int64).
bool has_fingerprint(const void* data, int size, int64_t hash) {
  if (size < 8) return false;
  const auto* b = static_cast<const uint8_t*>(data);
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | b[i];
  return static_cast<int64_t>(v) == hash;
}

}  // namespace

bool is_file_url(const std::string& url) {
  return url.rfind("file://", 0) == 0;
}

std::string lcm_url_for_log(const std::string& url) {
  // Appended piecewise: "'" + url + "'" draws a false -Wrestrict from GCC 12.
  std::string out = "'";
  if (!url.empty()) return (out += url) += "'";
  // lcm_create(NULL): LCM_DEFAULT_URL when set and not empty, else its built-in default.
  if (const char* env = std::getenv("LCM_DEFAULT_URL"); env != nullptr && *env != '\0')
    return (out += env) += "' (LCM_DEFAULT_URL)";
  return "default 'udpm://239.255.76.67:7667?ttl=0'";
}

std::unique_ptr<lcm::LCM> open_lcm(const std::string& url, std::string* why) {
  // stderr goes to an unlinked temporary file while LCM starts (the daemon's other threads do
  // not run yet).
  std::fflush(stderr);
  FILE* capture = std::tmpfile();
  const int saved_stderr = capture ? ::dup(STDERR_FILENO) : -1;
  if (saved_stderr >= 0) ::dup2(::fileno(capture), STDERR_FILENO);
  auto lcm = std::make_unique<lcm::LCM>(url);
  std::string said;
  if (saved_stderr >= 0) {
    std::fflush(stderr);
    ::dup2(saved_stderr, STDERR_FILENO);
    ::close(saved_stderr);
    std::rewind(capture);
    char buffer[512];
    for (size_t n; (n = std::fread(buffer, 1, sizeof buffer, capture)) > 0;) said.append(buffer, n);
  }
  if (capture) std::fclose(capture);
  if (lcm->good()) {
    std::fputs(said.c_str(), stderr);
    return lcm;
  }
  // "Error: Bad multicast port "99999"", "lcm.c:97 -- invalid URL [x]": the words after the
  // prefix, one clause per line.
  why->clear();
  std::istringstream lines(said);
  for (std::string line; std::getline(lines, line);) {
    if (const size_t dashes = line.find(" -- "); dashes != std::string::npos) {
      line.erase(0, dashes + 4);
    }
    if (line.rfind("Error: ", 0) == 0) line.erase(0, 7);
    if (!line.empty()) *why += (why->empty() ? "" : "; ") + line;
  }
  if (why->empty()) *why = "LCM refused it";
  return lcm;
}

std::string unreadable_log_reason(const std::string& file_url) {
  std::string path = file_url.substr(std::string("file://").size());
  path = path.substr(0, path.find('?'));  // the provider's options
  if (std::string why = unreadable_lcm_log_reason(path); !why.empty()) return why;
  return path + ": LCM refused the URL (check its options)";
}

DecodeOutcome decode_frame(const void* data, int size, bool expect_batch, IngestItem& out) {
  if (size < 8) return DecodeOutcome::kDecodeError;
  out.from_batch = expect_batch;
  out.samples.clear();
  out.batch_sat_id.clear();
  const int64_t hash = expect_batch ? mag_batch_t::getHash() : mag_sample_t::getHash();
  if (!has_fingerprint(data, size, hash)) return DecodeOutcome::kWrongType;
  if (!well_formed_lcm_frame(data, size, expect_batch)) return DecodeOutcome::kDecodeError;
  if (expect_batch) {
    mag_batch_t batch;
    if (batch.decode(data, 0, size) != size) return DecodeOutcome::kDecodeError;
    out.batch_sat_id = std::move(batch.sat_id);
    out.samples = std::move(batch.samples);
    return DecodeOutcome::kOk;
  }
  out.samples.resize(1);
  if (out.samples[0].decode(data, 0, size) != size) {
    out.samples.clear();
    return DecodeOutcome::kDecodeError;
  }
  return DecodeOutcome::kOk;
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

void LcmIngest::count_received(const std::string& sat_id, int64_t n) {
  auto it = received_by_sat_.find(sat_id);
  if (it == received_by_sat_.end()) {
    SpacecraftCounters& c = counters_.spacecraft.spacecraft(sat_id);
    // Bounded like the table (hostile ids must not grow it): past the cap, look up each time.
    if (received_by_sat_.size() >= SpacecraftCounterTable::kMaxSpacecraft) {
      c.received.fetch_add(n, std::memory_order_relaxed);
      return;
    }
    it = received_by_sat_.emplace(sat_id, &c).first;
  }
  it->second->received.fetch_add(n, std::memory_order_relaxed);
}

void LcmIngest::on_frame(const lcm::ReceiveBuffer* rbuf, bool batch) {
  IngestItem item;
  const auto outcome = decode_frame(rbuf->data, static_cast<int>(rbuf->data_size), batch, item);
  if (outcome != DecodeOutcome::kOk) {
    // One undecodable frame = one received, one rejected (its sample count is unknowable).
    counters_.received.fetch_add(1, std::memory_order_relaxed);
    count_received(std::string(), 1);
    counters_.reject(outcome == DecodeOutcome::kWrongType ? RejectReason::kWrongType
                                                          : RejectReason::kDecodeError);
    return;
  }
  counters_.received.fetch_add(static_cast<int64_t>(item.samples.size()),
                               std::memory_order_relaxed);
  if (batch) {
    count_received(item.batch_sat_id, static_cast<int64_t>(item.samples.size()));
  } else if (!item.samples.empty()) {
    count_received(item.samples[0].sat_id, 1);
  }
  if (item.samples.empty()) return;
  item.receive_utime = now_utime();
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
