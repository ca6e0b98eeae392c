#include <catch2/catch.hpp>

#include "tests/test_skip.hpp"

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <unistd.h>

#include <lcm/lcm-cpp.hpp>
#include <nlohmann/json.hpp>

#include "service/cli/cli_commands.hpp"
#include "service/io/sample_files.hpp"

using namespace magcal;
namespace fs = std::filesystem;

namespace {
fs::path temp_dir() {
  // One folder per process: CTest runs this file's cases side by side.
  const fs::path d =
      fs::temp_directory_path() / ("magcal_cli_sim_test_" + std::to_string(::getpid()));
  fs::create_directories(d);
  return d;
}
std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream os;
  os << in.rdbuf();
  return os.str();
}
int sim(const std::string& out, double hours, uint64_t seed, const std::string& truth = "",
        const std::string& scenario = "paper", int batch = 0) {
  cli::SimArgs a;
  a.scenario = scenario;
  a.hours = hours;
  a.seed = seed;
  a.out = out;
  a.truth = truth;
  a.batch_size = batch;
  return cli::run_sim(a);
}
bool leftovers(const fs::path& dir) {
  for (const auto& e : fs::directory_iterator(dir))
    if (e.path().string().find(".tmp.") != std::string::npos) return true;
  return false;
}
}  // namespace

TEST_CASE("magcal sim writes CSV and truth JSON, same seed gives the same bytes") {
  const fs::path d = temp_dir();
  const std::string a = (d / "a.csv").string(), b = (d / "b.csv").string(),
                    c = (d / "c.csv").string();
  const std::string truth = (d / "truth.json").string();
  REQUIRE(sim(a, 1.0, 3, truth) == cli::kExitOk);
  REQUIRE(sim(b, 1.0, 3) == cli::kExitOk);
  REQUIRE(sim(c, 1.0, 4) == cli::kExitOk);
  CHECK(slurp(a) == slurp(b));
  CHECK(slurp(a) != slurp(c));
  const CsvReadResult r = read_sample_csv(a);
  REQUIRE(r.ok());
  CHECK(r.rows.size() == 360);
  CHECK(r.rows[0].extras.q_body_from_eci.has_value());
  CHECK(r.rows[0].extras.r_ecef_m->norm() == Approx(6378137.0 + 550e3).epsilon(1e-3));

  const nlohmann::json j = nlohmann::json::parse(slurp(truth));
  for (const char* key :
       {"bias_nT", "D", "R_sensor_from_body", "alignment_deg", "installation_R",
        "internal_misalignment_mrad", "noise_sigma_nT", "nonlinearity_fraction_fs",
        "hysteresis_fraction_fs", "nbits", "full_scale_nT", "permeability",
        "temperature_coefficient_nT_per_C", "drift_nT_per_day", "seed", "sat_id"}) {
    INFO(key);
    CHECK(j.contains(key));
  }
  CHECK(j["bias_nT"][1].get<double>() == 800.0);
  CHECK(j["D"][1][1].get<double>() == 0.02);
  CHECK(j["seed"].get<uint64_t>() == 3);
  CHECK(j["alignment_deg"]["pitch"].get<double>() == Approx(2.0).margin(0.35));
  CHECK_FALSE(leftovers(d));
}

TEST_CASE("magcal sim writes an LCM log that lcm::LogFile reads back completely") {
  const fs::path d = temp_dir();
  const std::string log = (d / "s.lcm").string(), batched = (d / "b.lcm").string();
  REQUIRE(sim(log, 2.0, 1) == cli::kExitOk);
  REQUIRE(sim(batched, 2.0, 1, "", "tumbling", 100) == cli::kExitOk);
  const LcmReadResult r = read_sample_lcm_log(log);
  REQUIRE(r.ok());
  CHECK(r.samples.size() == 720);
  CHECK(r.undecodable == 0);
  CHECK(r.sat_ids == std::vector<std::string>{"PAPER-1"});
  CHECK(r.samples[1].utime - r.samples[0].utime == 10'000'000);
  const LcmReadResult rb = read_sample_lcm_log(batched);
  CHECK(rb.samples.size() == 720);
  CHECK(rb.events == 8);
  CHECK(rb.sat_ids == std::vector<std::string>{"TUMBLE-1"});
  // Same seed, same bytes for the log too.
  const std::string again = (d / "s2.lcm").string();
  REQUIRE(sim(again, 2.0, 1) == cli::kExitOk);
  CHECK(slurp(log) == slurp(again));
}

TEST_CASE("magcal sim errors: usage vs data, nothing half-written") {
  const fs::path d = temp_dir();
  CHECK(sim((d / "x.txt").string(), 1.0, 1) == cli::kExitUsage);
  CHECK(sim((d / "x.csv").string(), -1.0, 1) == cli::kExitUsage);
  CHECK(sim((d / "x.csv").string(), 1.0, 1, "", "nosuchpreset") == cli::kExitUsage);
  CHECK(sim((d / "x.csv").string(), 1.0, 1, "", (d / "missing.toml").string()) == cli::kExitData);
  CHECK(sim((d / "x.csv").string(), 1.0, 1, "", "paper", 10) == cli::kExitUsage);  // --batch on CSV
  CHECK(sim((d / "no_such_dir" / "x.csv").string(), 1.0, 1) == cli::kExitData);
  std::ofstream(d / "bad.toml") << "[sensor]\nnbits = 99\n";
  CHECK(sim((d / "x.csv").string(), 1.0, 1, "", (d / "bad.toml").string()) == cli::kExitData);
  CHECK_FALSE(fs::exists(d / "x.csv"));
  CHECK_FALSE(leftovers(d));
}

TEST_CASE("lcm-logplayer replays a simulated log (skipped without the tool)") {
  if (std::system("command -v lcm-logplayer > /dev/null 2>&1") != 0) {
    magcal::test::skip_or_fail("lcm-logplayer not installed");
    return;
  }
  const fs::path d = temp_dir();
  const std::string log = (d / "replay.lcm").string();
  REQUIRE(sim(log, 0.5, 1) == cli::kExitOk);
  // Replay over loopback multicast to a raw subscriber that decodes every frame itself.
  const std::string url =
      "udpm://239.255.76.67:7671?ttl=0&recv_buf_size=4194304";  // own port: no cross-talk
  lcm::LCM lcm(url);
  if (!lcm.good()) {
    magcal::test::skip_or_fail("no multicast route on this machine: lcm-logplayer replay");
    return;
  }
  struct Counter {
    int decoded = 0, bad = 0;
    // subscribeFunction, as the daemon does: LCM 1.3.1's untyped member-method subscription
    // hands its callback a bad context pointer (UBSan reports it).
    static void on(const lcm::ReceiveBuffer* rbuf, const std::string&, Counter* self) {
      mag_sample_t m;
      (m.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) > 0 ? self->decoded
                                                                      : self->bad) += 1;
    }
  } counter;
  lcm::Subscription* sub = lcm.subscribeFunction(kSamplesChannel, &Counter::on, &counter);
  sub->setQueueCapacity(0);  // unbounded: 180 small messages
  const std::string cmd =
      "timeout 60 lcm-logplayer -s 0 -l '" + url + "' '" + log + "' > /dev/null 2>&1 &";
  REQUIRE(std::system(cmd.c_str()) == 0);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (counter.decoded + counter.bad < 180 && std::chrono::steady_clock::now() < deadline)
    lcm.handleTimeout(100);
  CHECK(counter.decoded == 180);
  CHECK(counter.bad == 0);
}
