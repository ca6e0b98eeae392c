#include "pipeline/filter_start.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Eigenvalues>

#include "pipeline/levenberg_marquardt.hpp"
#include "pipeline/lm_refinement.hpp"
#include "pipeline/parameter_recovery.hpp"
#include "pipeline/scaled_inverse.hpp"

namespace magcal {

namespace {

constexpr int kMaxLmIterations = 100;
constexpr int kMaxLambdaIncreases = 12;
constexpr double kStepTolerance = 1e-8;       // dtheta^T F dtheta, chi-square units
constexpr double kDecrementTolerance = 1e-6;  // g^T F^-1 g when no step lowers the cost
constexpr double kDegenerateRatio = 1e-3;     // smallest / next scaled eigenvalue
constexpr double kSingularRatio = 1e-14;      // smallest / largest scaled eigenvalue
constexpr int kMaxLineIterations = 30;

// Levenberg-Marquardt on the moments from theta (must make I + E positive definite).
bool refine_on_moments(const Matrix11d& M, Vector9d& theta, double& cost, int& iterations) {
  LmDriverOptions options;
  options.max_iterations = kMaxLmIterations;
  options.max_lambda_increases = kMaxLambdaIncreases;
  options.step_tolerance = kStepTolerance;
  options.decrement_tolerance = kDecrementTolerance;
  const LmDriverResult<9> run =
      levenberg_marquardt<9>([&M](const Vector9d& x, double* c, Matrix9d* F,
                                  Vector9d* g) { return scalar_moments_cost<0>(M, x, c, F, g); },
                             theta_positive_definite, &theta, options);
  iterations += run.iterations;
  cost = run.cost;
  return run.evaluated && run.converged;
}

// Degenerate linear system (constant reference magnitude): the point on the near-null line
// u_p + t d where the intercept equals |b(theta)|^2 (secant iterations inside the region where
// I + E is positive definite; the function is linear in t for noise-free data).
bool line_start(const Eigen::Matrix<double, 10, 1>& u_p, const Eigen::Matrix<double, 10, 1>& d,
                Vector9d* theta) {
  auto h = [&](double t, double* value) {
    const Eigen::Matrix<double, 10, 1> u = u_p + t * d;
    const Vector9d th = u.head<9>();
    double bsq = 0.0;
    if (!theta_positive_definite(th) || !bias_norm_squared(th, &bsq, nullptr)) return false;
    *value = u(9) - bsq;
    return std::isfinite(*value);
  };
  const Vector6d Ep = u_p.segment<6>(3), Ed = d.segment<6>(3);
  if (!(Ed.squaredNorm() > 0.0)) return false;
  double t0 = -Ep.dot(Ed) / Ed.squaredNorm();  // E closest to 0
  double t1 = t0 + 1e-3 / Ed.norm();
  double h0 = 0.0, h1 = 0.0;
  if (!h(t0, &h0) || !h(t1, &h1)) return false;
  for (int it = 0; it < kMaxLineIterations; ++it) {
    if (h1 == h0) break;
    const double t2 = t1 - h1 * (t1 - t0) / (h1 - h0);
    double h2 = 0.0;
    if (!std::isfinite(t2) || !h(t2, &h2)) return false;
    t0 = t1;
    h0 = h1;
    t1 = t2;
    h1 = h2;
    if (std::abs(t1 - t0) <= 1e-12 * (1.0 + std::abs(t1))) break;
  }
  *theta = (u_p + t1 * d).head<9>();
  return theta->allFinite();
}

}  // namespace

void ScalarMoments::add(const Eigen::Vector3d& B, double y, double w, ScalarLag1Moments* lag1) {
  Vector11d u;
  u << 2.0 * B(0), 2.0 * B(1), 2.0 * B(2), -B(0) * B(0), -B(1) * B(1), -B(2) * B(2),
      -2.0 * B(0) * B(1), -2.0 * B(0) * B(2), -2.0 * B(1) * B(2), 1.0, y;
  u *= std::sqrt(w);
  add_outer_product<11>(m, u);
  if (lag1) {
    int k = 0;
    if (n > 0) {
      for (int i = 0; i < 11; ++i) {
        for (int j = i; j < 11; ++j)
          lag1->m(k++) += 0.5 * (u(i) * lag1->previous(j) + u(j) * lag1->previous(i));
      }
    }
    lag1->previous = u;
  }
  ++n;
}

Matrix11d ScalarMoments::matrix() const {
  return symmetric_from_packed<11>(m);
}

bool ScalarMoments::operator==(const ScalarMoments& o) const {
  return m == o.m && n == o.n;
}

Matrix11d ScalarLag1Moments::matrix() const {
  return symmetric_from_packed<11>(m);
}

bool ScalarLag1Moments::operator==(const ScalarLag1Moments& o) const {
  return m == o.m && previous == o.previous;
}

bool moments_cost(const Matrix11d& M, const Vector9d& theta, double* cost, Matrix9d* info_theta,
                  Vector9d* gradient) {
  return scalar_moments_cost<0>(M, theta, cost, info_theta, gradient);
}

double moments_fisher_condition(const Matrix11d& M, const Vector9d& p) {
  const CalibrationParameters params = CalibrationParameters::from_packed(p);
  Matrix9d info;
  if (!moments_cost(M, theta_from_parameters(params), nullptr, &info, nullptr))
    return std::numeric_limits<double>::infinity();
  const Matrix9d J = theta_jacobian(params);
  double condition = std::numeric_limits<double>::infinity();
  scaled_inverse<9>(Matrix9d(J.transpose() * info * J), nullptr, &condition, kSingularRatio);
  return condition;
}

FilterStartResult solve_filter_start(const ScalarMoments& moments, const ScalarLag1Moments& lag1,
                                     const FilterStartOptions& options) {
  FilterStartResult r;
  if (moments.n < std::max(options.min_samples, 11)) return r;
  const Matrix11d M = moments.matrix();

  // Linear system y = [L, -1] u, u = [theta; |b|^2], in the diagonally scaled form.
  Eigen::Matrix<double, 10, 1> sign = Eigen::Matrix<double, 10, 1>::Ones();
  sign(9) = -1.0;
  const Eigen::Matrix<double, 10, 10> A =
      sign.asDiagonal() * M.topLeftCorner<10, 10>() * sign.asDiagonal();
  const Eigen::Matrix<double, 10, 1> rhs = sign.asDiagonal() * M.block<10, 1>(0, 10);
  Vector9d candidates[3];
  int n_candidates = 0;
  const Eigen::Matrix<double, 10, 1> dA = A.diagonal();
  if (dA.minCoeff() > 0.0 && dA.allFinite()) {
    const Eigen::Matrix<double, 10, 1> s_inv = dA.cwiseSqrt().cwiseInverse();
    const Eigen::Matrix<double, 10, 10> As = s_inv.asDiagonal() * A * s_inv.asDiagonal();
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 10, 10>> eig(As);
    const auto& lam = eig.eigenvalues();
    const auto& V = eig.eigenvectors();
    const Eigen::Matrix<double, 10, 1> bs = s_inv.asDiagonal() * rhs;
    if (lam(0) > kSingularRatio * lam(9)) {
      const Eigen::Matrix<double, 10, 1> us = V * (V.transpose() * bs).cwiseQuotient(lam).eval();
      candidates[n_candidates++] = (s_inv.asDiagonal() * us).head<9>();
    }
    if (lam(0) < kDegenerateRatio * lam(1) && lam(1) > kSingularRatio * lam(9)) {
      Eigen::Matrix<double, 10, 1> coef = V.transpose() * bs;
      coef(0) = 0.0;
      for (int i = 1; i < 10; ++i) coef(i) /= lam(i);
      const Eigen::Matrix<double, 10, 1> u_p = s_inv.asDiagonal() * (V * coef);
      const Eigen::Matrix<double, 10, 1> d = s_inv.asDiagonal() * V.col(0);
      Vector9d theta;
      if (line_start(u_p, d, &theta)) candidates[n_candidates++] = theta;
    }
  }
  candidates[n_candidates++] = Vector9d::Zero();

  double best_cost = std::numeric_limits<double>::infinity();
  Vector9d best = Vector9d::Zero();
  for (int i = 0; i < n_candidates; ++i) {
    Vector9d theta = candidates[i];
    if (!theta.allFinite()) continue;
    if (!theta_positive_definite(theta)) theta.tail<6>().setZero();
    double cost = 0.0;
    if (refine_on_moments(M, theta, cost, r.iterations) && cost < best_cost) {
      best_cost = cost;
      best = theta;
    }
  }
  if (!std::isfinite(best_cost)) {  // no estimate, hence no information at one
    r.status = FilterStartStatus::kNoSolution;
    r.fisher_condition = std::numeric_limits<double>::infinity();
    return r;
  }

  Matrix9d info;
  moments_cost(M, best, nullptr, &info, nullptr);
  Matrix9d cov_theta;
  double condition_theta = 0.0;
  if (!scaled_inverse<9>(info, &cov_theta, &condition_theta, kSingularRatio) ||
      !theta_positive_definite(best)) {
    r.status = FilterStartStatus::kUnobservable;
    r.fisher_condition = std::numeric_limits<double>::infinity();
    return r;
  }
  const RecoveryResult rec = recover_parameters(best, &cov_theta);
  if (!rec.ok()) {
    r.status = FilterStartStatus::kNoSolution;
    r.fisher_condition = std::numeric_limits<double>::infinity();
    return r;
  }
  r.p = rec.parameters.packed();
  r.fisher_condition = moments_fisher_condition(M, r.p);
  if (!(r.fisher_condition <= options.max_condition)) {
    r.status = FilterStartStatus::kUnobservable;
    return r;
  }
  const double dof = static_cast<double>(moments.n - 9);
  r.noise_scale2 = std::max(1.0, best_cost / dof);
  double bsq = 0.0;
  bias_norm_squared(best, &bsq, nullptr);
  Vector11d c;
  c << -best, bsq, 1.0;
  const double rho = best_cost > 0.0 ? c.dot(lag1.matrix() * c) / best_cost : 0.0;
  r.residual_autocorrelation = rho;
  if (options.correlation_inflation) {
    const double rc = std::clamp(rho, 0.0, options.max_correlation);
    r.inflation = (1.0 + rc) / (1.0 - rc);
  }
  r.covariance = rec.covariance * (r.noise_scale2 * r.inflation);
  r.status = FilterStartStatus::kOk;
  return r;
}

double start_precheck_condition(const ScalarMoments& moments) {
  using Vector10d = Eigen::Matrix<double, 10, 1>;
  using Matrix10d = Eigen::Matrix<double, 10, 10>;
  const Matrix11d M = moments.matrix();
  const Matrix10d A = M.topLeftCorner<10, 10>();
  const Vector10d d = A.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return std::numeric_limits<double>::infinity();
  const Vector10d s_inv = d.cwiseSqrt().cwiseInverse();
  const Matrix10d As = s_inv.asDiagonal() * A * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<Matrix10d> eig(As, Eigen::EigenvaluesOnly);
  const double second = eig.eigenvalues()(1);
  return second > 0.0 ? eig.eigenvalues()(9) / second : std::numeric_limits<double>::infinity();
}

}  // namespace magcal
