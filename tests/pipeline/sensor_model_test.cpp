#include "pipeline/sensor_model.hpp"

#include <catch2/catch.hpp>

#include <cmath>

#include "pipeline/rotation.hpp"

using namespace magcal;

namespace {
constexpr double kDeg = 3.141592653589793 / 180.0;
const Eigen::Vector3d kH(21000.0, -8000.0, 33000.0);  // a LEO-like field, nT

SensorModelParameters all_off() {
  return SensorModelParameters{};
}
}  // namespace

TEST_CASE("everything off except the installation rotation: B == R h exactly") {
  SensorModelParameters p = all_off();
  p.installation_deg = Eigen::Vector3d(1.0, 2.0, 1.0);
  SensorModel m(p);
  NormalSampler n(1);
  const Eigen::Matrix3d R = dcm_from_roll_pitch_yaw({1.0 * kDeg, 2.0 * kDeg, 1.0 * kDeg});
  for (int k = 0; k < 5; ++k) {
    const Eigen::Vector3d h = kH * (1.0 + 0.1 * k);
    CHECK(m.measure(h, 10.0 * k, n) == R * h);
  }
  CHECK(m.sensor_from_body() == R);
}

TEST_CASE("only a bias: B - h equals the bias, D only: (I + D) B == h") {
  SensorModelParameters p = all_off();
  p.bias_nT = Eigen::Vector3d(1000.0, 800.0, 900.0);
  SensorModel m(p);
  NormalSampler n(1);
  CHECK((m.measure(kH, 0.0, n) - kH - p.bias_nT).cwiseAbs().maxCoeff() < 1e-9);

  SensorModelParameters q = all_off();
  q.D << 0.01, 0.01, 0.01, 0.01, 0.02, 0.01, 0.01, 0.01, 0.01;
  SensorModel md(q);
  const Eigen::Vector3d B = md.measure(kH, 0.0, n);
  CHECK(((Eigen::Matrix3d::Identity() + q.D) * B - kH).cwiseAbs().maxCoeff() < 1e-9);
  CHECK((B - kH).norm() > 100.0);  // the effect is really there
}

TEST_CASE("permeability adds P x, internal misalignment is the small rotation C_int") {
  SensorModelParameters p = all_off();
  p.permeability << 0.002, 0.001, 0.0, 0.001, -0.003, 0.0005, 0.0, 0.0005, 0.001;
  SensorModel m(p);
  NormalSampler n(1);
  CHECK((m.measure(kH, 0.0, n) - (Eigen::Matrix3d::Identity() + p.permeability) * kH).norm() <
        1e-9);

  SensorModelParameters c = all_off();
  c.internal_misalignment_mrad = Eigen::Vector3d(5.0, -3.0, 2.0);
  const Eigen::Matrix3d C = c.internal_misalignment();
  const Eigen::Vector3d theta = c.internal_misalignment_mrad * 1e-3;
  CHECK((C - (Eigen::Matrix3d::Identity() - cross_matrix(theta))).cwiseAbs().maxCoeff() <
        5e-5);  // O(theta^2)
  c.installation_deg = Eigen::Vector3d(1.0, 2.0, 1.0);
  SensorModel mc(c);
  CHECK((mc.sensor_from_body() - C * c.installation()).norm() == 0.0);
  CHECK((mc.measure(kH, 0.0, n) - C * c.installation() * kH).norm() < 1e-9);
}

TEST_CASE("nonlinearity is k_nl x^2 / FS per axis") {
  SensorModelParameters p = all_off();
  p.nonlinearity_fraction_fs = 1e-4;
  SensorModel m(p);
  NormalSampler n(1);
  const Eigen::Vector3d expected = kH + 1e-4 / p.full_scale_nT * kH.cwiseAbs2();
  CHECK((m.measure(kH, 0.0, n) - expected).cwiseAbs().maxCoeff() < 1e-9);
  // At full scale the error is k_nl FS = 10 nT.
  const Eigen::Vector3d fs = Eigen::Vector3d::Constant(p.full_scale_nT);
  CHECK((m.measure(fs, 0.0, n) - fs).maxCoeff() == Approx(10.0).epsilon(1e-9));
}

TEST_CASE("hysteresis switches with the direction of the noise-free field") {
  SensorModelParameters p = all_off();
  p.hysteresis_fraction_fs = 1e-4;  // 10 nT at 100 000 nT FS
  SensorModel m(p);
  NormalSampler n(1);
  const double kh = 1e-4 * p.full_scale_nT;
  Eigen::Vector3d h = kH;
  m.measure(h, 0.0, n);
  // Rising on x, falling on y, constant on z.
  h += Eigen::Vector3d(50.0, -50.0, 0.0);
  Eigen::Vector3d e = m.measure(h, 10.0, n) - h;
  CHECK(e.x() == Approx(kh));
  CHECK(e.y() == Approx(-kh));
  CHECK(e.z() == Approx(kh));  // initial sign kept while unchanged
  // Reverse directions: every sign flips; a constant field keeps the last sign.
  h += Eigen::Vector3d(-1.0, 1.0, -1.0);
  e = m.measure(h, 20.0, n) - h;
  CHECK(e.x() == Approx(-kh));
  CHECK(e.y() == Approx(kh));
  CHECK(e.z() == Approx(-kh));
  e = m.measure(h, 30.0, n) - h;
  CHECK(e.x() == Approx(-kh));
  CHECK(e.z() == Approx(-kh));
}

TEST_CASE("quantisation steps are the LSB, saturation clips to the range") {
  SensorModelParameters p = all_off();
  p.nbits = 16;
  SensorModel m(p);
  const double lsb = 2.0 * p.full_scale_nT / 65536.0;
  REQUIRE(p.lsb_nT() == lsb);
  // A slow ramp: every output is an integer number of LSB, and consecutive outputs differ by
  // 0 or 1 LSB; the quantisation error is within half an LSB.
  NormalSampler n(1);
  double previous = NAN;
  int steps = 0;
  for (int k = 0; k < 2000; ++k) {
    const Eigen::Vector3d h(1234.5 + 0.37 * k, -5000.0, 0.0);
    const Eigen::Vector3d B = m.measure(h, k, n);
    CHECK(B.x() / lsb == std::round(B.x() / lsb));
    CHECK(std::abs(B.x() - h.x()) <= 0.5 * lsb + 1e-9);
    if (k > 0) {
      const double d = (B.x() - previous) / lsb;
      CHECK((d == 0.0 || d == 1.0));
      steps += d == 1.0;
    }
    previous = B.x();
  }
  CHECK(steps == Approx(0.37 * 1999 / lsb).margin(1.0));

  // Saturation without quantisation clips to +-FS; with it, to [-FS, FS - LSB].
  SensorModelParameters s = all_off();
  s.saturation = true;
  const Eigen::Vector3d big(2e5, -3e5, 5e4);
  CHECK(SensorModel(s).measure(big, 0.0, n) == Eigen::Vector3d(1e5, -1e5, 5e4));
  s.nbits = 16;
  CHECK(SensorModel(s).measure(big, 0.0, n) == Eigen::Vector3d(1e5 - lsb, -1e5, 5e4));
  // Without saturation the (unquantised) output exceeds the range.
  CHECK(SensorModel(all_off()).measure(big, 0.0, n).x() == 2e5);
}

TEST_CASE("temperature-dependent bias and drift follow b0 + k_T (T - T0) + k_drift t") {
  SensorModelParameters p = all_off();
  p.bias_nT = Eigen::Vector3d(10.0, 20.0, 30.0);
  p.temperature_coefficient_nT_per_C = Eigen::Vector3d(2.0, -1.0, 0.5);
  p.reference_temperature_C = 20.0;
  p.temperature_mean_C = 15.0;
  p.temperature_amplitude_C = 10.0;
  p.temperature_period_s = 6000.0;
  p.drift_nT_per_day = Eigen::Vector3d(5.0, 0.0, -5.0);
  SensorModel m(p);
  CHECK(m.temperature_C(0.0) == Approx(15.0));
  CHECK(m.temperature_C(1500.0) == Approx(25.0));
  CHECK(m.temperature_C(4500.0) == Approx(5.0));
  NormalSampler n(1);
  const Eigen::Vector3d b_quarter = m.measure(kH, 1500.0, n) - kH;
  const Eigen::Vector3d expected = p.bias_nT + p.temperature_coefficient_nT_per_C * 5.0 +
                                   p.drift_nT_per_day * (1500.0 / 86400.0);
  CHECK((b_quarter - expected).norm() < 1e-9);
  CHECK((m.bias_nT(86400.0, 20.0) - (p.bias_nT + p.drift_nT_per_day)).norm() < 1e-12);
}

TEST_CASE("white noise has the configured sigma, the sampler is deterministic") {
  SensorModelParameters p = all_off();
  p.noise_sigma_nT = 3.0;
  SensorModel m(p);
  NormalSampler n(42);
  constexpr int kN = 30000;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero(), sum2 = Eigen::Vector3d::Zero();
  for (int k = 0; k < kN; ++k) {
    const Eigen::Vector3d e = m.measure(kH, k, n) - kH;
    sum += e;
    sum2 += e.cwiseAbs2();
  }
  const Eigen::Vector3d mean = sum / kN;
  const Eigen::Vector3d sd = (sum2 / kN - mean.cwiseAbs2()).cwiseSqrt();
  // 5-sigma bands of the estimators: mean 3/sqrt(N) ~ 0.017, sd 3/sqrt(2N) ~ 0.012.
  CHECK(mean.cwiseAbs().maxCoeff() < 5.0 * 3.0 / std::sqrt(kN));
  CHECK((sd.array() - 3.0).abs().maxCoeff() < 5.0 * 3.0 / std::sqrt(2.0 * kN));
  NormalSampler a(7), b(7), c(8);
  bool all_same = true, any_diff = false;
  for (int k = 0; k < 100; ++k) {
    const double x = a.next();
    all_same = all_same && x == b.next();
    any_diff = any_diff || x != c.next();
  }
  CHECK(all_same);
  CHECK(any_diff);
}

TEST_CASE("sensor parameters are validated, naming the key") {
  SensorModelParameters p = all_off();
  CHECK(p.validate().empty());
  p.bias_nT(1) = NAN;
  CHECK(p.validate().find("sensor.bias_nT") != std::string::npos);
  p = all_off();
  p.D(0, 1) = 0.01;
  CHECK(p.validate().find("sensor.D") != std::string::npos);
  p = all_off();
  p.nbits = 2;
  CHECK(p.validate().find("sensor.nbits") != std::string::npos);
  p = all_off();
  p.noise_sigma_nT = -1.0;
  CHECK(p.validate().find("sensor.noise_sigma_nT") != std::string::npos);
  p = all_off();
  p.D = -Eigen::Matrix3d::Identity() * 0.5;
  p.D(0, 0) = -1.0;
  CHECK(!p.validate().empty());
}
