// magcald as a real process (issue 6 "Done when"): replay of a simulated day via file:// (and,
// when multicast works here, live over udpm with lcm-logplayer and an independent lcm-logger);
// SIGTERM mid-stream then restart; a stream of malformed frames. Results are read back by
// independent decoders (lcm::LogFile + the generated types, the storage API).
// No sleeps to wait for things: every wait polls its condition against a deadline.
#include <catch2/catch.hpp>

#include "tests/test_skip.hpp"

#include <fcntl.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <set>
#include <thread>

#include <lcm/lcm-cpp.hpp>
#include <nlohmann/json.hpp>

#include "schemas/magcal_messages.hpp"
#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/daemon_test_support.hpp"

namespace {

namespace fs = std::filesystem;
using namespace magcal::test;

constexpr int kSimSamples = 8640;          // 24 h at 10 s (paper scenario)
constexpr double kRefitBiasTol_nT = 10.0;  // refit vs simulator truth, per axis
constexpr double kNoJumpSigmas = 5.0;      // UKF before/after restart
constexpr double kNoJumpFloor_nT = 1.0;

struct TempDir {
  fs::path dir;
  explicit TempDir(const std::string& name) {
    dir = fs::temp_directory_path() / ("magcald_it_" + std::to_string(::getpid()) + "_" + name);
    fs::remove_all(dir);
    fs::create_directories(dir);
  }
  ~TempDir() { fs::remove_all(dir); }
  std::string operator/(const std::string& f) const { return (dir / f).string(); }
};

const std::string kBin = MAGCAL_BIN_DIR;

std::vector<magcal::storage::CalibrationRecord> history(const std::string& db,
                                                        const std::string& sat,
                                                        const std::string& method) {
  magcal::storage::OpenOptions ro;
  ro.read_only = true;
  magcal::storage::Database d(db, ro);
  magcal::storage::SqliteCalibrationHistory h(d);
  magcal::storage::HistoryQuery q;
  q.sat_id = sat;
  q.method = method;
  return h.query(q);
}

int64_t stored_count(const std::string& db, const std::string& sat) {
  try {
    magcal::storage::OpenOptions ro;
    ro.read_only = true;
    magcal::storage::Database d(db, ro);
    magcal::storage::SqliteSampleWindowStore s(d);
    return s.count(sat);
  } catch (const magcal::storage::StorageError&) {
    return -1;  // not created yet
  }
}

void write_config(const std::string& path, const std::string& extra) {
  std::ofstream out(path);
  // Embedded defaults except what a replay needs (the data clock) and full 12 h windows only.
  out << "[refit]\nclock = \"data\"\nevery_hours = 6\nmin_samples = 4000\n" << extra;
}

std::string simulate_day(const TempDir& tmp) {
  const std::string log = tmp / "day.lcm";
  REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "24", "--seed", "1",
               "--out", log, "--truth", tmp / "truth.json", "--batch", "200"},
              tmp / "sim.log") == 0);
  return log;
}

}  // namespace

TEST_CASE("replay a simulated day via file://: all samples, snapshots, data-clock refits",
          "[daemon][integration]") {
  TempDir tmp("replay");
  const std::string log = simulate_day(tmp);
  const std::string out = tmp / "out.lcm";
  write_config(tmp / "d.toml", "[lcm]\npublish_url = \"file://" + out + "?mode=w\"\n");
  const int rc = run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
                      tmp / "m.db", "--lcm-url", "file://" + log + "?speed=0"},
                     tmp / "magcald.log");
  INFO(slurp(tmp / "magcald.log"));
  REQUIRE(rc == 0);

  const auto pub = read_published(out);
  CHECK(pub.undecodable == 0);
  REQUIRE_FALSE(pub.statuses.empty());
  const auto& last = pub.statuses.back();
  CHECK(last.received == kSimSamples);
  CHECK(last.stored == kSimSamples);
  CHECK(last.rejected == 0);
  CHECK(last.queue_overflow == 0);
  CHECK(last.missing_by_seq == 0);
  CHECK(last.n_spacecraft == 1);
  // The first refit once [refit] min_samples (4000 here) are stored and the UKF has started
  // (trigger "first"), then 14:00 and 20:00 (02:00 and 08:00 lack the samples).
  CHECK(last.refits_run == 3);

  const auto ukf = history(tmp / "m.db", "PAPER-1", "ukf");
  const auto refits = history(tmp / "m.db", "PAPER-1", "twostep");
  // One per 60 s of data from the filter's start from data (nothing while it collects), and
  // the start comes within the first orbits.
  REQUIRE(ukf.size() >= 2);
  for (size_t k = 1; k < ukf.size(); ++k) CHECK(ukf[k].utime - ukf[k - 1].utime == 60'000'000);
  CHECK(ukf.size() >= 1200);
  REQUIRE(refits.size() == 3);
  CHECK(refits[0].n_samples >= 4000);
  CHECK(refits[0].n_samples < 4320);  // the first refit: before a full window
  // What was published is what was stored.
  CHECK(pub.calibrations.size() == ukf.size() + refits.size());

  const auto truth = nlohmann::json::parse(slurp(tmp / "truth.json"));
  for (const auto& r : refits) {
    CHECK(r.verdict == "accepted");
    for (int i = 0; i < 3; ++i) {
      CHECK(std::abs(r.bias_nT[static_cast<size_t>(i)] - truth["bias_nT"][i].get<double>()) <
            kRefitBiasTol_nT);
    }
  }
  // Retention keeps the newest window + margin (data time), never the results; it deletes in
  // steps of 10 min of data (60 samples here).
  const int64_t kept = stored_count(tmp / "m.db", "PAPER-1");
  CHECK(kept >= 12 * 360);
  CHECK(kept <= 13 * 360 + 60 + 1);
}

TEST_CASE("a spacecraft backfilled behind another gets the data-clock refits of its own days",
          "[daemon][integration]") {
  // SAT-A's day is in the database; then SAT-B's recording of the same day is replayed into it.
  // Every data time of SAT-B is behind SAT-A's newest sample: a clock shared by the fleet never
  // moves and SAT-B would get no refit at all.
  TempDir tmp("backfill");
  for (const std::string sat : {"SAT-A", "SAT-B"}) {
    REQUIRE(run({kBin + "/magcal", "sim", "--scenario", "paper", "--hours", "24", "--seed",
                 sat == "SAT-A" ? "1" : "2", "--sat-id", sat, "--out", tmp / (sat + ".lcm"),
                 "--batch", "200"},
                tmp / "sim.log") == 0);
  }
  write_config(tmp / "d.toml", "");
  for (const std::string sat : {"SAT-A", "SAT-B"}) {
    const int rc = run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
                        tmp / "m.db", "--lcm-url", "file://" + tmp / (sat + ".lcm") + "?speed=0"},
                       tmp / (sat + ".log"));
    INFO(slurp(tmp / (sat + ".log")));
    REQUIRE(rc == 0);
  }
  const auto refits_a = history(tmp / "m.db", "SAT-A", "twostep");
  const auto refits_b = history(tmp / "m.db", "SAT-B", "twostep");
  // The first refit (4000 samples stored), 14:00 and 20:00 of the day for each (02:00 and 08:00
  // lack the samples): the same times, each spacecraft's refit on its own data.
  REQUIRE(refits_a.size() == 3);
  REQUIRE(refits_b.size() == 3);
  for (size_t k = 0; k < 3; ++k) {
    CHECK(refits_b[k].utime == refits_a[k].utime);
    CHECK(refits_b[k].verdict == "accepted");
    CHECK(refits_b[k].n_samples >= 4000);
  }
  // The second run logged SAT-B's refits (and refitted nothing of SAT-A's).
  const std::string log_b = slurp(tmp / "SAT-B.log");
  INFO(log_b);
  CHECK(log_b.find("refit SAT-B window") != std::string::npos);
  CHECK(log_b.find("refit SAT-A") == std::string::npos);
}

TEST_CASE("live over udpm: lcm-logplayer in, lcm-logger records the results",
          "[daemon][integration][multicast]") {
  const int port = 7700 + static_cast<int>(::getpid() % 200);  // not the default bus
  const std::string url = "udpm://239.255.76.67:" + std::to_string(port) + "?ttl=0";
  if (!multicast_available(url)) {
    magcal::test::skip_or_fail("multicast over loopback unavailable here: live udpm variant");
    return;
  }
  TempDir tmp("udpm");
  const std::string log = simulate_day(tmp);
  // Snapshots every 600 s of data keep the bursts small: lcm-logger drops beyond its queue.
  {
    std::ofstream cfg(tmp / "d.toml");
    cfg << "[refit]\nclock = \"data\"\nevery_hours = 6\nmin_samples = 4000\n"
        << "[ukf]\nsigma_nT = 7.5\nsnapshot_every_s = 600\n[service]\nstatus_every_s = 0.2\n";
  }
  const std::string recorded = tmp / "recorded.lcm";
  const pid_t logger = spawn({"lcm-logger", "--lcm-url=" + url + "&recv_buf_size=4194304", "-c",
                              "MAGCAL_CALIBRATION", "-f", recorded},
                             tmp / "logger.log");
  REQUIRE(logger > 0);
  const pid_t daemon = spawn({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml",
                              "--db", tmp / "m.db", "--lcm-url", url + "&recv_buf_size=4194304"},
                             tmp / "magcald.log");
  REQUIRE(daemon > 0);

  // The daemon is up (and subscribed) once its status messages arrive.
  lcm::LCM listener(url);
  REQUIRE(listener.good());
  // Raw subscriptions decoded here (an independent decoder; unbounded LCM queues).
  struct Listener {
    magcal::daemon_status_t st{};
    int n = 0;
    size_t calibrations = 0;
    int undecodable = 0;
  } heard;
  listener
      .subscribeFunction(
          "MAGCAL_STATUS",
          +[](const lcm::ReceiveBuffer* rb, const std::string&, Listener* l) {
            magcal::daemon_status_t m;
            if (m.decode(rb->data, 0, static_cast<int>(rb->data_size)) < 0) {
              ++l->undecodable;
              return;
            }
            l->st = m;
            ++l->n;
          },
          &heard)
      ->setQueueCapacity(0);
  listener
      .subscribeFunction(
          "MAGCAL_CALIBRATION",
          +[](const lcm::ReceiveBuffer* rb, const std::string&, Listener* l) {
            magcal::calibration_t m;
            if (m.decode(rb->data, 0, static_cast<int>(rb->data_size)) < 0) {
              ++l->undecodable;
              return;
            }
            ++l->calibrations;
          },
          &heard)
      ->setQueueCapacity(0);
  REQUIRE(wait_until(
      [&] {
        listener.handleTimeout(50);
        return heard.n >= 2 && fs::exists(recorded);
      },
      20));

  REQUIRE(run({"lcm-logplayer", "-l", url, "-s", "0", log}, tmp / "player.log") == 0);
  const bool all_stored = wait_until(
      [&] {
        listener.handleTimeout(50);
        return heard.st.stored == kSimSamples;
      },
      30);
  ::kill(daemon, SIGTERM);
  const int rc = wait_exit(daemon, 30);
  const size_t expected = history(tmp / "m.db", "PAPER-1", "ukf").size() +
                          history(tmp / "m.db", "PAPER-1", "twostep").size();
  // lcm-logger flushes every 100 ms: wait for it to have written everything.
  wait_until([&] { return read_published(recorded).calibrations.size() >= expected; }, 10);
  ::kill(logger, SIGINT);
  wait_exit(logger, 10);
  INFO(slurp(tmp / "magcald.log"));
  CHECK(all_stored);
  CHECK(rc == 0);
  CHECK(heard.st.received == kSimSamples);
  CHECK(heard.st.rejected == 0);

  const auto pub = read_published(recorded);
  CHECK(pub.undecodable == 0);
  const auto ukf = history(tmp / "m.db", "PAPER-1", "ukf");
  const auto refits = history(tmp / "m.db", "PAPER-1", "twostep");
  CHECK(refits.size() == 3);  // the first (4000 samples), 14:00, 20:00
  // The independent recorder saw every published result.
  std::set<std::pair<std::string, int64_t>> seen;
  for (const auto& c : pub.calibrations) seen.insert({c.method, c.utime});
  std::string missing;
  for (const auto* rows : {&ukf, &refits}) {
    for (const auto& r : *rows) {
      if (!seen.count({r.method, r.utime}))
        missing += r.method + "@" + std::to_string(r.utime) + " ";
    }
  }
  // Our own subscriber (unbounded LCM queue) must see every result exactly (those of the
  // filter's last reorder delay are published as magcald stops: read until none is left).
  while (listener.handleTimeout(200) > 0) {
  }
  CHECK(heard.calibrations == ukf.size() + refits.size());
  CHECK(heard.undecodable == 0);
  // lcm-logger 1.3.1 itself drops runs of consecutive messages here (measured: 0-20 of 145
  // per run, while the subscriber above, with setQueueCapacity(0), got all of them), so its
  // recording is checked for decodability and reported, not counted exactly.
  if (pub.calibrations.size() != ukf.size() + refits.size()) {
    WARN("lcm-logger recorded " << pub.calibrations.size() << " of " << ukf.size() + refits.size()
                                << " results; not recorded: " << missing);
  }
  CHECK_FALSE(pub.calibrations.empty());
}

TEST_CASE("SIGTERM mid-stream, restart: every sample stored or counted, no jump",
          "[daemon][integration]") {
  TempDir tmp("restart");
  const std::string log = simulate_day(tmp);
  const std::string db = tmp / "m.db";
  // Nothing purged while the day is replayed: where the signal lands depends on the machine's
  // speed, and past 13 h of data retention would delete what the counts below compare.
  const std::string keep_the_day = "[storage]\nretention_margin_hours = 24\n";
  write_config(tmp / "d.toml",
               "[lcm]\npublish_url = \"file://" + tmp / "out1.lcm" + "?mode=w\"\n" + keep_the_day);
  // speed 20000: the day's 43 packets arrive over ~4 s, so the signal lands mid-stream.
  const pid_t d1 = spawn({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml",
                          "--db", db, "--lcm-url", "file://" + log + "?speed=20000"},
                         tmp / "run1.log");
  REQUIRE(d1 > 0);
  REQUIRE(wait_until([&] { return stored_count(db, "PAPER-1") >= 1000; }, 30));
  // An on-demand refit in its own process while the daemon writes (SQLite WAL).
  {
    std::ofstream cfg(tmp / "refit.toml");
    cfg << "[refit]\nmin_samples = 500\n";
  }
  const int refit_rc = run({kBin + "/magcal", "refit", "--db", db, "--sat", "PAPER-1", "--config",
                            tmp / "refit.toml", "--json"},
                           tmp / "refit.json");
  ::kill(d1, SIGTERM);
  const int rc1 = wait_exit(d1, 30);
  INFO(slurp(tmp / "run1.log"));
  REQUIRE(rc1 == 0);
  {
    INFO(slurp(tmp / "refit.json"));
    CHECK(refit_rc == 0);
    const auto j = nlohmann::json::parse(slurp(tmp / "refit.json"), nullptr, false);
    REQUIRE_FALSE(j.is_discarded());
    CHECK(j["method"] == "twostep");
    CHECK(j["n_samples"].get<int>() >= 500);
    CHECK(j.contains("verdict"));
  }
  const auto p1 = read_published(tmp / "out1.lcm");
  REQUIRE_FALSE(p1.statuses.empty());
  const auto s1 = p1.statuses.back();
  CHECK(s1.received == s1.stored + s1.rejected + s1.queue_overflow);  // drained, nothing lost
  CHECK(s1.stored < kSimSamples);                                     // really mid-stream
  CHECK(stored_count(db, "PAPER-1") == s1.stored);
  const auto before = history(db, "PAPER-1", "ukf");
  REQUIRE_FALSE(before.empty());

  // Restart and replay the whole day: what was stored comes back as duplicates.
  write_config(tmp / "d.toml",
               "[lcm]\npublish_url = \"file://" + tmp / "out2.lcm" + "?mode=w\"\n" + keep_the_day);
  const int rc2 = run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
                       db, "--lcm-url", "file://" + log + "?speed=0"},
                      tmp / "run2.log");
  INFO(slurp(tmp / "run2.log"));
  REQUIRE(rc2 == 0);
  const auto s2 = read_published(tmp / "out2.lcm").statuses.back();
  CHECK(s2.received == kSimSamples);
  CHECK(s2.received == s2.stored + s2.rejected);
  CHECK(rejected(s2, "duplicate") == s1.stored);
  CHECK(s1.stored + s2.stored == kSimSamples);

  // The first snapshot after the restart continues from the last one before it.
  const auto after = history(db, "PAPER-1", "ukf");
  REQUIRE(after.size() > before.size());
  const auto& a = before.back();
  const auto& b = after[before.size()];
  CHECK(b.utime > a.utime);
  for (size_t i = 0; i < 3; ++i) {
    const double sigma = std::hypot(a.bias_sigma_nT[i], b.bias_sigma_nT[i]);
    INFO("axis " << i << ": " << a.bias_nT[i] << " -> " << b.bias_nT[i] << " sigma " << sigma);
    CHECK(std::abs(b.bias_nT[i] - a.bias_nT[i]) <=
          std::max(kNoJumpSigmas * sigma, kNoJumpFloor_nT));
  }
}

TEST_CASE("malformed frames are counted per reason and the daemon carries on",
          "[daemon][integration]") {
  TempDir tmp("malformed");
  const int64_t t0 = 1704067200000000;  // 2024-01-01T00:00:00Z
  const int64_t step = 10'000'000;
  auto sample = [&](int64_t seq, int64_t utime, const std::string& sat = "SAT-A") {
    magcal::mag_sample_t s{};
    s.utime = utime;
    s.sat_id = sat;
    s.seq = seq;
    s.b_sensor_nT[0] = 21000.0 + static_cast<double>(seq % 7) * 100.0;
    s.b_sensor_nT[1] = -15000.0 + static_cast<double>(seq % 5) * 200.0;
    s.b_sensor_nT[2] = 30000.0;
    s.has_reference = true;
    s.h_body_nT[0] = 20000.0;
    s.h_body_nT[1] = -15000.0;
    s.h_body_nT[2] = 31000.0;
    s.temperature_C = std::nanf("");
    return s;
  };
  const std::string log = tmp / "bad.lcm";
  {
    lcm::LogFile out(log, "w");
    REQUIRE(out.good());
    int64_t event = 0;
    auto write = [&](const std::string& channel, const std::vector<uint8_t>& bytes) {
      lcm::LogEvent e;
      e.eventnum = event++;
      e.timestamp = t0 + event;
      e.channel = channel;
      e.datalen = static_cast<int32_t>(bytes.size());
      e.data = const_cast<uint8_t*>(bytes.data());
      out.writeEvent(&e);
    };
    auto encode = [](const auto& msg) {
      std::vector<uint8_t> b(static_cast<size_t>(msg.getEncodedSize()));
      msg.encode(b.data(), 0, static_cast<int>(b.size()));
      return b;
    };
    for (int k = 0; k < 100; ++k) write("MAGCAL_SAMPLES", encode(sample(k, t0 + k * step)));
    const int64_t newest = t0 + 99 * step;
    magcal::calibration_t cal{};
    cal.sat_id = "SAT-A";
    write("MAGCAL_SAMPLES", encode(cal));          // wrong type
    write("MAGCAL_BATCH", encode(sample(0, t0)));  // wrong type (sample on batch)
    auto trunc = encode(sample(1, t0 + 1));
    trunc.resize(trunc.size() - 5);
    write("MAGCAL_SAMPLES", trunc);               // truncated
    write("MAGCAL_SAMPLES", {0x01, 0x02, 0x03});  // shorter than a fingerprint
    auto nan = sample(100, newest + step);
    nan.b_sensor_nT[1] = std::nan("");
    write("MAGCAL_SAMPLES", encode(nan));                         // non_finite
    write("MAGCAL_SAMPLES", encode(sample(50, t0 + 50 * step)));  // duplicate
    write("MAGCAL_SAMPLES", encode(sample(101, newest - 12LL * 3600 * 1000000 - step)));  // old
    auto absurd = sample(102, newest + 2 * step);
    absurd.has_position = true;
    absurd.r_ecef_m[0] = 1.0e6;
    write("MAGCAL_SAMPLES", encode(absurd));  // absurd_position
    auto loud = sample(103, newest + 3 * step);
    loud.b_sensor_nT[0] = 2.0e5;
    write("MAGCAL_SAMPLES", encode(loud));                                 // out_of_range
    write("MAGCAL_SAMPLES", encode(sample(5, t0 + 5 * step + step / 2)));  // out of order: stored
    magcal::mag_batch_t batch;
    batch.sat_id = "SAT-A";
    batch.samples = {sample(104, newest + 4 * step), sample(105, newest + 5 * step),
                     sample(106, newest + 6 * step, "SAT-B")};  // last one: mismatch
    batch.n = 3;
    write("MAGCAL_BATCH", encode(batch));
    write("MAGCAL_SAMPLES", encode(sample(0, t0, "SAT-X")));           // not on the whitelist
    write("MAGCAL_SAMPLES", encode(sample(110, newest + 10 * step)));  // seq 106..109 missing
    write("MAGCAL_SAMPLES", encode(sample(111, newest + 11 * step)));  // confirms that gap
  }
  const std::string out = tmp / "out.lcm";
  {
    std::ofstream cfg(tmp / "d.toml");
    cfg << "[lcm]\npublish_url = \"file://" << out << "?mode=w\"\n"
        << "[service]\nwhitelist = [\"SAT-A\", \"SAT-B\"]\n";
  }
  const int rc = run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
                      tmp / "m.db", "--lcm-url", "file://" + log + "?speed=0"},
                     tmp / "magcald.log");
  const std::string daemon_log = slurp(tmp / "magcald.log");
  INFO(daemon_log);
  REQUIRE(rc == 0);
  const auto st = read_published(out).statuses.back();
  CHECK(st.received == 116);
  CHECK(st.stored == 105);
  CHECK(st.rejected == 11);
  CHECK(rejected(st, "wrong_type") == 2);
  CHECK(rejected(st, "decode_error") == 2);
  CHECK(rejected(st, "non_finite") == 1);
  CHECK(rejected(st, "duplicate") == 1);
  CHECK(rejected(st, "older_than_window") == 1);
  CHECK(rejected(st, "absurd_position") == 1);
  CHECK(rejected(st, "out_of_range") == 1);
  CHECK(rejected(st, "batch_sat_mismatch") == 1);
  CHECK(rejected(st, "unknown_spacecraft") == 1);
  CHECK(st.missing_by_seq == 4);
  CHECK(stored_count(tmp / "m.db", "SAT-A") == 105);
  CHECK_THAT(daemon_log, Catch::Contains("rejected sample (non_finite)"));
}

namespace {
void write_sample_log(const std::string& path, const std::vector<magcal::mag_sample_t>& frames);
}  // namespace

TEST_CASE("bad config and unusable database: clear error, non-zero exit", "[daemon][integration]") {
  TempDir tmp("badcfg");
  {
    std::ofstream cfg(tmp / "bad.toml");
    cfg << "[refit]\nclock = \"sundial\"\n";
  }
  CHECK(run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "bad.toml"},
            tmp / "a.log") == 1);
  CHECK_THAT(slurp(tmp / "a.log"), Catch::Contains("[refit] clock"));
  {
    std::ofstream cfg(tmp / "unknown.toml");
    cfg << "[storage]\nwindow = 3\n";
  }
  CHECK(run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "unknown.toml"},
            tmp / "b.log") == 1);
  CHECK_THAT(slurp(tmp / "b.log"), Catch::Contains("unknown key [storage] window"));
  write_sample_log(tmp / "one.lcm",
                   {magcal::mag_sample_t{}});  // a log that opens: the database is what fails
  CHECK(run({kBin + "/magcald", "--http-listen", "", "--db", "/nonexistent-dir/x/m.db", "--lcm-url",
             "file://" + tmp / "one.lcm"},
            tmp / "c.log") == 2);
  CHECK_THAT(slurp(tmp / "c.log"), Catch::Contains("/nonexistent-dir/x/m.db"));
  // An LCM URL that cannot be opened is found before the database is created.
  CHECK(
      run({kBin + "/magcald", "--db", tmp / "never.db", "--lcm-url", "file://" + tmp / "none.lcm"},
          tmp / "c2.log") == 2);
  CHECK_THAT(slurp(tmp / "c2.log"), Catch::Contains("cannot open LCM URL"));
  CHECK_THAT(slurp(tmp / "c2.log"), Catch::Contains("none.lcm: No such file or directory"));
  CHECK_FALSE(fs::exists(tmp / "never.db"));
  // A log that exists but is not one (corrupt, or another file) says so, not "missing".
  {
    std::ofstream junk(tmp / "corrupt.lcm");
    for (int i = 0; i < 200; ++i) junk << "not an LCM event log, just text ";
  }
  CHECK(run({kBin + "/magcald", "--db", tmp / "never.db", "--lcm-url",
             "file://" + tmp / "corrupt.lcm"},
            tmp / "c3.log") == 2);
  INFO(slurp(tmp / "c3.log"));
  CHECK_THAT(slurp(tmp / "c3.log"), Catch::Contains("not an LCM log, or corrupt"));
  CHECK_THAT(slurp(tmp / "c3.log"), !Catch::Contains("No such file"));
  CHECK_FALSE(fs::exists(tmp / "never.db"));
  {
    std::ofstream junk(tmp / "junk.db");
    junk << "this is not a database, just text long enough to be a file header............\n";
  }
  CHECK(run({kBin + "/magcald", "--http-listen", "", "--db", tmp / "junk.db", "--lcm-url",
             "file://" + tmp / "none.lcm"},
            tmp / "d.log") == 2);
  CHECK(run({kBin + "/magcald", "--http-listen", "", "--log-level", "loud"}, tmp / "e.log") == 1);
}

namespace {

// A valid paper-like frame: 30 000 nT reference turning slowly, B = h + bias.
magcal::mag_sample_t rogue_test_sample(int64_t seq, int64_t utime) {
  magcal::mag_sample_t s{};
  s.utime = utime;
  s.sat_id = "SAT-T";
  s.seq = seq;
  const double a = 0.0021 * static_cast<double>(seq), c = 0.0013 * static_cast<double>(seq);
  const double h[3] = {30000.0 * std::cos(a) * std::cos(c), 30000.0 * std::sin(a) * std::cos(c),
                       30000.0 * std::sin(c)};
  const double bias[3] = {1000.0, -800.0, 900.0};
  for (int i = 0; i < 3; ++i) {
    s.h_body_nT[i] = h[i];
    s.b_sensor_nT[i] = h[i] + bias[i];
  }
  s.has_reference = true;
  s.temperature_C = std::nanf("");
  return s;
}

void write_sample_log(const std::string& path, const std::vector<magcal::mag_sample_t>& frames) {
  lcm::LogFile out(path, "w");
  REQUIRE(out.good());
  int64_t event = 0;
  for (const auto& s : frames) {
    std::vector<uint8_t> b(static_cast<size_t>(s.getEncodedSize()));
    s.encode(b.data(), 0, static_cast<int>(b.size()));
    lcm::LogEvent e;
    e.eventnum = event++;
    e.timestamp = 1704067200000000 + event;
    e.channel = "MAGCAL_SAMPLES";
    e.datalen = static_cast<int32_t>(b.size());
    e.data = b.data();
    out.writeEvent(&e);
  }
}

}  // namespace

TEST_CASE("one rogue time tag among 2000 frames: all 2000 kept, the rogue counted",
          "[daemon][integration][time]") {
  constexpr int kValid = 2000;
  const int64_t t0 = 1704067200000000;  // 2024-01-01T00:00:00Z
  const int64_t step = 10'000'000;
  const int64_t hour = 3600LL * 1000000;
  struct Case {
    const char* name;
    int64_t rogue_utime;  // 0 with gap_utime > 0: no rogue, a gap instead
    const char* reason;
    int64_t gap_utime;
  };
  const int64_t mid = t0 + (kValid / 2) * step;
  const Case cases[] = {
      {"20 h after the data", mid + 20 * hour, "time_jump", 0},
      {"20 h before the data", mid - 20 * hour, "older_than_window", 0},
      {"utime 0", 0, "time_out_of_range", 0},
      {"int64 min", std::numeric_limits<int64_t>::min(), "time_out_of_range", 0},
      {"int64 max", std::numeric_limits<int64_t>::max(), "time_out_of_range", 0},
      {"a genuine 3 h gap", 0, "", 3 * hour},
  };
  for (const auto& c : cases) {
    DYNAMIC_SECTION(c.name) {
      TempDir tmp("rogue");
      std::vector<magcal::mag_sample_t> frames;
      for (int k = 0; k < kValid; ++k) {
        frames.push_back(rogue_test_sample(k, t0 + k * step + (k >= kValid / 2 ? c.gap_utime : 0)));
        if (k == kValid / 2 && c.gap_utime == 0)
          frames.push_back(rogue_test_sample(k, c.rogue_utime));
      }
      // Then the recorder's dump of older in-window samples (between the stored ones).
      for (int k = kValid - 300; k < kValid; k += 3) {
        frames.push_back(
            rogue_test_sample(kValid + k, frames[static_cast<size_t>(k)].utime + step / 2));
      }
      const int dump = 100;
      write_sample_log(tmp / "in.lcm", frames);
      const std::string out = tmp / "out.lcm";
      {
        std::ofstream cfg(tmp / "d.toml");  // the embedded defaults, plus somewhere to publish
        cfg << "[lcm]\npublish_url = \"file://" << out << "?mode=w\"\n";
      }
      const int rc =
          run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
               tmp / "m.db", "--lcm-url", "file://" + (tmp / "in.lcm") + "?speed=0"},
              tmp / "magcald.log");
      INFO(slurp(tmp / "magcald.log"));
      REQUIRE(rc == 0);
      const auto st = read_published(out).statuses.back();
      const int64_t n_rogue = c.gap_utime == 0 ? 1 : 0;
      CHECK(st.received == kValid + dump + n_rogue);
      CHECK(st.stored == kValid + dump);
      CHECK(stored_count(tmp / "m.db", "SAT-T") == kValid + dump);
      CHECK(st.rejected == n_rogue);
      if (n_rogue) CHECK(rejected(st, c.reason) == 1);
      std::printf("rogue-frame replay (%s): received %lld, stored %lld, rejected %lld\n", c.name,
                  static_cast<long long>(st.received), static_cast<long long>(st.stored),
                  static_cast<long long>(st.rejected));
    }
  }
}

TEST_CASE("a replayed spacecraft that sent one frame, or too few to corroborate: all stored",
          "[daemon][integration][time]") {
  // SAT-T streams 200 frames; SAT-ONE sends one sample, SAT-FEW three single-sample frames
  // (corroboration needs four samples in more than one frame). At the end of the log nothing
  // contradicts them: stored, none counted as time_jump_unconfirmed.
  const int64_t t0 = 1704067200000000;  // 2024-01-01T00:00:00Z
  const int64_t step = 10'000'000;
  TempDir tmp("lonely");
  std::vector<magcal::mag_sample_t> frames;
  for (int k = 0; k < 200; ++k) {
    frames.push_back(rogue_test_sample(k, t0 + k * step));
    if (k == 50) {
      frames.push_back(rogue_test_sample(0, t0 + k * step));
      frames.back().sat_id = "SAT-ONE";
    }
    if (k == 60 || k == 61 || k == 62) {
      frames.push_back(rogue_test_sample(k - 60, t0 + k * step));
      frames.back().sat_id = "SAT-FEW";
    }
  }
  write_sample_log(tmp / "in.lcm", frames);
  const std::string out = tmp / "out.lcm";
  {
    std::ofstream cfg(tmp / "d.toml");
    cfg << "[lcm]\npublish_url = \"file://" << out << "?mode=w\"\n";
  }
  const int rc = run({kBin + "/magcald", "--http-listen", "", "--config", tmp / "d.toml", "--db",
                      tmp / "m.db", "--lcm-url", "file://" + (tmp / "in.lcm") + "?speed=0"},
                     tmp / "magcald.log");
  INFO(slurp(tmp / "magcald.log"));
  REQUIRE(rc == 0);
  const auto st = read_published(out).statuses.back();
  CHECK(st.received == 204);
  CHECK(st.stored == 204);
  CHECK(st.rejected == 0);
  CHECK(stored_count(tmp / "m.db", "SAT-ONE") == 1);
  CHECK(stored_count(tmp / "m.db", "SAT-FEW") == 3);
  CHECK(stored_count(tmp / "m.db", "SAT-T") == 200);
}
