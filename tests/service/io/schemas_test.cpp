// The LCM message definitions: every type encodes and decodes losslessly, and the fingerprints
// (which other tools depend on) stay what these definitions produce.
#include <catch2/catch.hpp>

#include <cmath>
#include <vector>

#include "schemas/magcal_messages.hpp"

namespace {

template <typename T>
T round_trip(const T& in) {
  std::vector<uint8_t> buf(static_cast<size_t>(in.getEncodedSize()));
  REQUIRE(in.encode(buf.data(), 0, static_cast<int>(buf.size())) == static_cast<int>(buf.size()));
  T out;
  REQUIRE(out.decode(buf.data(), 0, static_cast<int>(buf.size())) == static_cast<int>(buf.size()));
  return out;
}

magcal::mag_sample_t make_sample(int64_t seq) {
  magcal::mag_sample_t s{};
  s.utime = 1577836800000000 + seq * 10000000;
  s.sat_id = "SAT-1";
  s.seq = seq;
  s.b_sensor_nT[0] = 1234.5;
  s.b_sensor_nT[1] = -20000.25;
  s.b_sensor_nT[2] = 35000.0;
  s.has_position = true;
  s.r_ecef_m[0] = 6921000.0;
  s.has_attitude = true;
  s.q_body_from_eci[0] = 1.0;
  s.has_reference = false;
  s.temperature_C = std::nanf("");
  return s;
}

}  // namespace

TEST_CASE("mag_sample_t round-trips every field", "[schemas]") {
  const auto in = make_sample(7);
  const auto out = round_trip(in);
  CHECK(out.utime == in.utime);
  CHECK(out.sat_id == in.sat_id);
  CHECK(out.seq == 7);
  CHECK(out.b_sensor_nT[1] == in.b_sensor_nT[1]);
  CHECK(out.r_ecef_m[0] == in.r_ecef_m[0]);
  CHECK(out.has_position);
  CHECK_FALSE(out.has_reference);
  CHECK(std::isnan(out.temperature_C));
}

TEST_CASE("mag_batch_t carries its samples", "[schemas]") {
  magcal::mag_batch_t batch;
  batch.sat_id = "SAT-1";
  for (int i = 0; i < 200; ++i) batch.samples.push_back(make_sample(i));
  batch.n = static_cast<int32_t>(batch.samples.size());
  const auto out = round_trip(batch);
  REQUIRE(out.n == 200);
  CHECK(out.samples[199].seq == 199);
  // 200 samples stay under LCM's ~65 KB fragmentation threshold (toolchain.md).
  CHECK(batch.getEncodedSize() < 65000);
}

TEST_CASE("calibration_t and daemon_status_t round-trip", "[schemas]") {
  magcal::calibration_t c{};
  c.sat_id = "SAT-2";
  c.method = "twostep";
  c.cov[44] = 1e-8;
  c.status = 4;
  const auto c2 = round_trip(c);
  CHECK(c2.method == "twostep");
  CHECK(c2.cov[44] == 1e-8);
  CHECK(c2.status == 4);

  magcal::daemon_status_t st{};
  st.version = "x";
  st.rejected_reason = {"non_finite", "duplicate"};
  st.rejected_count = {3, 4};
  st.n_reasons = 2;
  const auto st2 = round_trip(st);
  CHECK(st2.rejected_count[1] == 4);
}

TEST_CASE("fingerprints are stable and distinguish the types", "[schemas]") {
  // The hash is a pure function of the field types and names. These golden values were
  // produced by lcm-gen 1.3.1 from the design's definitions: a silent edit of a .lcm file
  // (which would break every other tool on the bus) fails here.
  CHECK(magcal::mag_sample_t::getHash() == INT64_C(7804420587885521816));
  CHECK(magcal::mag_batch_t::getHash() == INT64_C(8100892405416991393));
  CHECK(magcal::calibration_t::getHash() == INT64_C(-3677493746968631786));
  const int64_t sample_fp = magcal::mag_sample_t::getHash();
  const int64_t batch_fp = magcal::mag_batch_t::getHash();
  const int64_t cal_fp = magcal::calibration_t::getHash();
  CHECK(sample_fp != batch_fp);
  CHECK(sample_fp != cal_fp);
  CHECK(batch_fp != cal_fp);
  // A decoder of another type refuses the bytes (fingerprint mismatch).
  const auto s = make_sample(1);
  std::vector<uint8_t> buf(static_cast<size_t>(s.getEncodedSize()));
  s.encode(buf.data(), 0, static_cast<int>(buf.size()));
  magcal::calibration_t wrong;
  CHECK(wrong.decode(buf.data(), 0, static_cast<int>(buf.size())) < 0);
  // Truncated frames are refused too.
  magcal::mag_sample_t truncated;
  CHECK(truncated.decode(buf.data(), 0, static_cast<int>(buf.size()) - 5) < 0);
}
