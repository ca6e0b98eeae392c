// SampleSpill: samples round-trip through the file bit for bit, in order and in chunks; the
// committed offset survives a reopen; a torn or corrupt last record is cut off and counted,
// never a crash; the size bound refuses a batch whole; one process at a time holds the file.
#include "service/daemon/intake/sample_spill.hpp"

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <optional>
#include <string>

#include <catch2/catch.hpp>

#include "service/io/fnv1a.hpp"
#include "tests/service/cli_test_support.hpp"

using magcal::SampleSpill;
using magcal::SpillError;
using magcal::storage::StoredSample;
using magcal::test::TempDir;

namespace {

// Samples with every field set from i, both kinds of reference and a NaN temperature.
std::vector<StoredSample> samples(int first, int n) {
  std::vector<StoredSample> out;
  for (int i = first; i < first + n; ++i) {
    StoredSample s;
    s.sat_id = i % 2 == 0 ? "SAT-A" : "SAT-LONGER-NAME-" + std::to_string(i % 7);
    s.utime = 1'700'000'000'000'000 + int64_t{i} * 10'000'000;
    s.seq = i;
    s.receive_utime = s.utime + 1234;
    s.b_sensor_nT = {i * 1.5, -i * 0.25, 1e-300 * i};
    s.has_direction = i % 3 != 0;
    s.h_body_nT = {i + 0.1, i + 0.2, i + 0.3};
    s.h_norm_nT = 45000.0 + i;
    s.has_attitude = i % 2 == 0;
    s.q_body_from_eci = {0.5, 0.5, -0.5, 0.5};
    s.has_position = i % 5 != 0;
    s.r_ecef_m = {7e6, -i * 1.0, 3.3};
    s.temperature_C = i % 4 == 0 ? std::numeric_limits<double>::quiet_NaN() : 20.0 + i;
    out.push_back(s);
  }
  return out;
}

void check_equal(const StoredSample& a, const StoredSample& b) {
  CHECK(a.sat_id == b.sat_id);
  CHECK(a.utime == b.utime);
  CHECK(a.seq == b.seq);
  CHECK(a.receive_utime == b.receive_utime);
  CHECK(a.b_sensor_nT == b.b_sensor_nT);
  CHECK(a.has_direction == b.has_direction);
  CHECK(a.h_body_nT == b.h_body_nT);
  CHECK(a.h_norm_nT == b.h_norm_nT);
  CHECK(a.has_attitude == b.has_attitude);
  CHECK(a.q_body_from_eci == b.q_body_from_eci);
  CHECK(a.has_position == b.has_position);
  CHECK(a.r_ecef_m == b.r_ecef_m);
  CHECK(std::isnan(a.temperature_C) == std::isnan(b.temperature_C));
  if (!std::isnan(a.temperature_C)) CHECK(a.temperature_C == b.temperature_C);
}

// Every held record, chunk by chunk, each committed.
std::vector<StoredSample> drain(SampleSpill& spill, size_t chunk) {
  std::vector<StoredSample> all, part;
  while (spill.read_chunk(chunk, part) > 0) {
    all.insert(all.end(), part.begin(), part.end());
    spill.commit_read();
  }
  return all;
}

// A spill file as the first format lays it out, byte by byte, written here without SampleSpill:
// "MGSPILL1", the committed offset, the database's name; then per sample u32 length, u64
// FNV-1a, payload (sat_id length and bytes, utime, seq, receive_utime, b, a flags byte
// direction 1 | attitude 2 | position 4, h, |h|, q, r, temperature; native byte order).
std::string first_format_file(const std::string& database, const std::vector<StoredSample>& rows) {
  auto put = [](std::string& out, const auto& v) {
    out.append(reinterpret_cast<const char*>(&v), sizeof v);
  };
  std::string file = "MGSPILL1";
  put(file, static_cast<uint64_t>(8 + 8 + 4 + database.size()));
  put(file, static_cast<uint32_t>(database.size()));
  file += database;
  for (const StoredSample& s : rows) {
    std::string payload;
    put(payload, static_cast<uint32_t>(s.sat_id.size()));
    payload += s.sat_id;
    put(payload, s.utime);
    put(payload, s.seq);
    put(payload, s.receive_utime);
    for (const double v : s.b_sensor_nT) put(payload, v);
    put(payload, static_cast<uint8_t>((s.has_direction ? 1 : 0) | (s.has_attitude ? 2 : 0) |
                                      (s.has_position ? 4 : 0)));
    for (const double v : s.h_body_nT) put(payload, v);
    put(payload, s.h_norm_nT);
    for (const double v : s.q_body_from_eci) put(payload, v);
    for (const double v : s.r_ecef_m) put(payload, v);
    put(payload, s.temperature_C);
    put(file, static_cast<uint32_t>(payload.size()));
    put(file, magcal::fnv1a_64(payload));
    file += payload;
  }
  return file;
}

std::string file_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

}  // namespace

TEST_CASE("spilled samples come back in order, in chunks, and the file goes", "[sample_spill]") {
  TempDir dir("spill");
  const std::string path = dir.file("spill.bin");
  std::optional<SampleSpill> spill_holder(std::in_place, path, "postgresql://magcal@db/fleet",
                                          1 << 20);
  SampleSpill& spill = *spill_holder;
  // Created at once (a directory that cannot take it shows at start), holding nothing.
  REQUIRE(std::filesystem::exists(path));
  const auto header = static_cast<int64_t>(std::filesystem::file_size(path));
  CHECK(spill.bytes() == 0);
  CHECK(spill.held_samples() == 0);
  const auto a = samples(0, 100), b = samples(100, 57);
  REQUIRE(spill.append(a));
  REQUIRE(spill.append(b));
  CHECK(spill.held_samples() == 157);
  CHECK(spill.bytes() + header == static_cast<int64_t>(std::filesystem::file_size(path)));
  // A read that is not committed is read again.
  std::vector<StoredSample> part;
  REQUIRE(spill.read_chunk(10, part) == 10);
  REQUIRE(spill.read_chunk(10, part) == 10);
  CHECK(part[0].seq == 0);
  const auto back = drain(spill, 40);
  REQUIRE(back.size() == 157);
  for (size_t i = 0; i < back.size(); ++i) check_equal(back[i], i < 100 ? a[i] : b[i - 100]);
  CHECK(spill.held_samples() == 0);
  CHECK(spill.bytes() == 0);
  // Cut back to its header, still open: it takes the next outage's samples.
  CHECK(std::filesystem::file_size(path) == static_cast<uintmax_t>(header));
  REQUIRE(spill.append(samples(7, 3)));
  CHECK(drain(spill, 100).size() == 3);
  // Holding nothing, it goes with its holder.
  spill_holder.reset();
  CHECK_FALSE(std::filesystem::exists(path));
}

TEST_CASE("the file keeps its first format byte for byte, both ways", "[sample_spill]") {
  TempDir dir("spill");
  const auto rows = samples(0, 12);
  const std::string expected = first_format_file("db-one", rows);
  SECTION("an append writes exactly the first format's bytes") {
    const std::string path = dir.file("new.bin");
    SampleSpill spill(path, "db-one", 1 << 20);
    REQUIRE(spill.append(rows));
    CHECK(file_bytes(path) == expected);
  }
  SECTION("a file in the first format, written by an earlier build, reads back") {
    const std::string path = dir.file("old.bin");
    std::ofstream(path, std::ios::binary) << expected;
    SampleSpill spill(path, "db-two", 1 << 20);
    CHECK(spill.found_database() == "db-one");
    CHECK(spill.dropped_records() == 0);
    CHECK(spill.held_samples() == 12);
    const auto back = drain(spill, 5);
    REQUIRE(back.size() == rows.size());
    for (size_t i = 0; i < back.size(); ++i) check_equal(back[i], rows[i]);
  }
}

TEST_CASE("a spill file that cannot be created is an error naming its path and errno",
          "[sample_spill]") {
  TempDir dir("spill");
  // A regular file where the directory should be (as root too, unlike a permission).
  const std::string not_a_dir = dir.file("plain");
  std::ofstream(not_a_dir) << "x";
  const std::string path = not_a_dir + "/spill.bin";
  CHECK_THROWS_WITH(SampleSpill(path, "db", 1 << 20),
                    Catch::Contains(path) && Catch::Contains("cannot create") &&
                        Catch::Contains("Not a directory (ENOTDIR)"));
}

TEST_CASE("a reopened spill file holds what was not committed", "[sample_spill]") {
  TempDir dir("spill");
  const std::string path = dir.file("spill.bin");
  const auto rows = samples(0, 30);
  {
    SampleSpill spill(path, "db-one", 1 << 20);
    REQUIRE(spill.append(rows));
    std::vector<StoredSample> part;
    REQUIRE(spill.read_chunk(12, part) == 12);
    spill.commit_read();
  }  // a daemon stopped (or killed) during the outage
  SampleSpill again(path, "db-two", 1 << 20);
  CHECK(again.found_database() == "db-one");
  CHECK(again.held_samples() == 18);
  CHECK(again.dropped_records() == 0);
  const auto back = drain(again, 100);
  REQUIRE(back.size() == 18);
  for (size_t i = 0; i < back.size(); ++i) check_equal(back[i], rows[12 + i]);
}

TEST_CASE("a torn or corrupt last record is dropped and counted, the rest kept", "[sample_spill]") {
  TempDir dir("spill");
  const std::string path = dir.file("spill.bin");
  const auto rows = samples(0, 20);
  const auto size_with = [&](int n) {
    SampleSpill spill(dir.file("measure.bin"), "db", 1 << 20);
    REQUIRE(spill.append(std::span(rows).first(static_cast<size_t>(n))));
    const int64_t bytes = spill.bytes();
    drain(spill, 100);
    return bytes;
  };
  const int64_t nineteen = size_with(19), twenty = size_with(20);
  // (Its header: the file holding nothing.)
  const auto header = static_cast<int64_t>([&] {
    const SampleSpill empty(dir.file("header.bin"), "db", 1 << 20);
    return std::filesystem::file_size(dir.file("header.bin"));
  }());
  SECTION("torn: the last record cut short (a crash during its write)") {
    {
      SampleSpill spill(path, "db", 1 << 20);
      REQUIRE(spill.append(rows));
    }
    std::filesystem::resize_file(path, static_cast<uintmax_t>(header + twenty - 5));
  }
  SECTION("corrupt: one byte of the last record's payload changed") {
    {
      SampleSpill spill(path, "db", 1 << 20);
      REQUIRE(spill.append(rows));
    }
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(header + twenty - 3);
    f.put('\x5a');
  }
  SECTION("garbage after the last record") {
    {
      SampleSpill spill(path, "db", 1 << 20);
      REQUIRE(spill.append(std::span(rows).first(19)));
    }
    std::ofstream(path, std::ios::app | std::ios::binary) << std::string(7, '\xff');
  }
  SampleSpill spill(path, "db", 1 << 20);
  CHECK(spill.dropped_records() == 1);
  CHECK(spill.held_samples() == 19);
  CHECK(spill.bytes() == nineteen);
  CHECK(std::filesystem::file_size(path) == static_cast<uintmax_t>(header + nineteen));
  // Appends go on after the last good record.
  REQUIRE(spill.append(std::span(rows).subspan(19)));
  const auto back = drain(spill, 7);
  REQUIRE(back.size() == 20);
  for (size_t i = 0; i < back.size(); ++i) check_equal(back[i], rows[i]);
}

TEST_CASE("a batch that would pass max_bytes is refused whole", "[sample_spill]") {
  TempDir dir("spill");
  const auto rows = samples(0, 10);
  int64_t ten = 0;
  {
    SampleSpill measure(dir.file("m.bin"), "db", 1 << 20);
    REQUIRE(measure.append(rows));
    ten = measure.bytes();
    drain(measure, 100);
  }
  SampleSpill spill(dir.file("spill.bin"), "db", 2 * ten);
  REQUIRE(spill.append(rows));
  CHECK_FALSE(spill.append(samples(10, 15)));
  CHECK(spill.held_samples() == 10);
  CHECK(spill.bytes() == ten);
  REQUIRE(spill.append(samples(10, 5)));
  CHECK(drain(spill, 100).size() == 15);
}

TEST_CASE("one holder at a time, a foreign file is refused with its path", "[sample_spill]") {
  TempDir dir("spill");
  const std::string path = dir.file("spill.bin");
  SampleSpill first(path, "db", 1 << 20);
  REQUIRE(first.append(samples(0, 3)));
  try {
    SampleSpill second(path, "db", 1 << 20);
    FAIL("a second holder opened the file");
  } catch (const SpillError& e) {
    CHECK(std::string(e.what()).find(path) != std::string::npos);
    CHECK(std::string(e.what()).find("locked") != std::string::npos);
  }
  std::ofstream(dir.file("foreign.bin")) << "not a spill file at all";
  CHECK_THROWS_WITH(SampleSpill(dir.file("foreign.bin"), "db", 1 << 20),
                    Catch::Contains("not a magcal spill file"));
}
