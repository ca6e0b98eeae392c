// Time-tag offset estimation (issue 7) on synthetic LEO data with a known injected offset:
// tilted dipole rotating with the Earth, ISS-like circular orbit, tumbling body, the estimation
// model's sensor (bias, D, white noise). The reference series is |H| at *mislabelled* times:
// the value tagged T is the true field at T - tau_true, so the reference for a measurement at t
// is at t + tau_true (the header's sign convention).
#include "pipeline/time_offset.hpp"

#include <cmath>
#include <fstream>
#include <random>
#include <sstream>
#include <string>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <catch2/catch.hpp>

#include "tests/test_skip.hpp"

#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/time_utc.hpp"

using namespace magcal;

namespace {

constexpr double kTwoPi = 6.283185307179586;
constexpr int64_t kStartUtime = 1577836800LL * 1000000;  // 2020-01-01T00:00:00Z
constexpr double kStart_s = 1577836800.0;

// Tilted dipole field (nT) in an inertial frame at time t (s since the start): circular orbit,
// 6800 km radius, 51.6 deg inclination, 5570 s period; dipole tilted 11 deg, turning with the
// Earth.
Eigen::Vector3d dipole_field_nT(double t) {
  constexpr double kB0 = 30000.0, kRe = 6371.0, kR = 6800.0, kInc = 51.6 * kTwoPi / 360.0;
  const double u = kTwoPi * t / 5570.0;
  const Eigen::Vector3d r_hat(std::cos(u), std::sin(u) * std::cos(kInc),
                              std::sin(u) * std::sin(kInc));
  const double tilt = 11.0 * kTwoPi / 360.0, lon = kTwoPi * t / 86164.0;
  const Eigen::Vector3d m(std::sin(tilt) * std::cos(lon), std::sin(tilt) * std::sin(lon),
                          std::cos(tilt));
  const double scale = kB0 * std::pow(kRe / kR, 3);
  return scale * (3.0 * m.dot(r_hat) * r_hat - m);
}

struct Synthetic {
  SampleSet samples;
  ReferenceSeries reference;
  int bad_rows = 0;
};

// Measurements every period_s for hours; reference |H| every ref_period_s, tags late by tau.
Synthetic make_data(double tau_true_s, double hours, double period_s, double ref_period_s,
                    double sigma_nT, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, sigma_nT);
  Eigen::Matrix3d D;
  D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  const Eigen::Vector3d b(1000.0, 800.0, 900.0);
  const Eigen::Matrix3d IpD_inv = (Eigen::Matrix3d::Identity() + D).inverse();
  Synthetic out;
  const int n = static_cast<int>(hours * 3600.0 / period_s);
  for (int k = 0; k < n; ++k) {
    const double t = k * period_s;
    // Tumbling body: rotation about a slowly precessing axis (every axis sees the field).
    const Eigen::Vector3d axis =
        Eigen::Vector3d(std::cos(kTwoPi * t / 10800.0), std::sin(kTwoPi * t / 10800.0), 0.7)
            .normalized();
    const Eigen::Matrix3d A(Eigen::AngleAxisd(0.005 * t, axis));
    const Eigen::Vector3d h = A * dipole_field_nT(t);
    CalibrationSample s;
    s.utime = kStartUtime + static_cast<int64_t>(std::llround(t * 1e6));
    s.b_sensor_nT = IpD_inv * (h + b + Eigen::Vector3d(noise(rng), noise(rng), noise(rng)));
    s.has_reference_direction = false;
    out.samples.push_back(s);
  }
  // Reference covering the measurements plus margins on both sides.
  for (double T = -2000.0; T <= hours * 3600.0 + 2000.0; T += ref_period_s) {
    out.reference.t_s.push_back(kStart_s + T);
    out.reference.value_nT.push_back(dipole_field_nT(T - tau_true_s).norm());
  }
  return out;
}

TimeOffsetOptions search(double tau_min, double tau_max, double step) {
  TimeOffsetOptions o;
  o.tau_min_s = tau_min;
  o.tau_max_s = tau_max;
  o.step_s = step;
  return o;
}

}  // namespace

TEST_CASE("interpolation: exact where it should be, NaN outside and across gaps", "[time]") {
  ReferenceSeries s;
  for (double t : {0.0, 1.0, 2.5, 3.0, 5.0, 100.0}) {
    s.t_s.push_back(t);
    s.value_nT.push_back(3.0 + 2.0 * t - 0.5 * t * t);  // a quadratic
  }
  REQUIRE(s.validate().empty());
  constexpr double kTol = 1e-9;
  // Cubic Hermite with quadratic-exact tangents reproduces a quadratic (interior intervals).
  for (double t : {1.2, 2.0, 2.7, 4.1})
    CHECK(interpolate(s, t, Interpolation::kCubic) ==
          Approx(3.0 + 2.0 * t - 0.5 * t * t).margin(kTol));
  CHECK(interpolate(s, 1.75, Interpolation::kLinear) ==
        Approx(0.5 * (s.value_nT[1] + s.value_nT[2])).margin(kTol));
  CHECK(interpolate(s, 2.5, Interpolation::kCubic) == Approx(s.value_nT[2]).margin(kTol));
  CHECK(std::isnan(interpolate(s, -0.1, Interpolation::kCubic)));
  CHECK(std::isnan(interpolate(s, 100.1, Interpolation::kLinear)));
  CHECK(std::isnan(interpolate(s, 50.0, Interpolation::kCubic, 10.0)));  // inside a 95 s gap
  CHECK(std::isfinite(interpolate(s, 4.0, Interpolation::kCubic, 10.0)));

  ReferenceSeries bad = s;
  bad.t_s[3] = 2.0;
  CHECK_FALSE(bad.validate().empty());
  bad = s;
  bad.value_nT[1] = NAN;
  CHECK_FALSE(bad.validate().empty());
}

TEST_CASE("recovers an injected 480 s offset to sub-sample accuracy", "[time]") {
  constexpr double kTauTrue = 480.0;
  // 6 h of 10 s samples, 3 nT noise, reference every 10 s.
  const Synthetic d = make_data(kTauTrue, 6.0, 10.0, 10.0, 3.0, 1);
  const TimeOffsetResult r = estimate_time_offset(d.samples, d.reference, search(0, 1000, 20));
  INFO(r.message << " tau " << r.tau_s << " +- " << r.sigma_tau_s << " s, rms " << r.residual_rms_nT
                 << " nT (at 0: " << r.residual_rms_at_zero_nT << "), fits " << r.n_fits);
  REQUIRE(r.ok());
  CHECK(std::abs(r.tau_s - kTauTrue) < 0.1);  // sample period is 10 s
  CHECK(std::abs(r.tau_s - kTauTrue) < 5.0 * r.sigma_tau_s);
  CHECK(r.residual_rms_nT < 1.2 * 3.0);      // noise level once aligned
  CHECK(r.residual_rms_at_zero_nT > 100.0);  // the "before": offset ignored
  CHECK(r.profile_tau_s.size() == 51);
  CHECK(r.profile_rms_nT.size() == 51);
  CHECK(r.n_samples == static_cast<int>(d.samples.size()));

  // Negative offsets and a non-grid value, linear interpolation.
  const Synthetic neg = make_data(-123.4, 6.0, 10.0, 10.0, 3.0, 2);
  TimeOffsetOptions o = search(-600, 600, 15);
  o.interpolation = Interpolation::kLinear;
  const TimeOffsetResult rn = estimate_time_offset(neg.samples, neg.reference, o);
  INFO("negative: tau " << rn.tau_s << " +- " << rn.sigma_tau_s);
  REQUIRE(rn.ok());
  CHECK(std::abs(rn.tau_s + 123.4) < 0.2);
}

TEST_CASE("the reported sigma of tau is consistent with the scatter", "[time]") {
  // Large noise (300 nT, a low-cost sensor) so the offset error is well above the
  // interpolation error; normalised errors should have rms ~1.
  constexpr int kRuns = 16;
  constexpr double kTauTrue = 480.0;
  double sum_z2 = 0.0, sigma_mean = 0.0;
  for (int run = 0; run < kRuns; ++run) {
    const Synthetic d = make_data(kTauTrue, 3.0, 10.0, 10.0, 300.0, 100 + run);
    const TimeOffsetResult r = estimate_time_offset(d.samples, d.reference, search(400, 560, 20));
    REQUIRE(r.ok());
    const double z = (r.tau_s - kTauTrue) / r.sigma_tau_s;
    sum_z2 += z * z / kRuns;
    sigma_mean += r.sigma_tau_s / kRuns;
  }
  // rms of kRuns standard normals: chi-square(16)/16 lies in [0.36, 1.8] with 99 % probability.
  INFO("rms normalised error " << std::sqrt(sum_z2) << ", mean sigma " << sigma_mean << " s");
  CHECK(sum_z2 > 0.36);
  CHECK(sum_z2 < 1.8);
}

TEST_CASE("time offset off-nominal cases", "[time]") {
  const Synthetic d = make_data(480.0, 3.0, 10.0, 10.0, 3.0, 7);

  SECTION("true offset outside the searched range: at_boundary, not a fake minimum") {
    const TimeOffsetResult r = estimate_time_offset(d.samples, d.reference, search(0, 300, 20));
    CHECK(r.status == TimeOffsetStatus::kAtBoundary);
    CHECK(r.tau_s == 300.0);
  }
  SECTION("range larger than the reference margins leaves too few samples") {
    const TimeOffsetResult r =
        estimate_time_offset(d.samples, d.reference, search(-20000, 20000, 1000));
    CHECK(r.status == TimeOffsetStatus::kTooFewSamples);
  }
  SECTION("invalid options and series") {
    CHECK(estimate_time_offset(d.samples, d.reference, search(10, 0, 1)).status ==
          TimeOffsetStatus::kInvalidInput);
    CHECK(estimate_time_offset(d.samples, d.reference, search(0, 10, 0)).status ==
          TimeOffsetStatus::kInvalidInput);
    ReferenceSeries bad = d.reference;
    bad.value_nT.pop_back();
    CHECK(estimate_time_offset(d.samples, bad, search(0, 600, 20)).status ==
          TimeOffsetStatus::kInvalidInput);
  }
  SECTION("NaN samples are skipped, not propagated") {
    SampleSet s = d.samples;
    s[5].b_sensor_nT.x() = NAN;
    const TimeOffsetResult r = estimate_time_offset(s, d.reference, search(400, 560, 20));
    REQUIRE(r.ok());
    CHECK(r.n_samples == static_cast<int>(s.size()) - 1);
    CHECK(std::abs(r.tau_s - 480.0) < 0.2);
  }
  SECTION("apply_time_offset drops samples without a reference value") {
    SampleSet out;
    const int dropped =
        apply_time_offset(d.samples, d.reference, 5000.0, Interpolation::kCubic, &out);
    CHECK(dropped > 0);
    CHECK(out.size() + dropped == d.samples.size());
    CHECK_FALSE(out.front().has_reference_direction);
  }
}

// ---------------------------------------------------------------------------------------------
// Real data: ISS Astro Pi Mark II "IR" (../shared/data/real/README.md). Position columns lag the
// magnetometer by ~480 s; the issue requires tau in 470–490 s and residual < 600 nT after it.

namespace {

struct IssData {
  SampleSet samples;
  ReferenceSeries reference;
  int bad_rows = 0;
};

// Reads the CSV: UTC time, geodetic lat/lon (deg), Mag in uT; |H| from IGRF-14 at 420 km.
// Skips the first 20 rows (start-up transients, README).
bool load_iss(IssData* out) {
  const std::string path =
      std::string(MAGCAL_SHARED_DATA_DIR) + "/real/astropi_mk2_ir_commissioning_2022-01-31.csv";
  std::ifstream in(path);
  if (!in) return false;
  constexpr int kSkipRows = 20;
  constexpr double kAltitude_m = 420e3;
  constexpr double kDeg = kTwoPi / 360.0;
  IgrfModel igrf;
  std::string line;
  std::getline(in, line);  // header
  for (int row = 0; std::getline(in, line); ++row) {
    if (row < kSkipRows) continue;
    std::vector<std::string> f;
    std::stringstream ss(line);
    for (std::string cell; std::getline(ss, cell, ',');) f.push_back(cell);
    if (f.size() < 10 || f[0].size() != 19) {
      ++out->bad_rows;
      continue;
    }
    std::string iso = f[0];
    iso[10] = 'T';
    const auto utime = parse_iso8601_utc(iso + "Z");
    if (!utime || !igrf.set_date(decimal_year_from_utime(*utime))) {
      ++out->bad_rows;
      continue;
    }
    const Eigen::Vector3d r =
        ecef_from_geodetic({std::stod(f[1]) * kDeg, std::stod(f[2]) * kDeg, kAltitude_m});
    const double t_s = static_cast<double>(*utime) * 1e-6;
    if (!out->reference.t_s.empty() && !(t_s > out->reference.t_s.back())) continue;
    out->reference.t_s.push_back(t_s);
    out->reference.value_nT.push_back(igrf.field_ecef_nT(r).norm());
    CalibrationSample s;
    s.utime = *utime;
    s.b_sensor_nT = 1000.0 * Eigen::Vector3d(std::stod(f[7]), std::stod(f[8]), std::stod(f[9]));
    s.has_reference_direction = false;
    out->samples.push_back(s);
  }
  return true;
}

}  // namespace

TEST_CASE("ISS Astro Pi: the ~480 s position lag is found from the data", "[time][real]") {
  IssData d;
  if (!load_iss(&d)) {
    magcal::test::skip_or_fail("ISS recording not found under " MAGCAL_SHARED_DATA_DIR "/real");
    return;
  }
  CHECK(d.bad_rows == 0);
  REQUIRE(d.samples.size() > 13000);
  TimeOffsetOptions o = search(-1000, 1000, 40);
  o.fit.sigma_nT = 150.0;  // first-difference noise per axis (README), incl. quantisation
  const TimeOffsetResult r = estimate_time_offset(d.samples, d.reference, o);
  WARN("ISS: tau " << r.tau_s << " +- " << r.sigma_tau_s << " s (white " << r.sigma_tau_white_s
                   << " s, rho " << r.residual_lag1_correlation << "), residual rms "
                   << r.residual_rms_nT << " nT (offset ignored: " << r.residual_rms_at_zero_nT
                   << " nT), " << r.n_samples << " samples, " << r.n_fits << " fits");
  REQUIRE(r.ok());
  CHECK(r.tau_s > 470.0);
  CHECK(r.tau_s < 490.0);
  CHECK(r.residual_rms_nT < 600.0);
  CHECK(r.residual_rms_at_zero_nT > 3000.0);

  // Each half of the recording finds the same lag on its own.
  const std::size_t half = d.samples.size() / 2;
  for (int part = 0; part < 2; ++part) {
    SampleSet s(d.samples.begin() + (part == 0 ? 0 : half),
                part == 0 ? d.samples.begin() + half : d.samples.end());
    const TimeOffsetResult h = estimate_time_offset(s, d.reference, search(380, 580, 20));
    WARN("ISS half " << part + 1 << ": tau " << h.tau_s << " +- " << h.sigma_tau_s << " s, rms "
                     << h.residual_rms_nT << " nT");
    // Measured: 446 s and 490 s. The lag is not constant over the 19.5 h (clock / TLE drift),
    // so only "the lag is found in each half" is asserted here, not agreement within sigma.
    REQUIRE(h.ok());
    CHECK(std::abs(h.tau_s - r.tau_s) < 60.0);
    CHECK(h.residual_rms_nT < 600.0);
  }
}
