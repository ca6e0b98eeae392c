// Acceptance gates. Definitions and defaults in the header.
#include "pipeline/acceptance_gates.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <Eigen/Dense>

namespace magcal {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

template <typename... Args>
std::string format(const char* fmt, Args... args) {
  char buf[512];
  std::snprintf(buf, sizeof(buf), fmt, args...);
  return buf;
}

// Upper standard-normal quantile z with P(Z > z) = p, by bisection on erfc (pure, no tables).
double normal_upper_quantile(double p) {
  double lo = -40.0, hi = 40.0;
  for (int i = 0; i < 200; ++i) {
    const double mid = 0.5 * (lo + hi);
    if (0.5 * std::erfc(mid / std::sqrt(2.0)) > p)
      lo = mid;
    else
      hi = mid;
  }
  return 0.5 * (lo + hi);
}

const char* const kAxis[3] = {"x", "y", "z"};
const char* const kDName[6] = {"D11", "D22", "D33", "D12", "D13", "D23"};

void residual_gate(const CalibrationResult& r, const GateOptions& o, GateVerdict& v) {
  const double rms = r.residual_rms_nT;
  if (!(rms >= 0.0)) {
    v.skipped.push_back("residual");
    return;
  }
  if (o.residual_test == GateOptions::ResidualTest::kFactor) {
    if (rms > o.residual_factor * o.expected_residual_nT)
      v.reasons.push_back(format("residual_rms %.1f nT > %g x expected %.1f nT", rms,
                                 o.residual_factor, o.expected_residual_nT));
    return;
  }
  const double dof = static_cast<double>(r.n_samples) - 9.0;
  if (!(dof >= 1.0)) {
    v.skipped.push_back("residual");
    return;
  }
  const double chi2 = r.n_samples * rms * rms / (o.expected_residual_nT * o.expected_residual_nT);
  const double limit = chi_square_upper_quantile(dof, o.residual_tail_probability);
  if (chi2 > limit)
    v.reasons.push_back(
        format("residual_chi2 %.1f > %.1f (rms %.1f nT, expected %.1f nT, dof %.0f, p %g)", chi2,
               limit, rms, o.expected_residual_nT, dof, o.residual_tail_probability));
}

void observability_gate(const CalibrationResult& r, const GateInputs& in, const GateOptions& o,
                        GateVerdict& v) {
  const double cond = r.fisher_condition_number;
  if (cond > 0.0 && std::isfinite(cond)) {
    if (cond > o.max_fisher_condition)
      v.reasons.push_back(format("fisher_condition %.3g > max %.3g", cond, o.max_fisher_condition));
  } else if (std::isinf(cond)) {
    v.reasons.push_back(format("fisher_condition inf > max %.3g", o.max_fisher_condition));
  } else {
    v.skipped.push_back("fisher_condition");
  }
  if (o.min_fisher_eigenvalue > 0.0) {
    if (std::isnan(in.fisher_min_eigenvalue))
      v.skipped.push_back("fisher_min_eigenvalue");
    else if (in.fisher_min_eigenvalue < o.min_fisher_eigenvalue)
      v.reasons.push_back(format("fisher_min_eigenvalue %.3g < min %.3g", in.fisher_min_eigenvalue,
                                 o.min_fisher_eigenvalue));
  }
}

void coverage_gate(const GateInputs& in, const GateOptions& o, GateVerdict& v) {
  if (std::isnan(in.min_coverage_eigenvalue)) {
    v.skipped.push_back("coverage");
    return;
  }
  if (in.min_coverage_eigenvalue < o.min_coverage_eigenvalue)
    v.reasons.push_back(format("coverage_min_eigenvalue %.4f < min %.4f",
                               in.min_coverage_eigenvalue, o.min_coverage_eigenvalue));
}

void bounds_gate(const CalibrationResult& r, const GateOptions& o, GateVerdict& v) {
  const Vector9d p = r.parameters.packed();
  for (int i = 0; i < 3; ++i) {
    // !(x <= max) also rejects NaN.
    if (!(std::abs(p(i)) <= o.max_bias_nT))
      v.reasons.push_back(
          format("bias_bound %s |b| %.1f nT > %.1f nT", kAxis[i], std::abs(p(i)), o.max_bias_nT));
  }
  for (int j = 0; j < 6; ++j) {
    const double value = std::abs(p(3 + j));
    const bool diagonal = j < 3;
    const double limit = diagonal ? o.max_scale : o.max_nonorthogonality;
    if (!(value <= limit))
      v.reasons.push_back(format("%s %s |D| %.4f > %.4f",
                                 diagonal ? "scale_bound" : "nonorthogonality_bound", kDName[j],
                                 value, limit));
  }
  if (r.has_alignment && !(r.alignment.residual_fraction <= o.max_alignment_residual_fraction)) {
    v.reasons.push_back(
        format("alignment_mismatch: after the best rotation the calibrated and reference "
               "directions differ by %.0f %% of |h| (> %.0f %%): check the sensor axes' signs and "
               "order (a left-handed frame) and the attitude",
               100.0 * r.alignment.residual_fraction, 100.0 * o.max_alignment_residual_fraction));
  }
  if (r.has_alignment && !r.alignment.inconsistency.empty())
    v.reasons.push_back("alignment_inconsistent: " + r.alignment.inconsistency);
}

// d^T (P1 + P2)^-1 d for one block of the parameter difference; NaN when P1 + P2 is not
// positive definite (solved in the diagonally scaled form: nT and dimensionless D).
template <int N>
double change_chi_square(const Eigen::Matrix<double, N, 1>& d,
                         const Eigen::Matrix<double, N, N>& P) {
  const Eigen::Matrix<double, N, 1> diag = P.diagonal();
  if (!(diag.minCoeff() > 0.0) || !P.allFinite()) return kNaN;
  const Eigen::Matrix<double, N, 1> inv = diag.cwiseSqrt().cwiseInverse();
  const Eigen::Matrix<double, N, N> Ps = inv.asDiagonal() * P * inv.asDiagonal();
  const Eigen::LDLT<Eigen::Matrix<double, N, N>> ldlt(Ps);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 1e-12)) return kNaN;
  const Eigen::Matrix<double, N, 1> ds = inv.cwiseProduct(d);
  return ds.dot(ldlt.solve(ds));
}

void change_gate(const CalibrationResult& r, const GateInputs& in, const GateOptions& o,
                 GateVerdict& v) {
  if (in.previous_accepted == nullptr) {
    v.skipped.push_back("change");
    return;
  }
  const CalibrationResult& prev = *in.previous_accepted;
  const Vector9d d = r.parameters.packed() - prev.parameters.packed();
  const Matrix9d P = r.covariance + prev.covariance;
  // Bias (3) and D (6) separately: a jump in either is a different physical event.
  const Eigen::Vector3d db = d.head<3>();
  const Vector6d dD = d.tail<6>();
  const bool bias_below_floor = db.cwiseAbs().maxCoeff() <= o.bias_change_floor_nT;
  const bool D_below_floor = dD.cwiseAbs().maxCoeff() <= o.D_change_floor;
  if (!bias_below_floor) {
    const double chi2 = change_chi_square<3>(db, P.topLeftCorner<3, 3>());
    const double limit = chi_square_upper_quantile(3.0, o.change_tail_probability);
    if (!(chi2 <= limit))
      v.reasons.push_back(format(
          "bias_change chi2 %.1f > %.1f (dof 3, p %g; change %.1f %.1f "
          "%.1f nT, floor %.1f nT)",
          chi2, limit, o.change_tail_probability, db(0), db(1), db(2), o.bias_change_floor_nT));
  }
  if (!D_below_floor) {
    const double chi2 = change_chi_square<6>(dD, P.bottomRightCorner<6, 6>());
    const double limit = chi_square_upper_quantile(6.0, o.change_tail_probability);
    if (!(chi2 <= limit)) {
      int worst = 0;
      dD.cwiseAbs().maxCoeff(&worst);
      v.reasons.push_back(format(
          "D_change chi2 %.1f > %.1f (dof 6, p %g; largest %s %.5f, floor "
          "%.5f)",
          chi2, limit, o.change_tail_probability, kDName[worst], dD(worst), o.D_change_floor));
    }
  }
}

void outlier_gate(const GateInputs& in, GateVerdict& v) {
  const GateInputs::Outliers& o = in.outliers;
  if (o.count <= 0) return;
  v.reasons.push_back(
      format("outliers: %d samples' %s lie more than %.0f robust sigmas from the median (the "
             "largest, %s, %.4g nT): the fit is pulled by them; a robust fit (magcal fit --robust, "
             "[refit] robust = true) leaves them out",
             o.count, o.raw ? "uncalibrated residuals |B| - |h|" : "residuals", o.robust_sigmas,
             sample_label(static_cast<std::size_t>(o.largest_sample), o.largest_utime).c_str(),
             o.largest_residual_nT));
}

void unmodelled_gate(const GateInputs& in, GateVerdict& v) {
  if (!in.unmodelled_effects) return;
  v.reasons.push_back(
      "centered solution: the residuals show sensor effects it does not model (BIC prefers the "
      "nonlinearity/hysteresis extension), which bias its D beyond its sigmas: use twostep");
}

}  // namespace

std::string GateOptions::validate() const {
  if (!(expected_residual_nT > 0.0)) return "gates expected_residual_nT must be > 0";
  if (!(residual_factor > 0.0)) return "gates residual_factor must be > 0";
  if (!(residual_tail_probability > 0.0 && residual_tail_probability < 1.0))
    return "gates residual_tail_probability must be in (0, 1)";
  if (!(max_fisher_condition >= 1.0)) return "gates max_fisher_condition must be >= 1";
  if (!(min_fisher_eigenvalue >= 0.0)) return "gates min_fisher_eigenvalue must be >= 0";
  if (!(min_coverage_eigenvalue >= 0.0 && min_coverage_eigenvalue <= 1.0 / 3.0))
    return "gates min_coverage_eigenvalue must be in [0, 1/3]";
  if (!(max_bias_nT > 0.0) || !(max_scale > 0.0) || !(max_nonorthogonality > 0.0))
    return "gates parameter bounds must be > 0";
  if (!(change_tail_probability > 0.0 && change_tail_probability < 1.0) ||
      !(bias_change_floor_nT >= 0.0) || !(D_change_floor >= 0.0))
    return "gates change_tail_probability must be in (0, 1), floors >= 0";
  return {};
}

double chi_square_upper_quantile(double dof, double tail_probability) {
  if (!(dof > 0.0) || !(tail_probability > 0.0 && tail_probability < 1.0)) return kNaN;
  // Wilson–Hilferty: (X/k)^(1/3) ~ N(1 - 2/(9k), 2/(9k)).
  const double a = 2.0 / (9.0 * dof);
  const double c = 1.0 - a + normal_upper_quantile(tail_probability) * std::sqrt(a);
  return dof * c * c * c;
}

double ar1_variance_factor(double rho, double max_rho) {
  const double r = std::clamp(std::isfinite(rho) ? rho : 0.0, 0.0, max_rho);
  return (1.0 + r) / (1.0 - r);
}

GateVerdict evaluate_gates(const CalibrationResult& result, const GateInputs& inputs,
                           const GateOptions& options) {
  GateVerdict v;
  if (options.residual_enabled) residual_gate(result, options, v);
  if (options.observability_enabled) observability_gate(result, inputs, options, v);
  if (options.coverage_enabled) coverage_gate(inputs, options, v);
  if (options.bounds_enabled) bounds_gate(result, options, v);
  if (options.change_enabled) change_gate(result, inputs, options, v);
  if (options.outliers_enabled) outlier_gate(inputs, v);
  if (options.unmodelled_enabled) unmodelled_gate(inputs, v);
  v.accepted = v.reasons.empty();
  return v;
}

void apply_verdict(CalibrationResult& result, const GateVerdict& verdict) {
  result.accepted = verdict.accepted;
  result.rejection_reasons = verdict.reasons;
  if (!verdict.accepted && result.status == CalibrationStatus::kOk)
    result.status = CalibrationStatus::kRejected;
}

void reject_unless_ok(const CalibrationResult& result, GateVerdict& verdict) {
  if (result.status == CalibrationStatus::kOk) return;
  verdict.accepted = false;
  verdict.reasons.insert(verdict.reasons.begin(),
                         std::string(to_string(result.status)) +
                             (result.message.empty() ? "" : ": " + result.message));
}

Eigen::Vector3d direction_coverage_eigenvalues(const SampleSet& samples) {
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  int n = 0;
  for (const auto& s : samples) {
    const double norm = s.b_sensor_nT.norm();
    if (!std::isfinite(norm) || norm <= 0.0) continue;
    const Eigen::Vector3d d = s.b_sensor_nT / norm;
    scatter.noalias() += d * d.transpose();
    ++n;
  }
  if (n == 0) return Eigen::Vector3d::Constant(kNaN);
  return Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(scatter / n, Eigen::EigenvaluesOnly)
      .eigenvalues();
}

}  // namespace magcal
