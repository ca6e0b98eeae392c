#include "pipeline/lm_refinement.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include <Eigen/Dense>

#include "pipeline/scalar_measurement.hpp"

namespace magcal {

const char* to_string(LmStatus s) {
  switch (s) {
    case LmStatus::kOk:
      return "ok";
    case LmStatus::kNotConverged:
      return "not_converged";
    case LmStatus::kNotPositiveDefinite:
      return "not_positive_definite";
    case LmStatus::kSingular:
      return "singular";
    case LmStatus::kTooFewSamples:
      return "too_few_samples";
    case LmStatus::kInvalidInput:
      return "invalid_input";
  }
  return "invalid_input";
}

std::string LmOptions::validate() const {
  if (!(sigma_nT > 0.0) || !std::isfinite(sigma_nT)) return "sigma_nT must be positive";
  if (max_iterations < 1) return "max_iterations must be at least 1";
  if (!(tolerance > 0.0)) return "tolerance must be positive";
  if (!(initial_lambda >= 0.0)) return "initial_lambda must be >= 0";
  if (max_lambda_increases < 1) return "max_lambda_increases must be at least 1";
  if (!(huber_k > 0.0)) return "huber_k must be positive";
  if (min_samples < 10) return "min_samples must be at least 10";
  return {};
}

bool bias_norm_squared(const Vector9d& theta, double* bsq, Vector9d* gradient) {
  const Eigen::Matrix3d I_E = Eigen::Matrix3d::Identity() + unpack_symmetric(theta.tail<6>());
  const Eigen::Vector3d c = theta.head<3>();
  const Eigen::LDLT<Eigen::Matrix3d> ldlt(I_E);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().cwiseAbs().minCoeff() > 1e-12)) {
    return false;
  }
  const Eigen::Vector3d x = ldlt.solve(c);
  if (bsq) *bsq = c.dot(x);
  if (gradient) {
    *gradient << 2.0 * x, -x(0) * x(0), -x(1) * x(1), -x(2) * x(2), -2.0 * x(0) * x(1),
        -2.0 * x(0) * x(2), -2.0 * x(1) * x(2);
  }
  return true;
}

double lm_residual(const Vector9d& theta, const Eigen::Vector3d& B, double z_minus_mu) {
  double bsq = 0.0;
  if (!bias_norm_squared(theta, &bsq, nullptr)) return std::numeric_limits<double>::quiet_NaN();
  return z_minus_mu - scalar_regressor(B).dot(theta) + bsq;
}

RowVector9d lm_residual_jacobian(const Vector9d& theta, const Eigen::Vector3d& B) {
  Vector9d g;
  if (!bias_norm_squared(theta, nullptr, &g)) {
    return RowVector9d::Constant(std::numeric_limits<double>::quiet_NaN());
  }
  return -scalar_regressor(B) + g.transpose();
}

namespace {

bool is_positive_definite(const Vector9d& theta) {
  const Eigen::Matrix3d I_E = Eigen::Matrix3d::Identity() + unpack_symmetric(theta.tail<6>());
  return Eigen::LLT<Eigen::Matrix3d>(I_E).info() == Eigen::Success;
}

// Everything one pass over the samples at the current estimate produces.
struct Accumulation {
  Matrix9d F = Matrix9d::Zero();  // sum w u J^T J
  Vector9d g = Vector9d::Zero();  // sum w u J^T r
  double cost = 0.0;              // 1/2 sum w u r^2
  int n_downweighted = 0;
};

class Problem {
 public:
  Problem(const SampleSet& samples, const LmOptions& options)
      : samples_(samples), options_(options), mu_(scalar_noise_mean(options.sigma_nT)) {
    if (options.robust) u_.resize(samples.size());
  }

  // w_k from the estimate theta_w (|y|^2 = |B|^2 - L theta + |b|^2; |B|^2 if that is not
  // positive, e.g. far from the solution).
  double weight(const Eigen::Vector3d& B, const RowVector9d& L, const Vector9d& theta_w,
                double bsq_w) const {
    double y2 = B.squaredNorm() - L.dot(theta_w) + bsq_w;
    if (!(y2 > 0.0)) y2 = B.squaredNorm();
    const double s2 = options_.sigma_nT * options_.sigma_nT;
    return 1.0 / (4.0 * s2 * y2 + 6.0 * s2 * s2);
  }

  double z_minus_mu(const CalibrationSample& s) const {
    return scalar_measurement(s.b_sensor_nT, s.h_body_nT.norm()) - mu_;
  }

  // Robust weights u_k at theta (stored in u_), returns the number below 1.
  int update_robust_weights(const Vector9d& theta, double bsq) {
    if (!options_.robust) return 0;
    std::vector<double> abs_e(samples_.size());
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      const CalibrationSample& s = samples_[k];
      const RowVector9d L = scalar_regressor(s.b_sensor_nT);
      const double r = z_minus_mu(s) - L.dot(theta) + bsq;
      abs_e[k] = std::abs(r) * std::sqrt(weight(s.b_sensor_nT, L, theta, bsq));
      u_[k] = abs_e[k];
    }
    auto mid = abs_e.begin() + static_cast<std::ptrdiff_t>(abs_e.size() / 2);
    std::nth_element(abs_e.begin(), mid, abs_e.end());
    scale_ = std::max(1.0, 1.4826 * *mid);
    const double threshold = options_.huber_k * scale_;
    int n = 0;
    for (double& u : u_) {
      if (u > threshold) {
        u = threshold / u;
        ++n;
      } else {
        u = 1.0;
      }
    }
    return n;
  }

  // F, g and cost at theta with weights from theta (and the current u_). When theta_w is given,
  // also the cost at theta with the weights of theta_w (the LM acceptance test against the
  // previous iterate), so a trial and the next iteration's accumulation share one pass.
  bool accumulate(const Vector9d& theta, Accumulation* acc, const Vector9d* theta_w = nullptr,
                  double* cost_w = nullptr) const {
    double bsq = 0.0, bsq_w = 0.0;
    Vector9d gb;
    if (!bias_norm_squared(theta, &bsq, &gb)) return false;
    if (theta_w && !bias_norm_squared(*theta_w, &bsq_w, nullptr)) return false;
    const RowVector9d gbt = gb.transpose();
    Matrix9d F = Matrix9d::Zero();
    Vector9d g = Vector9d::Zero();
    double cost = 0.0, cost_old = 0.0;
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      const CalibrationSample& s = samples_[k];
      const RowVector9d L = scalar_regressor(s.b_sensor_nT);
      const double u = options_.robust ? u_[k] : 1.0;
      const double w = u * weight(s.b_sensor_nT, L, theta, bsq);
      const double r = z_minus_mu(s) - L.dot(theta) + bsq;
      const RowVector9d J = gbt - L;
      F.noalias() += (J.transpose() * w) * J;  // fixed-size 9x9, vectorised
      g.noalias() += (w * r) * J.transpose();
      cost += 0.5 * w * r * r;
      if (theta_w) cost_old += 0.5 * u * weight(s.b_sensor_nT, L, *theta_w, bsq_w) * r * r;
    }
    acc->F = F;
    acc->g = g;
    acc->cost = cost;
    if (cost_w) *cost_w = cost_old;
    return std::isfinite(cost) && std::isfinite(cost_old);
  }

  double scale() const { return scale_; }

 private:
  const SampleSet& samples_;
  const LmOptions& options_;
  double mu_;
  std::vector<double> u_;
  double scale_ = 1.0;
};

// Solves (F + lambda diag F) x = rhs in the diagonally scaled form; false if singular.
bool solve_scaled(const Matrix9d& F, double lambda, const Vector9d& rhs, Vector9d* x) {
  const Vector9d d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return false;
  const Vector9d s_inv = d.cwiseSqrt().cwiseInverse();
  Matrix9d A = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  A.diagonal().array() += lambda;
  const Eigen::LDLT<Matrix9d> ldlt(A);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 1e-15)) return false;
  *x = s_inv.asDiagonal() * ldlt.solve(s_inv.asDiagonal() * rhs);
  return x->allFinite();
}

}  // namespace

LmResult refine_lm(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options) {
  LmResult res;
  if (std::string err = options.validate(); !err.empty()) {
    res.message = "invalid options: " + err;
    return res;
  }
  if (static_cast<int>(samples.size()) < options.min_samples) {
    res.status = LmStatus::kTooFewSamples;
    res.message = "too few samples: " + std::to_string(samples.size()) + " < " +
                  std::to_string(options.min_samples);
    return res;
  }
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const double h = samples[k].h_body_nT.norm();
    if (!samples[k].b_sensor_nT.allFinite() || !std::isfinite(h) || !(h > 0.0)) {
      res.message = "sample " + std::to_string(k) + ": non-finite field or |h| <= 0";
      return res;
    }
  }
  if (!theta0.allFinite()) {
    res.message = "start theta is not finite";
    return res;
  }

  Vector9d theta = theta0;
  if (!is_positive_definite(theta)) theta.tail<6>().setZero();  // documented fallback start

  Problem problem(samples, options);
  double lambda = options.initial_lambda;
  Accumulation acc;  // always at theta, with weights (and u) evaluated at theta
  double bsq = 0.0;
  bias_norm_squared(theta, &bsq, nullptr);
  int n_down = problem.update_robust_weights(theta, bsq);
  if (!problem.accumulate(theta, &acc)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: non-finite cost";
    return res;
  }
  for (int iter = 0; iter < options.max_iterations; ++iter) {
    res.iterations = iter + 1;
    bool accepted = false;
    double step_chi2 = 0.0;
    for (int trial = 0; trial < options.max_lambda_increases; ++trial) {
      Vector9d step;
      if (!solve_scaled(acc.F, lambda, -acc.g, &step)) {
        lambda = std::max(lambda * 10.0, 1e-6);
        continue;
      }
      const Vector9d candidate = theta + step;
      Accumulation next;
      double cost_fixed_weights = 0.0;
      if (is_positive_definite(candidate) &&
          problem.accumulate(candidate, &next, &theta, &cost_fixed_weights) &&
          cost_fixed_weights <= acc.cost) {
        step_chi2 = step.dot(acc.F * step);
        theta = candidate;
        acc = next;
        lambda = std::max(lambda * 0.1, 1e-12);
        accepted = true;
        break;
      }
      lambda = std::max(lambda * 10.0, 1e-6);
    }
    if (!accepted) {
      // No step lowers the cost: converged if the Gauss-Newton decrement g^T F^-1 g (the
      // chi-square still to gain) is negligible, i.e. we sit at the minimum to rounding.
      Vector9d gn;
      res.converged = solve_scaled(acc.F, 0.0, acc.g, &gn) && acc.g.dot(gn) < 1e-6;
      break;
    }
    if (options.robust) {  // IRLS: new u at the new iterate, then F and g with it
      bias_norm_squared(theta, &bsq, nullptr);
      n_down = problem.update_robust_weights(theta, bsq);
      if (!problem.accumulate(theta, &acc)) {
        res.status = LmStatus::kSingular;
        res.message = "refinement: non-finite cost";
        return res;
      }
    }
    if (step_chi2 < options.tolerance) {
      res.converged = true;
      break;
    }
  }

  // acc holds the undamped information at the solution with the weights evaluated there.
  res.n_downweighted = n_down;
  res.robust_scale = problem.scale();
  res.theta = theta;
  res.cost = acc.cost;
  const Vector9d d = acc.F.diagonal();
  if (!(d.minCoeff() > 0.0)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular";
    return res;
  }
  const Vector9d s_inv = d.cwiseSqrt().cwiseInverse();
  const Matrix9d Fs = s_inv.asDiagonal() * acc.F * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Matrix9d> eig(Fs);
  if (!(eig.eigenvalues()(0) > 1e-14 * eig.eigenvalues()(8))) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular (geometry)";
    return res;
  }
  res.theta_covariance = s_inv.asDiagonal() * eig.eigenvectors() *
                         eig.eigenvalues().cwiseInverse().asDiagonal() *
                         eig.eigenvectors().transpose() * s_inv.asDiagonal();
  if (res.converged) {
    res.status = LmStatus::kOk;
  } else {
    res.status = LmStatus::kNotConverged;
    res.message =
        "refinement did not converge in " + std::to_string(options.max_iterations) + " iterations";
  }
  return res;
}

}  // namespace magcal
