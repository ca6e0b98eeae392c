#include "service/io/sample_files.hpp"

#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <vector>

#include <lcm/lcm-cpp.hpp>

using namespace magcal;

namespace {
std::string temp_file(const std::string& name) {
  return (std::filesystem::temp_directory_path() / ("magcal_sample_files_test_" + name)).string();
}
void write_text(const std::string& path, const std::string& text) {
  std::ofstream(path) << text;
}

mag_sample_t make_sample(int64_t k, const std::string& sat) {
  mag_sample_t m{};
  m.utime = 1577836800LL * 1'000'000 + k * 10'000'000;
  m.sat_id = sat;
  m.seq = k;
  for (int i = 0; i < 3; ++i) {
    m.b_sensor_nT[i] = 1000.0 * (i + 1) + 0.1 * static_cast<double>(k);
    m.h_body_nT[i] = -500.0 * (i + 1) + 1.0 / 3.0;
    m.r_ecef_m[i] = 7e6 / (i + 1);
  }
  m.q_body_from_eci[0] = 1.0;
  m.has_position = m.has_attitude = m.has_reference = true;
  m.temperature_C = 20.5f;
  return m;
}

// An lcm-gen message's encoded bytes (fingerprint first).
template <typename Message>
std::vector<uint8_t> encoded(const Message& m) {
  std::vector<uint8_t> bytes(static_cast<size_t>(m.getEncodedSize()));
  m.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  return bytes;
}

// Writes `bytes` as one event on `channel`; 0 on success.
int write_event(lcm::LogFile& log, const std::string& channel, int64_t timestamp,
                std::vector<uint8_t>& bytes, int64_t eventnum = 0) {
  lcm::LogEvent ev{};
  ev.eventnum = eventnum;
  ev.channel = channel;
  ev.timestamp = timestamp;
  ev.datalen = static_cast<int32_t>(bytes.size());
  ev.data = bytes.data();
  return log.writeEvent(&ev);
}
}  // namespace

TEST_CASE("CSV round trip is exact, with extras") {
  const std::string path = temp_file("roundtrip.csv");
  SampleCsvWriter w;
  REQUIRE(w.open(path).empty());
  SampleSet written;
  for (int k = 0; k < 50; ++k) {
    CalibrationSample s;
    s.utime = 1577836800LL * 1'000'000 + k * 10'000'000 + 123;
    s.b_sensor_nT = Eigen::Vector3d(1.0 / 3.0 + k, -2.0 / 7.0, 1e5 - 0.1);
    s.h_body_nT = Eigen::Vector3d(M_PI * 1e4, -M_E * 1e4, 1e-300);
    CsvSampleExtras e;
    if (k % 2 == 0) {
      e.q_body_from_eci = Eigen::Vector4d(0.5, 0.5, -0.5, 0.5);
      e.r_ecef_m = Eigen::Vector3d(7e6, -1.5, 3.25);
      e.temperature_C = 21.125;
    }
    w.write(s, e);
    written.push_back(s);
  }
  REQUIRE(w.close().empty());
  const CsvReadResult r = read_sample_csv(path);
  REQUIRE(r.ok());
  REQUIRE(r.rows.size() == written.size());
  for (size_t k = 0; k < written.size(); ++k) {
    CHECK(r.rows[k].sample.utime == written[k].utime);
    CHECK(r.rows[k].sample.b_sensor_nT == written[k].b_sensor_nT);
    CHECK(r.rows[k].sample.h_body_nT == written[k].h_body_nT);
    CHECK(r.rows[k].extras.q_body_from_eci.has_value() == (k % 2 == 0));
    if (k % 2 == 0) CHECK(*r.rows[k].extras.temperature_C == 21.125);
  }
  std::filesystem::remove(path);
}

TEST_CASE("CSV reader: columns by name, extra columns ignored, blank lines skipped") {
  const std::string path = temp_file("reordered.csv");
  write_text(path,
             "hz_nT,note,t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT\n"
             "3,foo,1577836800.5,10,20,30,1,2\n"
             "\n"
             "6,bar,1577836810,40,50,60,4,5\r\n");
  const CsvReadResult r = read_sample_csv(path);
  REQUIRE(r.ok());
  REQUIRE(r.rows.size() == 2);
  CHECK(r.rows[0].sample.utime == 1577836800500000LL);
  CHECK(r.rows[0].sample.b_sensor_nT == Eigen::Vector3d(10, 20, 30));
  CHECK(r.rows[1].sample.h_body_nT == Eigen::Vector3d(4, 5, 6));
  CHECK_FALSE(r.rows[0].extras.q_body_from_eci.has_value());
  std::filesystem::remove(path);
}

TEST_CASE("CSV reader errors name the file, line and column") {
  const std::string path = temp_file("bad.csv");
  write_text(path, "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT\n1,2,3,4,5,6\n");
  CsvReadResult r = read_sample_csv(path);
  CHECK(r.error.find("hz_nT") != std::string::npos);
  CHECK(r.rows.empty());

  write_text(path, "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n1,2,3,4,5,6,7\n1,2,x,4,5,6,7\n");
  r = read_sample_csv(path);
  CHECK(r.error.find("line 3") != std::string::npos);
  CHECK(r.error.find("by_nT") != std::string::npos);
  CHECK(r.rows.empty());

  // A missing reading (empty or not finite) drops its row, counted; text is an error.
  write_text(path,
             "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n1,2,3,nan,5,6,7\n2,2,3,4,,6,7\n"
             "3,2,3,4,5,6,7\n4,inf,3,4,5,6,7\n");
  r = read_sample_csv(path);
  REQUIRE(r.ok());
  CHECK(r.rows.size() == 1);
  CHECK(r.missing_dropped == 3);
  write_text(path, "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n1,2,3,n/a,5,6,7\n");
  CHECK(read_sample_csv(path).error.find("bz_nT") != std::string::npos);
  write_text(path, "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n1,2,3\n");
  CHECK(read_sample_csv(path).error.find("line 2") != std::string::npos);
  write_text(path, "");
  CHECK(!read_sample_csv(path).ok());
  std::filesystem::remove(path);
  CHECK(read_sample_csv(path).error.find("cannot open") != std::string::npos);
}

TEST_CASE(
    "CSV reader: a field beyond any magnetometer's range is an error naming line and column") {
  const std::string path = temp_file("range.csv");
  const std::string header = "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT\n";
  // At the limit: read.
  write_text(path, header + "1,1e7,-1e7,3,4,5,6\n2,1,2,3,1e7,5,-1e7\n");
  CsvReadResult r = read_sample_csv(path);
  REQUIRE(r.ok());
  CHECK(r.rows.size() == 2);
  // Beyond it, in any of the six field columns: the line and the column are named.
  const char* columns[] = {"bx_nT", "by_nT", "bz_nT", "hx_nT", "hy_nT", "hz_nT"};
  for (int c = 0; c < 6; ++c) {
    std::string row = "3";
    for (int i = 0; i < 6; ++i) row += i == c ? (c % 2 ? ",-1e300" : ",1.0000001e7") : ",5";
    write_text(path, header + "1,1,2,3,4,5,6\n\n" + row + "\n2,1,2,3,4,5,6\n");
    r = read_sample_csv(path);
    INFO(r.error);
    CHECK(r.error.find("line 4") != std::string::npos);
    CHECK(r.error.find(std::string("column ") + columns[c]) != std::string::npos);
    CHECK(r.error.find("range") != std::string::npos);
    CHECK(r.rows.empty());
  }
  std::filesystem::remove(path);
}

TEST_CASE(
    "CSV reader: an exact repeat of a row is dropped and counted, a conflicting one is an error") {
  const std::string path = temp_file("dup.csv");
  const std::string header =
      "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT,qw,qx,qy,qz,r_ecef_x_m,r_ecef_y_m,r_ecef_z_m,"
      "temperature_C\n";
  std::string body;
  for (int k = 0; k < 5; ++k) {
    body += std::to_string(1577836800 + 10 * k) + "," + std::to_string(1000 + k) +
            ",2,3,4,5,6,1,0,0,0,7e6,0,0,20\n";
  }
  write_text(path, header + body + body);
  CsvReadResult r = read_sample_csv(path);
  REQUIRE(r.ok());
  CHECK(r.rows.size() == 5);
  CHECK(r.duplicates_dropped == 5);
  for (int k = 0; k < 5; ++k)
    CHECK(r.rows[static_cast<size_t>(k)].sample.b_sensor_nT.x() == 1000 + k);

  // Same time tag, another value (here only the temperature extra): which row is the
  // measurement is unknowable, so the file is refused, naming both lines.
  write_text(path, header + body + "1577836820,1002,2,3,4,5,6,1,0,0,0,7e6,0,0,21\n");
  r = read_sample_csv(path);
  INFO(r.error);
  CHECK(r.error.find("line 7") != std::string::npos);
  CHECK(r.error.find("line 4") != std::string::npos);
  CHECK(r.rows.empty());
  CHECK(r.duplicates_dropped == 0);
  // A distinct time tag below the reader's microsecond resolution is the same time tag.
  write_text(path, header + body + "1577836820.0000001,1002,2,3,4,5,6,1,0,0,0,7e6,0,0,20\n");
  r = read_sample_csv(path);
  REQUIRE(r.ok());
  CHECK(r.duplicates_dropped == 1);
  std::filesystem::remove(path);
}

TEST_CASE("LCM log: samples and batches read back, every event decodes with lcm::LogFile") {
  const std::string path = temp_file("log.lcm");
  for (int batch : {0, 7}) {
    SampleLcmLogWriter w;
    REQUIRE(w.open(path, batch).empty());
    for (int k = 0; k < 30; ++k) REQUIRE(w.write(make_sample(k, k < 20 ? "A" : "B")).empty());
    REQUIRE(w.close().empty());

    // Raw pass: channel, timestamp = (first) sample utime, decodes fully.
    lcm::LogFile log(path, "r");
    REQUIRE(log.good());
    int events = 0;
    while (const lcm::LogEvent* ev = log.readNextEvent()) {
      ++events;
      if (batch == 0) {
        CHECK(ev->channel == kSamplesChannel);
        mag_sample_t m;
        CHECK(m.decode(ev->data, 0, ev->datalen) == ev->datalen);
        CHECK(ev->timestamp == m.utime);
      } else {
        CHECK(ev->channel == kBatchChannel);
        mag_batch_t b;
        CHECK(b.decode(ev->data, 0, ev->datalen) == ev->datalen);
        CHECK(b.n == static_cast<int>(b.samples.size()));
        CHECK(ev->timestamp == b.samples.front().utime);
      }
    }
    // 20 A + 10 B in batches of 7, split at the sat change: 3 + 2 + ... = ceil(20/7) + ceil(10/7)
    CHECK(events == (batch == 0 ? 30 : 5));

    LcmReadResult r = read_sample_lcm_log(path);
    REQUIRE(r.ok());
    CHECK(r.samples.size() == 30);
    CHECK(r.undecodable == 0);
    CHECK(r.sat_ids == std::vector<std::string>{"A", "B"});
    CHECK(r.samples[5].b_sensor_nT[2] == make_sample(5, "A").b_sensor_nT[2]);
    CHECK(r.samples[29].seq == 29);
    LcmReadOptions only_b;
    only_b.sat_id = "B";
    CHECK(read_sample_lcm_log(path, only_b).samples.size() == 10);
  }
  const CalibrationSample c = to_calibration_sample(make_sample(3, "A"));
  CHECK(c.has_reference_direction);
  CHECK(c.h_body_nT.x() == make_sample(3, "A").h_body_nT[0]);
  mag_sample_t no_ref = make_sample(3, "A");
  no_ref.has_reference = false;
  CHECK_FALSE(to_calibration_sample(no_ref).has_reference_direction);
  std::filesystem::remove(path);
}

TEST_CASE("LCM log reader counts undecodable events and survives a truncated file") {
  const std::string path = temp_file("corrupt.lcm");
  {
    lcm::LogFile log(path, "w");
    REQUIRE(log.good());
    const mag_sample_t m = make_sample(1, "A");
    std::vector<uint8_t> buf = encoded(m);
    write_event(log, kSamplesChannel, m.utime, buf);
    buf[3] ^= 0xFF;  // corrupt the fingerprint
    write_event(log, kSamplesChannel, m.utime, buf);
    write_event(log, "OTHER", m.utime, buf);  // ignored channel
  }
  LcmReadResult r = read_sample_lcm_log(path);
  REQUIRE(r.ok());
  CHECK(r.samples.size() == 1);
  CHECK(r.undecodable == 1);
  CHECK(r.events == 2);
  // Truncate in the middle of the last event: still no crash, earlier events kept.
  std::filesystem::resize_file(path, std::filesystem::file_size(path) - 10);
  r = read_sample_lcm_log(path);
  CHECK(r.samples.size() == 1);
  std::filesystem::remove(path);
  CHECK(!read_sample_lcm_log(path).ok());
}

TEST_CASE("LCM log reader: frames whose lengths lie are counted, never decoded (no throw)") {
  // Zeroed bytes inside a log give a string length of 0, on which lcm-gen's decoder throws
  // std::length_error: the layout is walked before decoding, by `magcal fit` as by magcald.
  const std::string path = temp_file("lying_lengths.lcm");
  {
    lcm::LogFile log(path, "w");
    REQUIRE(log.good());
    const mag_sample_t m = make_sample(1, "A");
    std::vector<uint8_t> buf = encoded(m);
    write_event(log, kSamplesChannel, m.utime, buf);
    std::vector<uint8_t> zero_len = buf;  // sat_id length (after fingerprint and utime) = 0
    std::fill(zero_len.begin() + 16, zero_len.begin() + 20, 0);
    write_event(log, kSamplesChannel, m.utime, zero_len);
    mag_batch_t batch;
    batch.sat_id = "A";
    batch.n = 1;
    batch.samples = {make_sample(2, "A")};
    std::vector<uint8_t> bbuf = encoded(batch);
    const std::size_t n_at = 8 + 4 + batch.sat_id.size() + 1;  // after fingerprint and sat_id
    std::fill(bbuf.begin() + static_cast<std::ptrdiff_t>(n_at),
              bbuf.begin() + static_cast<std::ptrdiff_t>(n_at) + 4, 0x7F);  // n = 2^31 - 1
    write_event(log, kBatchChannel, m.utime, bbuf);
  }
  const LcmReadResult r = read_sample_lcm_log(path);
  REQUIRE(r.ok());
  CHECK(r.samples.size() == 1);
  CHECK(r.undecodable == 2);
  CHECK(r.events == 3);
  std::filesystem::remove(path);
}

TEST_CASE("LCM log reader: not an LCM log, or a log without our samples, is an error saying so") {
  const std::string path = temp_file("garbage.lcm");
  {
    std::ofstream f(path, std::ios::binary);
    for (int i = 0; i < 5000; ++i) f.put(static_cast<char>((i * 7919) % 251));
  }
  LcmReadResult r = read_sample_lcm_log(path);
  INFO(r.error);
  CHECK(r.error.find("not an LCM log") != std::string::npos);
  CHECK(r.error.find(path) != std::string::npos);
  // The same words as magcald's replay start error (one helper).
  CHECK(r.error == unreadable_lcm_log_reason(path));

  write_text(path, "");
  CHECK(read_sample_lcm_log(path).error.find("empty file") != std::string::npos);

  // A valid log, but only another channel: says which channels it holds.
  std::filesystem::remove(path);
  const mag_sample_t m = make_sample(1, "A");
  std::vector<uint8_t> buf = encoded(m);
  auto write_log = [&](const char* channel, int count) {
    lcm::LogFile log(path, "w");
    REQUIRE(log.good());
    for (int i = 0; i < count; ++i) REQUIRE(write_event(log, channel, m.utime, buf, i) == 0);
  };
  write_log("POSE", 3);
  CHECK(unreadable_lcm_log_reason(path).empty());
  r = read_sample_lcm_log(path);
  INFO(r.error);
  CHECK(r.error.find("without events on MAGCAL_SAMPLES or MAGCAL_BATCH") != std::string::npos);
  CHECK(r.error.find("POSE") != std::string::npos);
  CHECK(r.samples.empty());

  // Our channel, but another message type in it (mag_sample_t on the batch channel).
  write_log(kBatchChannel, 2);
  r = read_sample_lcm_log(path);
  CHECK(r.error.find("none of its 2 events") != std::string::npos);
  CHECK(r.samples.empty());
  std::filesystem::remove(path);
}

TEST_CASE(
    "LCM log reader: an exact repeat of a sample is dropped and counted, a conflict is an error") {
  const std::string path = temp_file("dup.lcm");
  auto write = [&](const std::vector<mag_sample_t>& samples, int batch) {
    SampleLcmLogWriter w;
    REQUIRE(w.open(path, batch).empty());
    for (const mag_sample_t& m : samples) REQUIRE(w.write(m).empty());
    REQUIRE(w.close().empty());
  };
  std::vector<mag_sample_t> twice;
  for (int pass = 0; pass < 2; ++pass) {
    for (int k = 0; k < 10; ++k) {
      twice.push_back(make_sample(k, "A"));
      twice.back().seq = k + 100 * pass;     // a re-sent frame may be renumbered
      twice.push_back(make_sample(k, "B"));  // another spacecraft at the same utime: kept
    }
  }
  for (int batch : {0, 4}) {
    write(twice, batch);
    LcmReadResult r = read_sample_lcm_log(path);
    INFO(r.error);
    REQUIRE(r.ok());
    CHECK(r.samples.size() == 20);
    CHECK(r.duplicates_dropped == 20);
    LcmReadOptions only_a;
    only_a.sat_id = "A";
    r = read_sample_lcm_log(path, only_a);
    CHECK(r.samples.size() == 10);
    CHECK(r.duplicates_dropped == 10);
  }
  std::vector<mag_sample_t> conflicting = {make_sample(0, "A"), make_sample(1, "A"),
                                           make_sample(1, "A")};
  conflicting[2].h_body_nT[1] += 1.0;
  conflicting[2].seq = 7;
  write(conflicting, 0);
  const LcmReadResult r = read_sample_lcm_log(path);
  INFO(r.error);
  CHECK(r.error.find("samples 1 (seq 1) and 2 (seq 7) of spacecraft 'A'") != std::string::npos);
  CHECK(r.samples.empty());
  std::filesystem::remove(path);
}

TEST_CASE(
    "CSV reader: temperature_C empty or NaN is unknown, text or an absurd value is an error") {
  const std::string path = temp_file("temperature.csv");
  const std::string header = "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT,temperature_C\n";
  write_text(path, header +
                       "1,2,3,4,5,6,7,21.5\n2,2,3,4,5,6,7,\n3,2,3,4,5,6,7,NaN\n"
                       "4,2,3,4,5,6,7,nan\n5,2,3,4,5,6,7\n6,2,3,4,5,6,7,-150\n");
  CsvReadResult r = read_sample_csv(path);
  REQUIRE(r.ok());
  REQUIRE(r.rows.size() == 6);
  CHECK(r.rows[0].sample.temperature_C == 21.5);
  for (size_t i = 1; i < 5; ++i) CHECK(std::isnan(r.rows[i].sample.temperature_C));
  CHECK(r.rows[5].sample.temperature_C == -150.0);  // the plausible range is inclusive

  // Text where a number belongs: an error, as for the field columns (it used to be "unknown").
  write_text(path, header + "1,2,3,4,5,6,7,21.5\n2,2,3,4,5,6,7,hot\n");
  r = read_sample_csv(path);
  CHECK(r.rows.empty());
  CHECK(r.error.find("line 3") != std::string::npos);
  CHECK(r.error.find("column temperature_C: not a number") != std::string::npos);
  // A telemetry fault, not a temperature: one such row moved a thermal fit's bias by 7 sigma.
  for (const std::string bad : {"-300", "1e6", "200.5", "inf"}) {
    INFO(bad);
    write_text(path, header + "1,2,3,4,5,6,7,21.5\n2,2,3,4,5,6,7," + bad + "\n");
    r = read_sample_csv(path);
    CHECK(r.rows.empty());
    CHECK(r.error.find("line 3: column temperature_C") != std::string::npos);
  }
  std::filesystem::remove(path);
}

TEST_CASE("plausible_temperature_C: a reading within [-150, 200] degC, else unknown") {
  CHECK(plausible_temperature_C(20.0) == 20.0);
  CHECK(plausible_temperature_C(kMinPlausibleTemperature_C) == kMinPlausibleTemperature_C);
  CHECK(plausible_temperature_C(kMaxPlausibleTemperature_C) == kMaxPlausibleTemperature_C);
  CHECK(std::isnan(plausible_temperature_C(-300.0)));
  CHECK(std::isnan(plausible_temperature_C(1e6)));
  CHECK(std::isnan(plausible_temperature_C(std::numeric_limits<double>::quiet_NaN())));
  CHECK(std::isnan(plausible_temperature_C(std::numeric_limits<double>::infinity())));
  mag_sample_t m = make_sample(1, "SAT");
  m.temperature_C = -300.0f;
  CHECK(std::isnan(to_calibration_sample(m).temperature_C));  // `fit` on an LCM log, as magcald
  m.temperature_C = 20.5f;
  CHECK(to_calibration_sample(m).temperature_C == 20.5);
}
