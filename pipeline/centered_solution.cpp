#include "pipeline/centered_solution.hpp"

#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include <Eigen/Dense>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/outer_product_sum.hpp"
#include "pipeline/scalar_measurement.hpp"

namespace magcal {

const char* to_string(CenteredStatus s) {
  switch (s) {
    case CenteredStatus::kOk:
      return "ok";
    case CenteredStatus::kNotPositiveDefinite:
      return "not_positive_definite";
    case CenteredStatus::kSingular:
      return "singular";
    case CenteredStatus::kTooFewSamples:
      return "too_few_samples";
    case CenteredStatus::kInvalidInput:
      return "invalid_input";
  }
  return "invalid_input";
}

std::string CenteredOptions::validate() const {
  if (!(sigma_nT > 0.0) || !std::isfinite(sigma_nT)) return "sigma_nT must be positive";
  if (min_samples < 10) return "min_samples must be at least 10";
  if (!(max_condition > 1.0)) return "max_condition must exceed 1";
  return {};
}

namespace {

// With NT temperature columns (0 or 4) appended to L_k: unknowns [theta; a].
template <int NT>
CenteredResult centered(const SampleSet& samples, const CenteredOptions& options,
                        const CalibrationParameters* weight_parameters) {
  constexpr int P = 9 + NT;
  using RowP = Eigen::Matrix<double, 1, P>;
  using VectorP = Eigen::Matrix<double, P, 1>;
  using MatrixP = Eigen::Matrix<double, P, P>;
  auto regressor = [&](const CalibrationSample& s) {
    RowP L;
    L.template head<9>() = scalar_regressor(s.b_sensor_nT);
    if constexpr (NT > 0) {
      L.template tail<NT>() =
          temperature_columns_centered(s, options.reference_temperature_C).transpose();
    }
    return L;
  };
  CenteredResult r;
  r.n_samples = static_cast<int>(samples.size());
  const double sigma = options.sigma_nT;
  const double mu = scalar_noise_mean(sigma);  // constant: cancels, kept for the formula
  auto weight = [&](const Eigen::Vector3d& B) {
    const Eigen::Vector3d y = weight_parameters ? weight_parameters->apply(B) : B;
    return 1.0 / scalar_noise_variance(y, sigma);
  };

  // Pass 1: weighted means.
  double sum_w = 0.0, sum_wz = 0.0;
  RowP sum_wL = RowP::Zero();
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    const double h = s.h_body_nT.norm();
    if (!s.b_sensor_nT.allFinite() || !std::isfinite(h) || !(h > 0.0)) {
      r.status = CenteredStatus::kInvalidInput;
      r.message = "sample " + std::to_string(k) + ": non-finite field or |h| <= 0";
      return r;
    }
    const double w = weight(s.b_sensor_nT);
    sum_w += w;
    sum_wz += w * (scalar_measurement(s.b_sensor_nT, h) - mu);
    sum_wL.noalias() += w * regressor(s);
  }
  const double z_bar = sum_wz / sum_w;
  const RowP L_bar = sum_wL / sum_w;

  // Pass 2: centered normal equations.
  // [F g; g^T .] = sum w [Lc zc]^T [Lc zc], one blocked outer-product sum.
  OuterProductSum<P + 1> normal;
  for (const CalibrationSample& s : samples) {
    const double w = weight(s.b_sensor_nT);
    Eigen::Matrix<double, P + 1, 1> row;
    row.template head<P>() = (regressor(s) - L_bar).transpose();
    row(P) = scalar_measurement(s.b_sensor_nT, s.h_body_nT.norm()) - mu - z_bar;
    normal.add(std::sqrt(w) * row);
  }
  const Eigen::Matrix<double, P + 1, P + 1> normal_sum = normal.sum();
  const MatrixP F = normal_sum.template topLeftCorner<P, P>();
  const VectorP g = normal_sum.template block<P, 1>(0, P);

  // Scaled solve: F_s = S^-1 F S^-1.
  const VectorP d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) {
    r.status = CenteredStatus::kSingular;
    r.message = "centered normal matrix is singular (a regressor does not vary)";
    return r;
  }
  const VectorP s_inv = d.cwiseSqrt().cwiseInverse();
  const MatrixP Fs = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<MatrixP> eig(Fs);
  const double lmin = eig.eigenvalues()(0), lmax = eig.eigenvalues()(P - 1);
  r.condition_number = lmin > 0.0 ? lmax / lmin : std::numeric_limits<double>::infinity();
  if (!(r.condition_number < options.max_condition)) {
    r.status = CenteredStatus::kSingular;
    char buf[128];
    std::snprintf(buf, sizeof buf,
                  "centered normal matrix is singular (scaled condition number %.3g): the field "
                  "direction does not vary enough",
                  r.condition_number);
    r.message = buf;
    return r;
  }
  const MatrixP Fs_inv = eig.eigenvectors() * eig.eigenvalues().cwiseInverse().asDiagonal() *
                         eig.eigenvectors().transpose();
  const MatrixP F_inv = s_inv.asDiagonal() * Fs_inv * s_inv.asDiagonal();
  MatrixP covariance = F_inv;
  const VectorP x = F_inv * g;

  if (options.residual_covariance) {
    // Pass 3: scores and normalised residuals at theta.
    std::vector<VectorP> scores(samples.size());
    std::vector<double> e(samples.size());
    double chi2 = 0.0;
    for (std::size_t k = 0; k < samples.size(); ++k) {
      const CalibrationSample& s = samples[k];
      const double w = weight(s.b_sensor_nT);
      const RowP Lc = regressor(s) - L_bar;
      const double residual =
          scalar_measurement(s.b_sensor_nT, s.h_body_nT.norm()) - mu - z_bar - Lc.dot(x);
      scores[k] = (w * residual) * Lc.transpose();
      e[k] = std::sqrt(w) * residual;
      chi2 += w * residual * residual;
    }
    const double n = static_cast<double>(samples.size());
    const double dof = n - (P + 1.0);  // the parameters and the eliminated mean
    r.chi2 = chi2;
    r.noise_scale = std::sqrt(chi2 / dof);
    r.residual_autocorrelation = lag1_autocorrelation(e);
    r.lag_window = bartlett_lag_window(r.residual_autocorrelation, r.n_samples);
    const MatrixP hac = F_inv * newey_west_meat<P>(scores, r.lag_window) * F_inv * (n / dof);
    covariance = covariance_not_below(F_inv, hac);
  }
  r.theta = x.template head<9>();
  r.theta_covariance = covariance.template topLeftCorner<9, 9>();
  r.theta_covariance_white = F_inv.template topLeftCorner<9, 9>();
  if constexpr (NT > 0) {
    r.temperature_terms = x.template tail<NT>();
    r.temperature_covariance = covariance.template bottomRightCorner<NT, NT>();
  }

  const Eigen::Matrix3d I_E = Eigen::Matrix3d::Identity() + unpack_symmetric(r.theta.tail<6>());
  const Eigen::Vector3d s_IE =
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(I_E, Eigen::EigenvaluesOnly).eigenvalues();
  if (!r.theta.allFinite()) {
    r.status = CenteredStatus::kSingular;
    r.message = "centered solution is not finite";
    return r;
  }
  if (!(s_IE.minCoeff() > 0.0)) {
    r.status = CenteredStatus::kNotPositiveDefinite;
    r.message = "centered solution: I + E is not positive definite";
    return r;
  }
  r.status = CenteredStatus::kOk;
  return r;
}

}  // namespace

CenteredResult centered_solution(const SampleSet& samples, const CenteredOptions& options,
                                 const CalibrationParameters* weight_parameters) {
  CenteredResult r;
  if (std::string err = options.validate(); !err.empty()) {
    r.message = "invalid options: " + err;
    return r;
  }
  r.n_samples = static_cast<int>(samples.size());
  if (r.n_samples < options.min_samples) {
    r.status = CenteredStatus::kTooFewSamples;
    r.message = "too few samples: " + std::to_string(r.n_samples) + " < " +
                std::to_string(options.min_samples);
    return r;
  }
  if (options.temperature_model) return centered<4>(samples, options, weight_parameters);
  return centered<0>(samples, options, weight_parameters);
}

}  // namespace magcal
