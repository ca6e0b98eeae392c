// Recording-based fit (service/analysis/real_data_fit.hpp) on the two real files of
// ../shared/data/real (README there: sources, licences, statistics measured independently with
// numpy) and on simulated recordings with known truth. Real-file tests are skipped
// (tests/test_skip.hpp) when the folder is absent.
#include "service/analysis/real_data_fit.hpp"

#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <random>
#include <string>

#include <Eigen/Dense>
#include <catch2/catch.hpp>

#include <nlohmann/json.hpp>
#include "tests/test_skip.hpp"

#include "pipeline/rotation.hpp"
#include "pipeline/temperature_model.hpp"

using namespace magcal;

namespace {

const std::string kIssPath =
    std::string(MAGCAL_SHARED_DATA_DIR) + "/real/astropi_mk2_ir_commissioning_2022-01-31.csv";
const std::string kBroadPath =
    std::string(MAGCAL_SHARED_DATA_DIR) + "/real/broad_02_undisturbed_slow_rotation_B_mag_quat.csv";

std::optional<FieldRecording> read_iss() {
  if (!std::filesystem::exists(kIssPath)) return std::nullopt;
  FieldRecordingOptions o;
  o.field_unit = FieldUnit::kMicroTesla;
  o.altitude_km = 420.0;  // ISS, no altitude column (README)
  o.skip_first = 20;      // start-up transients (README)
  std::string error;
  auto rec = read_field_recording(kIssPath, o, &error);
  INFO(error);
  REQUIRE(rec);
  return rec;
}

std::optional<FieldRecording> read_broad() {
  if (!std::filesystem::exists(kBroadPath)) return std::nullopt;
  std::string error;
  auto rec = read_field_recording(kBroadPath, {}, &error);
  INFO(error);
  REQUIRE(rec);
  return rec;
}

// Issue 7 targets (ISS).
constexpr double kTauMin_s = 470.0, kTauMax_s = 490.0;
constexpr double kMaxResidualAfter_nT = 600.0;
constexpr double kMinResidualBefore_nT = 3000.0;  // README: 3 410 nT with the offset ignored
constexpr double kMaxHalfBiasDiff_nT = 500.0;
constexpr double kMaxHalfDiagDDiff = 0.02;
constexpr double kIssExpectedResidual_nT = 500.0;
// Coarser than the CLI default (40 s) to keep the test modest under ASan; the refinement
// inside the bracketing interval still resolves the minimum (same tau to 0.1 s, measured).
constexpr double kIssTestGrid_s = 100.0;  // README: ~545 nT after the offset
// BROAD targets.
constexpr double kBroadRadiusRef_nT = 44520.0, kBroadRadiusTol_nT = 100.0;  // README 44.52 uT
constexpr double kBroadResidualLo_nT = 600.0, kBroadResidualHi_nT = 900.0;  // README ~0.8 uT
constexpr double kMaxEnuStd_nT = 1100.0;

double max_abs_diff(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return (a - b).cwiseAbs().maxCoeff();
}

}  // namespace

TEST_CASE("ISS Astro Pi: offset found, residual drops, halves agree in bias, gates",
          "[real][iss]") {
  const auto rec = read_iss();
  if (!rec) {
    magcal::test::skip_or_fail(std::string(kIssPath) + " not found");
    return;
  }
  CHECK(rec->n_skipped_first == 20);
  CHECK(rec->n_rejected_non_finite == 0);

  RecordingFitOptions o;
  o.estimate_time_offset = true;  // default range -1000..1000 s
  o.offset_step_s = kIssTestGrid_s;
  o.split_halves = true;
  std::string error;
  const auto rep = fit_recording(*rec, o, &error);
  INFO(error);
  REQUIRE(rep);
  REQUIRE(rep->offset_estimate);
  const TimeOffsetResult& off = *rep->offset_estimate;
  const CalibrationResult& r = rep->result;
  WARN("ISS: tau " << off.tau_s << " +- " << off.sigma_tau_s << " s; residual rms offset ignored "
                   << rep->residual_rms_zero_offset_nT << " nT -> " << r.residual_rms_nT
                   << " nT (sigma used " << rep->sigma_used_nT << " nT, " << r.n_samples
                   << " samples); b " << r.parameters.bias_nT.transpose() << " nT, diag(D) "
                   << r.parameters.D.diagonal().transpose());
  CHECK(off.ok());
  CHECK(rep->time_offset_s > kTauMin_s);
  CHECK(rep->time_offset_s < kTauMax_s);
  CHECK(std::isfinite(off.sigma_tau_s));
  CHECK(off.sigma_tau_s > 0.0);
  CHECK(rep->residual_rms_zero_offset_nT > kMinResidualBefore_nT);
  CHECK(r.residual_rms_nT < kMaxResidualAfter_nT);
  CHECK(rep->sigma_estimated);
  CHECK(rep->sigma_used_nT == Approx(r.residual_rms_nT).epsilon(0.03));

  // Gates: the spacecraft default (7.5 nT expected) rejects on residual — correct.
  CHECK_FALSE(r.accepted);
  REQUIRE_FALSE(r.rejection_reasons.empty());
  CHECK(r.rejection_reasons.front().rfind("residual", 0) == 0);
  CHECK(r.status == CalibrationStatus::kRejected);

  // Halves at the whole recording's offset: bias agrees within 0.5 uT per axis.
  REQUIRE(rep->first_half);
  REQUIRE(rep->second_half);
  const CalibrationResult& h1 = rep->first_half->result;
  const CalibrationResult& h2 = rep->second_half->result;
  WARN("ISS halves: b1 " << h1.parameters.bias_nT.transpose() << " b2 "
                         << h2.parameters.bias_nT.transpose() << " nT; diag(D) 1 "
                         << h1.parameters.D.diagonal().transpose() << " 2 "
                         << h2.parameters.D.diagonal().transpose() << "; rms " << h1.residual_rms_nT
                         << " / " << h2.residual_rms_nT << " nT");
  CHECK(h1.residual_rms_nT < kMaxResidualAfter_nT);
  CHECK(h2.residual_rms_nT < kMaxResidualAfter_nT);
  // A half with a bias rate publishes the bias at its own end: both are compared at the first
  // half's end, where the second begins (moved by their rates, as the refit's change gate does).
  const int64_t boundary_utime = h1.window_end_utime;
  const Eigen::Vector3d b1 = at_utime(h1, boundary_utime).parameters.bias_nT;
  const Eigen::Vector3d b2 = at_utime(h2, boundary_utime).parameters.bias_nT;
  WARN("ISS halves at the boundary: b1 "
       << b1.transpose() << " b2 " << b2.transpose() << " nT; rates "
       << h1.bias_rate_nT_per_h.transpose() << " / " << h2.bias_rate_nT_per_h.transpose()
       << " nT/h; spans " << (h1.window_end_utime - h1.window_start_utime) / 3.6e9 << " / "
       << (h2.window_end_utime - h2.window_start_utime) / 3.6e9 << " h");
  CHECK(max_abs_diff(b1, b2) < kMaxHalfBiasDiff_nT);

  // With an expected residual fitting this sensor the same fit is accepted.
  RecordingFitOptions o2;
  o2.time_offset_s = rep->time_offset_s;
  o2.batch.gate_options.expected_residual_nT = kIssExpectedResidual_nT;
  const auto rep2 = fit_recording(*rec, o2, &error);
  REQUIRE(rep2);
  INFO(rep2->result.rejection_reasons.size());
  CHECK(rep2->result.accepted);
  CHECK(rep2->result.status == CalibrationStatus::kOk);
  CHECK(rep2->result.residual_rms_nT == Approx(r.residual_rms_nT).epsilon(1e-6));

  // With the offset ignored the residual is far above what that expected residual allows.
  CHECK(rep->residual_rms_zero_offset_nT > 3.0 * kIssExpectedResidual_nT);
}

// Issue 7 also asks diag(D) of the halves to agree within 0.02. On this file that is not
// attainable: at the README's 480 s, diag(D) = (0.072, 0.195, 0.090) and (0.077, 0.126, 0.126)
// (the README's own numpy fit gives the same halves' residuals, 457 / 462 nT, and reports only
// the bias agreement). This test pins down why: the halves' difference is many times their
// formal sigma, so the gap is unmodelled (ISS stray fields, a drifting lag), not noise — and it
// still guards the fit against regressions with a 0.1 bound.
TEST_CASE("ISS Astro Pi: halves' diag(D) differ by more than noise, less than 0.1", "[real][iss]") {
  const auto rec = read_iss();
  if (!rec) {
    magcal::test::skip_or_fail(std::string(kIssPath) + " not found");
    return;
  }
  RecordingFitOptions o;
  o.time_offset_s = 480.0;  // README
  o.split_halves = true;
  std::string error;
  const auto rep = fit_recording(*rec, o, &error);
  REQUIRE(rep);
  REQUIRE(rep->first_half);
  REQUIRE(rep->second_half);
  const auto& r1 = rep->first_half->result;
  const auto& r2 = rep->second_half->result;
  const Eigen::Vector3d d1 = r1.parameters.D.diagonal();
  const Eigen::Vector3d d2 = r2.parameters.D.diagonal();
  WARN("ISS halves at 480 s: diag(D) " << d1.transpose() << " vs " << d2.transpose());
  constexpr double kRegressionBound = 0.1;
  CHECK(max_abs_diff(d1, d2) < kRegressionBound);
  // D22: the largest gap, compared with the combined formal (white-noise) 1-sigma of the two
  // halves: far beyond it. The reported (HAC, issue 10) covariance covers it: within 5 sigma.
  const double sigma_combined =
      std::sqrt(r1.covariance_white_noise(4, 4) + r2.covariance_white_noise(4, 4));
  const double sigma_reported = std::sqrt(r1.covariance(4, 4) + r2.covariance(4, 4));
  WARN("D22 gap " << std::abs(d1(1) - d2(1)) << " = " << std::abs(d1(1) - d2(1)) / sigma_combined
                  << " formal sigma, " << std::abs(d1(1) - d2(1)) / sigma_reported
                  << " reported sigma");
  CHECK(std::abs(d1(1) - d2(1)) > 5.0 * sigma_combined);
  CHECK(std::abs(d1(1) - d2(1)) < 5.0 * sigma_reported);
}

TEST_CASE("BROAD lab data: auto magnitude, residual ~0.8 uT, stage 2 against optical truth",
          "[real][broad]") {
  const auto rec = read_broad();
  if (!rec) {
    magcal::test::skip_or_fail(std::string(kBroadPath) + " not found");
    return;
  }
  CHECK(rec->rows.size() == 53240);
  CHECK(rec->n_missing_quaternion == 1706);  // README

  RecordingFitOptions o;
  o.reference_magnitude_auto = true;
  std::string error;
  const auto rep = fit_recording(*rec, o, &error);
  INFO(error);
  REQUIRE(rep);
  REQUIRE(rep->sphere);
  const RecordingAlignment& al = rep->alignment;
  const CalibrationResult& r = rep->result;
  constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;
  WARN("BROAD: sphere radius " << rep->sphere->radius_nT << " nT, centre "
                               << rep->sphere->center_nT.transpose() << ", rms "
                               << rep->sphere->residual_rms_nT << " nT; 9-param residual "
                               << r.residual_rms_nT << " nT; b " << r.parameters.bias_nT.transpose()
                               << "; ENU std R_hat " << al.enu_std_nT.transpose() << " / R=I "
                               << al.enu_std_identity_nT.transpose() << " nT; field ENU "
                               << al.field_enu_nT.transpose() << "; R_hat rpy deg "
                               << al.rpy.roll_rad * kRadToDeg << " " << al.rpy.pitch_rad * kRadToDeg
                               << " " << al.rpy.yaw_rad * kRadToDeg);
  CHECK(rep->reference_magnitude_nT == rep->sphere->radius_nT);
  CHECK(std::abs(rep->sphere->radius_nT - kBroadRadiusRef_nT) < kBroadRadiusTol_nT);
  CHECK(r.residual_rms_nT > kBroadResidualLo_nT);
  CHECK(r.residual_rms_nT < kBroadResidualHi_nT);
  CHECK(r.residual_rms_nT <= rep->sphere->residual_rms_nT);  // 9 params nest the sphere's 4

  REQUIRE(al.estimated);
  CHECK(al.n_pairs == 53240 - 1706);
  CHECK(r.has_alignment);
  for (int i = 0; i < 3; ++i) {
    CHECK(al.enu_std_nT(i) <= kMaxEnuStd_nT);
    CHECK(al.enu_std_nT(i) <= al.enu_std_identity_nT(i));
  }
  // The rotated field is the lab's (README: (-0.37, 15.22, -41.78) uT, |.| 44.4 uT).
  CHECK(std::abs(al.field_enu_nT.norm() - rep->reference_magnitude_nT) < kBroadRadiusTol_nT * 5);
}

// ---------------------------------------------------------------------------------------------
// Simulated recordings with known truth (the estimator does not see it).

namespace {

struct ConstantFieldTruth {
  Eigen::Vector3d b_nT{400.0, -250.0, 600.0};
  Eigen::Matrix3d D;
  Eigen::Vector3d f_enu_nT{-370.0, 15220.0, -41780.0};
  Eigen::Matrix3d R;
  ConstantFieldTruth() {
    D << 0.02, 0.004, -0.003, 0.004, -0.015, 0.002, -0.003, 0.002, 0.01;
    R = dcm_from_roll_pitch_yaw(
        {0.5 / 57.29577951308232, -0.3 / 57.29577951308232, 1.0 / 57.29577951308232});
  }
};

// Random attitudes; every 10th row without a quaternion.
FieldRecording simulate_constant_field(const ConstantFieldTruth& t, int n, double sigma_nT,
                                       unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  FieldRecording rec;
  rec.has_quaternion_columns = true;
  const Eigen::Matrix3d inv = (Eigen::Matrix3d::Identity() + t.D).inverse();
  for (int k = 0; k < n; ++k) {
    QuaternionWxyz q_file(g(rng), g(rng), g(rng), g(rng));  // IMU -> ENU
    q_file.normalize();
    const Eigen::Vector3d h_body = dcm_from_quaternion(quaternion_conjugate(q_file)) * t.f_enu_nT;
    // (I + D) B - b = R h + noise  =>  B = (I + D)^-1 (R h + b + noise)
    const Eigen::Vector3d noise = sigma_nT * Eigen::Vector3d(g(rng), g(rng), g(rng));
    FieldRecordingRow row;
    row.utime = 1'600'000'000'000'000 + k * 3500;
    row.b_sensor_nT = inv * (t.R * h_body + t.b_nT + noise);
    row.has_quaternion = k % 10 != 0;
    row.q_file = q_file;
    if (!row.has_quaternion) ++rec.n_missing_quaternion;
    rec.rows.push_back(row);
  }
  return rec;
}

}  // namespace

TEST_CASE("simulated constant field: b, D (given magnitude), R and the ENU field recovered",
          "[sim]") {
  const ConstantFieldTruth t;
  const double sigma = 50.0;
  const FieldRecording rec = simulate_constant_field(t, 3000, sigma, 11);
  RecordingFitOptions o;
  o.reference_magnitude_nT = t.f_enu_nT.norm();  // true magnitude: D is then identifiable
  std::string error;
  const auto rep = fit_recording(rec, o, &error);
  INFO(error);
  REQUIRE(rep);
  const CalibrationResult& r = rep->result;
  // 5 formal sigmas of the fit's own covariance (sigma estimated from the residual).
  constexpr double kSigmas = 5.0;
  const Eigen::Vector3d sb = r.bias_sigma_nT();
  for (int i = 0; i < 3; ++i)
    CHECK(std::abs(r.parameters.bias_nT(i) - t.b_nT(i)) < kSigmas * sb(i));
  const Eigen::Vector3d sd = r.covariance.diagonal().segment<3>(3).cwiseSqrt();
  for (int i = 0; i < 3; ++i) CHECK(std::abs(r.parameters.D(i, i) - t.D(i, i)) < kSigmas * sd(i));
  CHECK(rep->sigma_used_nT == Approx(sigma).epsilon(0.1));  // scalar residual ~ sigma
  REQUIRE(rep->alignment.estimated);
  CHECK(rep->alignment.n_pairs == 2700);
  const Eigen::Matrix3d& R_hat = rep->result.alignment.R_sensor_from_body;
  constexpr double kAngleTol_rad = 1e-3;  // ~ sigma / |f| / sqrt(N) x margin
  CHECK(rotation_angle(R_hat * t.R.transpose()) < kAngleTol_rad);
  CHECK((rep->alignment.field_enu_nT - t.f_enu_nT).norm() < 5.0 * sigma);
  // With R_hat the ENU scatter is at the noise level; with I it carries the misalignment.
  CHECK(rep->alignment.enu_std_nT.maxCoeff() < 2.0 * sigma);
  CHECK(rep->alignment.enu_std_identity_nT.maxCoeff() > rep->alignment.enu_std_nT.maxCoeff());
}

TEST_CASE("simulated constant field, auto magnitude: sphere radius within the scale ambiguity",
          "[sim]") {
  const ConstantFieldTruth t;
  const FieldRecording rec = simulate_constant_field(t, 2000, 30.0, 12);
  RecordingFitOptions o;
  o.reference_magnitude_auto = true;
  o.alignment = false;
  std::string error;
  const auto rep = fit_recording(rec, o, &error);
  REQUIRE(rep);
  REQUIRE(rep->sphere);
  // The raw radius is |f| scaled by (I + D)^-1 on average: within max|D_ii| of |f|.
  CHECK(std::abs(rep->sphere->radius_nT / t.f_enu_nT.norm() - 1.0) < 0.03);
  CHECK(rep->result.residual_rms_nT < 3.0 * 30.0);
  CHECK_FALSE(rep->alignment.estimated);
}

TEST_CASE("recording fit off-nominal: unusable inputs are errors, not garbage", "[sim]") {
  const ConstantFieldTruth t;
  const FieldRecording rec = simulate_constant_field(t, 200, 30.0, 13);
  std::string error;
  SECTION("no position and no constant magnitude") {
    CHECK_FALSE(fit_recording(rec, {}, &error));
    CHECK(error.find("--reference-magnitude") != std::string::npos);
  }
  SECTION("time offset with a constant reference") {
    RecordingFitOptions o;
    o.reference_magnitude_auto = true;
    o.estimate_time_offset = true;
    CHECK_FALSE(o.validate().empty());
    CHECK_FALSE(fit_recording(rec, o, &error));
  }
  SECTION("invalid magnitude, sigma, offset range") {
    RecordingFitOptions o;
    o.reference_magnitude_nT = -5.0;
    CHECK_FALSE(o.validate().empty());
    o.reference_magnitude_nT = 40000.0;
    o.sigma_nT = std::nan("");
    CHECK_FALSE(o.validate().empty());
    o.sigma_nT.reset();
    o.offset_min_s = 10.0;
    o.offset_max_s = -10.0;
    CHECK_FALSE(o.validate().empty());
  }
  SECTION("too few samples: failed status, not an estimate") {
    FieldRecording few = rec;
    few.rows.resize(12);
    RecordingFitOptions o;
    o.reference_magnitude_nT = 44000.0;
    const auto rep = fit_recording(few, o, &error);
    REQUIRE(rep);
    CHECK(rep->result.status == CalibrationStatus::kFailed);
    CHECK_FALSE(rep->alignment.estimated);
  }
  SECTION("auto magnitude on planar data: sphere fit refuses") {
    FieldRecording flat = rec;
    for (FieldRecordingRow& row : flat.rows) row.b_sensor_nT.z() = 0.0;
    RecordingFitOptions o;
    o.reference_magnitude_auto = true;
    CHECK_FALSE(fit_recording(flat, o, &error));
    CHECK(error.find("sphere") != std::string::npos);
  }
}

// `magcal fit --input <the recording as a BROAD-layout temp file> <flags> --json`, parsed (the
// real file takes ~10 s under ASan).
nlohmann::json magcal_fit_json(const FieldRecording& rec, const std::string& flags) {
  const std::string path =
      (std::filesystem::temp_directory_path() / "magcal_real_data_fit_cli.csv").string();
  {
    std::FILE* f = std::fopen(path.c_str(), "w");
    REQUIRE(f);
    std::fputs("t_s,mag_x_uT,mag_y_uT,mag_z_uT,q_w,q_x,q_y,q_z,movement\n", f);
    for (std::size_t k = 0; k < rec.rows.size(); ++k) {
      const FieldRecordingRow& r = rec.rows[k];
      const Eigen::Vector3d b = r.b_sensor_nT / 1000.0;
      if (r.has_quaternion)
        std::fprintf(f, "%.6f,%.8f,%.8f,%.8f,%.10f,%.10f,%.10f,%.10f,1\n", k / 285.714, b(0), b(1),
                     b(2), r.q_file(0), r.q_file(1), r.q_file(2), r.q_file(3));
      else
        std::fprintf(f, "%.6f,%.8f,%.8f,%.8f,nan,nan,nan,nan,1\n", k / 285.714, b(0), b(1), b(2));
    }
    std::fclose(f);
  }
  const std::string cmd =
      std::string(MAGCAL_BIN_DIR) + "/magcal fit --input " + path + " " + flags + " --json";
  std::string out;
  {
    std::unique_ptr<FILE, int (*)(FILE*)> pipe(popen(cmd.c_str(), "r"), pclose);
    REQUIRE(pipe);
    std::array<char, 4096> buf{};
    while (std::fgets(buf.data(), buf.size(), pipe.get())) out += buf.data();
  }
  std::error_code ec;
  std::filesystem::remove(path, ec);
  return nlohmann::json::parse(out, nullptr, false);
}

TEST_CASE("magcal fit dispatches a foreign CSV to the recording fit (JSON keys)", "[sim][cli]") {
  const ConstantFieldTruth t;
  const FieldRecording rec = simulate_constant_field(t, 1500, 50.0, 14);
  const nlohmann::json j =
      magcal_fit_json(rec, "--reference-magnitude auto --expected-residual-nT 60");
  REQUIRE_FALSE(j.is_discarded());
  for (const char* key :
       {"bias_nT", "D", "residual_rms_nT", "verdict", "rejection_reasons", "reference_magnitude_nT",
        "sphere_fit", "R_sensor_from_body", "alignment_deg", "field_enu_nT", "enu_std_nT",
        "enu_std_identity_nT", "n_missing_quaternion"})
    CHECK(j.contains(key));
  CHECK(j["verdict"] == "accepted");
  CHECK(j["n_missing_quaternion"] == rec.n_missing_quaternion);
  CHECK(j["reference"] == "constant");
}

// A noisy bench capture (150 nT) with the quaternions in the wrong convention: the alignment is
// refused, naming the convention that fits; never applied.
TEST_CASE("a recording's quaternion order or conjugate mix-up is refused and named", "[sim]") {
  const ConstantFieldTruth t;
  const double sigma = 150.0;
  const FieldRecording good = simulate_constant_field(t, 3000, sigma, 21);
  const auto fit = [&](const FieldRecording& rec) {
    RecordingFitOptions o;
    o.reference_magnitude_nT = t.f_enu_nT.norm();
    o.sigma_nT = sigma;
    o.batch.gate_options.expected_residual_nT = sigma;
    std::string error;
    const auto rep = fit_recording(rec, o, &error);
    REQUIRE(rep);
    return *rep;
  };
  struct Mixup {
    bool scalar_last, conjugate;
    const char* named;
  };
  for (const Mixup& m :
       {Mixup{true, false, "the quaternion columns look like x, y, z, w (scalar last)"},
        Mixup{false, true, "the quaternions look conjugated"}}) {
    FieldRecording rec = good;
    for (FieldRecordingRow& row : rec.rows) {
      const QuaternionWxyz q = m.conjugate ? quaternion_conjugate(row.q_file) : row.q_file;
      row.q_file = m.scalar_last ? QuaternionWxyz(q(1), q(2), q(3), q(0)) : q;
    }
    const RecordingFitReport rep = fit(rec);
    INFO(rep.alignment.inconsistency);
    CHECK_FALSE(rep.result.accepted);
    CHECK(rep.alignment.inconsistency.find(m.named) != std::string::npos);
    CHECK(rep.alignment.residual_per_axis_nT > 20.0 * sigma);
  }
  // The right convention stays accepted, its residual at the noise.
  const RecordingFitReport rep = fit(good);
  INFO(rep.alignment.inconsistency);
  CHECK(rep.result.accepted);
  CHECK(rep.alignment.inconsistency.empty());
  CHECK(rep.alignment.residual_per_axis_nT < 1.5 * sigma);
}

// --sigma-nT sets the residual gate's expectation as --help says: max(7.5, --sigma-nT).
TEST_CASE("magcal fit on a recording: --sigma-nT drives the expected residual", "[sim][cli]") {
  const ConstantFieldTruth t;
  const FieldRecording rec = simulate_constant_field(t, 1500, 150.0, 22);
  const nlohmann::json j = magcal_fit_json(
      rec, "--reference-magnitude " + std::to_string(t.f_enu_nT.norm()) + " --sigma-nT 150");
  REQUIRE_FALSE(j.is_discarded());
  INFO(j.dump());
  CHECK(j["verdict"] == "accepted");
  for (const auto& reason : j["rejection_reasons"])
    CHECK(reason.get<std::string>().find("residual") == std::string::npos);
}
