// The LCM receive side of magcald (design.md "Daemon data flow", toolchain.md "LCM 1.3.1").
//
// Subscribes RAW (no typed subscribe: a typed handler that fails to decode only prints to
// stderr) to the samples and batch channels, with setQueueCapacity(0) so LCM itself never
// drops (its default keeps 30 messages and silently discards the rest); the bound is our
// IngestQueue, whose overflow is counted. The handler only decodes and hands off. The loop is
// handleTimeout() with a stop flag (set from SIGINT/SIGTERM). With a file:// URL the provider
// reports the end of the log, which ends run() with kEndOfLog (replay mode).
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <unordered_map>

#include <lcm/lcm-cpp.hpp>

#include "service/daemon/intake/ingest_queue.hpp"
#include "service/daemon/ops/health.hpp"

namespace magcal {

enum class DecodeOutcome { kOk, kWrongType, kDecodeError };

// Decodes one frame of the samples channel (expect_batch = false: a mag_sample_t) or of the
// batch channel (a mag_batch_t) into `out`. kWrongType: the fingerprint is not the expected
// type's; kDecodeError: right fingerprint but truncated/corrupt (or shorter than a fingerprint,
// or any string length or batch count that does not fit the frame: checked before lcmgen's
// decoder, which trusts them). Never throws.
DecodeOutcome decode_frame(const void* data, int size, bool expect_batch, IngestItem& out);

class LcmIngest {
 public:
  enum class End { kStopped, kEndOfLog, kError };

  // Subscribes immediately; `lcm` must be good() and outlive this object. Counts the samples
  // received in `counters`, per spacecraft too (a batch counts under its sat_id, an undecodable
  // frame as 1 under "").
  LcmIngest(lcm::LCM& lcm, const std::string& samples_channel, const std::string& batch_channel,
            IngestQueue& queue, DaemonCounters& counters);
  ~LcmIngest();
  LcmIngest(const LcmIngest&) = delete;
  LcmIngest& operator=(const LcmIngest&) = delete;

  // Receives until `stop` or `*abort` is set (kStopped), the log ends (kEndOfLog: file://
  // only) or the provider fails (kError).
  End run(const std::atomic<bool>& stop, bool is_file_provider,
          const std::atomic<bool>* abort = nullptr);

 private:
  static void on_samples(const lcm::ReceiveBuffer* rbuf, const std::string& channel,
                         LcmIngest* self);
  static void on_batch(const lcm::ReceiveBuffer* rbuf, const std::string& channel, LcmIngest* self);
  void on_frame(const lcm::ReceiveBuffer* rbuf, bool batch);
  void count_received(const std::string& sat_id, int64_t n);

  lcm::LCM& lcm_;
  IngestQueue& queue_;
  DaemonCounters& counters_;
  // This thread's own cache of the per-spacecraft counters (no lock, no allocation once seen).
  std::unordered_map<std::string, SpacecraftCounters*> received_by_sat_;
  lcm::Subscription* samples_sub_ = nullptr;
  lcm::Subscription* batch_sub_ = nullptr;
};

// True for file:// URLs (replay mode).
bool is_file_url(const std::string& url);

// The LCM URL as the start log shows it: 'url' when given; an empty one is what LCM opens then,
// $LCM_DEFAULT_URL ("'memq://' (LCM_DEFAULT_URL)") or LCM's own default
// ("default 'udpm://239.255.76.67:7667?ttl=0'").
std::string lcm_url_for_log(const std::string& url);

// An lcm::LCM on `url` (check good()). LCM itself prints why it cannot open a URL on stderr
// ("Error: LCM provider "x" not found"); that text is taken instead and, when the instance is
// not good(), returned in *why without LCM's prefixes, for the caller's one line. Whatever LCM
// says of a URL it does open (a warning) still reaches stderr.
std::unique_ptr<lcm::LCM> open_lcm(const std::string& url, std::string* why);

// Why LCM could not open the log of a file:// URL, for the start error: what
// unreadable_lcm_log_reason (service/io/sample_checks.hpp) says of its file, else that LCM
// refused the URL's options.
std::string unreadable_log_reason(const std::string& file_url);

}  // namespace magcal
