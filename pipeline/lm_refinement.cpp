#include "pipeline/lm_refinement.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include <Eigen/Dense>

#include "pipeline/hac_covariance.hpp"
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

// The unknowns: theta (9) and NX linear extension coefficients a (model extension columns
// phi_k, fixed per sample): r_k = z_k - mu - L_k theta + |b|^2 - phi_k a.
template <int NX>
struct Types {
  static constexpr int P = 9 + NX;
  using Vector = Eigen::Matrix<double, P, 1>;
  using Row = Eigen::Matrix<double, 1, P>;
  using Matrix = Eigen::Matrix<double, P, P>;
  using Extension = Eigen::Matrix<double, NX == 0 ? 1 : NX, 1>;
};

// Everything one pass over the samples at the current estimate produces.
template <int NX>
struct Accumulation {
  typename Types<NX>::Matrix F = Types<NX>::Matrix::Zero();  // sum w u J^T J
  typename Types<NX>::Vector g = Types<NX>::Vector::Zero();  // sum w u J^T r
  double cost = 0.0;                                         // 1/2 sum w u r^2
};

template <int NX>
class Problem {
 public:
  using T = Types<NX>;
  using Phi = std::vector<typename T::Extension>;

  Problem(const SampleSet& samples, const LmOptions& options, const Phi* phi)
      : samples_(samples), options_(options), phi_(phi), mu_(scalar_noise_mean(options.sigma_nT)) {
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

  // r_k and its Jacobian row at x = [theta; a] (gbt: the |b|^2 gradient at theta).
  double residual(std::size_t k, const RowVector9d& L, const typename T::Vector& x, double bsq,
                  const RowVector9d& gbt, typename T::Row* J) const {
    const CalibrationSample& s = samples_[k];
    double r = scalar_measurement(s.b_sensor_nT, s.h_body_nT.norm()) - mu_ -
               L.dot(x.template head<9>()) + bsq;
    if (J) J->template head<9>() = gbt - L;
    if constexpr (NX > 0) {
      const typename T::Extension& phi = (*phi_)[k];
      r -= phi.dot(x.template tail<NX>());
      if (J) J->template tail<NX>() = -phi.transpose();
    }
    return r;
  }

  // Robust weights u_k at x (stored in u_), returns the number below 1.
  int update_robust_weights(const typename T::Vector& x) {
    if (!options_.robust) return 0;
    const Vector9d theta = x.template head<9>();
    double bsq = 0.0;
    Vector9d gb;
    bias_norm_squared(theta, &bsq, &gb);
    std::vector<double> abs_e(samples_.size());
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      const RowVector9d L = scalar_regressor(samples_[k].b_sensor_nT);
      const double r = residual(k, L, x, bsq, gb.transpose(), nullptr);
      abs_e[k] = std::abs(r) * std::sqrt(weight(samples_[k].b_sensor_nT, L, theta, bsq));
      u_[k] = abs_e[k];
    }
    auto mid = abs_e.begin() + static_cast<std::ptrdiff_t>(abs_e.size() / 2);
    std::nth_element(abs_e.begin(), mid, abs_e.end());
    scale_ = std::max(1.0, 1.4826 * *mid);  // 1.4826 x median |e|: a robust sigma
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

  // F, g and cost at x with weights from x (and the current u_). When x_w is given, also the
  // cost at x with the weights of x_w (the LM acceptance test against the previous iterate),
  // so a trial and the next iteration's accumulation share one pass.
  bool accumulate(const typename T::Vector& x, Accumulation<NX>* acc,
                  const typename T::Vector* x_w = nullptr, double* cost_w = nullptr) const {
    const Vector9d theta = x.template head<9>();
    double bsq = 0.0, bsq_w = 0.0;
    Vector9d gb;
    if (!bias_norm_squared(theta, &bsq, &gb)) return false;
    Vector9d theta_w = theta;
    if (x_w) {
      theta_w = x_w->template head<9>();
      if (!bias_norm_squared(theta_w, &bsq_w, nullptr)) return false;
    }
    const RowVector9d gbt = gb.transpose();
    typename T::Matrix F = T::Matrix::Zero();
    typename T::Vector g = T::Vector::Zero();
    typename T::Row J;
    double cost = 0.0, cost_old = 0.0;
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      const Eigen::Vector3d& B = samples_[k].b_sensor_nT;
      const RowVector9d L = scalar_regressor(B);
      const double u = options_.robust ? u_[k] : 1.0;
      const double w = u * weight(B, L, theta, bsq);
      const double r = residual(k, L, x, bsq, gbt, &J);
      F.noalias() += (J.transpose() * w) * J;  // fixed-size, vectorised
      g.noalias() += (w * r) * J.transpose();
      cost += 0.5 * w * r * r;
      if (x_w) cost_old += 0.5 * u * weight(B, L, theta_w, bsq_w) * r * r;
    }
    acc->F = F;
    acc->g = g;
    acc->cost = cost;
    if (cost_w) *cost_w = cost_old;
    return std::isfinite(cost) && std::isfinite(cost_old);
  }

  // Per-sample scores u_k = w_k r_k J_k^T (robust weight included) and normalised residuals
  // e_k = sqrt(w_k) r_k at x, in sample order (HAC covariance).
  void scores(const typename T::Vector& x, std::vector<typename T::Vector>* u,
              std::vector<double>* e) const {
    const Vector9d theta = x.template head<9>();
    double bsq = 0.0;
    Vector9d gb;
    bias_norm_squared(theta, &bsq, &gb);
    const RowVector9d gbt = gb.transpose();
    typename T::Row J;
    u->resize(samples_.size());
    e->resize(samples_.size());
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      const Eigen::Vector3d& B = samples_[k].b_sensor_nT;
      const RowVector9d L = scalar_regressor(B);
      const double uk = options_.robust ? u_[k] : 1.0;
      const double w = uk * weight(B, L, theta, bsq);
      const double r = residual(k, L, x, bsq, gbt, &J);
      (*u)[k] = (w * r) * J.transpose();
      (*e)[k] = std::sqrt(w) * r;
    }
  }

  const std::vector<double>& robust_weights() const { return u_; }
  double scale() const { return scale_; }

 private:
  const SampleSet& samples_;
  const LmOptions& options_;
  const Phi* phi_;
  double mu_;
  std::vector<double> u_;
  double scale_ = 1.0;
};

// Solves (F + lambda diag F) x = rhs in the diagonally scaled form; false if singular.
template <int P>
bool solve_scaled(const Eigen::Matrix<double, P, P>& F, double lambda,
                  const Eigen::Matrix<double, P, 1>& rhs, Eigen::Matrix<double, P, 1>* x) {
  using V = Eigen::Matrix<double, P, 1>;
  const V d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return false;
  const V s_inv = d.cwiseSqrt().cwiseInverse();
  Eigen::Matrix<double, P, P> A = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  A.diagonal().array() += lambda;
  const Eigen::LDLT<Eigen::Matrix<double, P, P>> ldlt(A);
  if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().minCoeff() > 1e-15)) return false;
  *x = s_inv.asDiagonal() * ldlt.solve(s_inv.asDiagonal() * rhs);
  return x->allFinite();
}

std::string check_inputs(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options,
                         LmResult* res) {
  if (std::string err = options.validate(); !err.empty()) return "invalid options: " + err;
  if (static_cast<int>(samples.size()) < options.min_samples) {
    res->status = LmStatus::kTooFewSamples;
    return "too few samples: " + std::to_string(samples.size()) + " < " +
           std::to_string(options.min_samples);
  }
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const double h = samples[k].h_body_nT.norm();
    if (!samples[k].b_sensor_nT.allFinite() || !std::isfinite(h) || !(h > 0.0)) {
      return "sample " + std::to_string(k) + ": non-finite field or |h| <= 0";
    }
  }
  if (!theta0.allFinite()) return "start theta is not finite";
  return {};
}

template <int NX>
LmResult refine(const SampleSet& samples, const Vector9d& theta0,
                const typename Types<NX>::Extension& a0, const LmOptions& options,
                const typename Problem<NX>::Phi* phi) {
  using T = Types<NX>;
  constexpr int P = T::P;
  LmResult res;
  if (std::string err = check_inputs(samples, theta0, options, &res); !err.empty()) {
    res.message = err;
    return res;
  }

  typename T::Vector x;
  x.template head<9>() = theta0;
  if constexpr (NX > 0) x.template tail<NX>() = a0;
  if (!is_positive_definite(theta0)) x.template segment<6>(3).setZero();  // fallback start

  Problem<NX> problem(samples, options, phi);
  double lambda = options.initial_lambda;
  Accumulation<NX> acc;  // always at x, with weights (and u) evaluated at x
  int n_down = problem.update_robust_weights(x);
  if (!problem.accumulate(x, &acc)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: non-finite cost";
    return res;
  }
  for (int iter = 0; iter < options.max_iterations; ++iter) {
    // Converged when even the full Gauss-Newton step would gain less than the tolerance
    // (g^T F^-1 g = its step^T F step): checked before trying steps, because at the minimum no
    // trial lowers the cost (rounding) and each failed trial costs a pass over the samples.
    if (typename T::Vector gn;
        iter > 0 && solve_scaled<P>(acc.F, 0.0, acc.g, &gn) && acc.g.dot(gn) < options.tolerance) {
      res.converged = true;
      break;
    }
    res.iterations = iter + 1;
    bool accepted = false;
    double step_chi2 = 0.0;
    for (int trial = 0; trial < options.max_lambda_increases; ++trial) {
      typename T::Vector step;
      if (!solve_scaled<P>(acc.F, lambda, -acc.g, &step)) {
        lambda = std::max(lambda * 10.0, 1e-6);
        continue;
      }
      const typename T::Vector candidate = x + step;
      Accumulation<NX> next;
      double cost_fixed_weights = 0.0;
      if (is_positive_definite(candidate.template head<9>()) &&
          problem.accumulate(candidate, &next, &x, &cost_fixed_weights) &&
          cost_fixed_weights <= acc.cost) {
        step_chi2 = step.dot(acc.F * step);
        x = candidate;
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
      typename T::Vector gn;
      res.converged = solve_scaled<P>(acc.F, 0.0, acc.g, &gn) && acc.g.dot(gn) < 1e-6;
      break;
    }
    if (options.robust) {  // IRLS: new u at the new iterate, then F and g with it
      n_down = problem.update_robust_weights(x);
      if (!problem.accumulate(x, &acc)) {
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
  res.theta = x.template head<9>();
  if constexpr (NX > 0) res.extension = x.template tail<NX>();
  res.cost = acc.cost;
  const typename T::Vector d = acc.F.diagonal();
  if (!(d.minCoeff() > 0.0)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular";
    return res;
  }
  const typename T::Vector s_inv = d.cwiseSqrt().cwiseInverse();
  const typename T::Matrix Fs = s_inv.asDiagonal() * acc.F * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<typename T::Matrix> eig(Fs);
  if (!(eig.eigenvalues()(0) > 1e-14 * eig.eigenvalues()(P - 1))) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular (geometry)";
    return res;
  }
  const typename T::Matrix F_inv = s_inv.asDiagonal() * eig.eigenvectors() *
                                   eig.eigenvalues().cwiseInverse().asDiagonal() *
                                   eig.eigenvectors().transpose() * s_inv.asDiagonal();
  res.theta_covariance_white = F_inv.template topLeftCorner<9, 9>();
  res.theta_covariance = res.theta_covariance_white;
  if constexpr (NX > 0) res.extension_covariance = F_inv.template bottomRightCorner<NX, NX>();
  const double dof = static_cast<double>(samples.size()) - P;
  res.n_parameters = P;
  res.noise_scale = std::sqrt(2.0 * acc.cost / dof);
  if (options.robust) res.robust_weights = problem.robust_weights();
  {
    std::vector<typename T::Vector> scores;
    std::vector<double> e;
    problem.scores(x, &scores, &e);
    res.residual_autocorrelation = lag1_autocorrelation(e);
    if (options.hac) {
      res.lag_window =
          bartlett_lag_window(res.residual_autocorrelation, static_cast<int>(samples.size()));
      // Small-sample correction n / (n - p), as for the reduced chi-square.
      const typename T::Matrix omega =
          newey_west_meat<P>(scores, res.lag_window) * (static_cast<double>(samples.size()) / dof);
      const typename T::Matrix hac = F_inv * omega * F_inv;
      res.theta_covariance = covariance_not_below(res.theta_covariance_white,
                                                  Matrix9d(hac.template topLeftCorner<9, 9>()));
    }
  }
  if (res.converged) {
    res.status = LmStatus::kOk;
  } else {
    res.status = LmStatus::kNotConverged;
    res.message =
        "refinement did not converge in " + std::to_string(options.max_iterations) + " iterations";
  }
  return res;
}

}  // namespace

LmResult refine_lm(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options) {
  return refine<0>(samples, theta0, Types<0>::Extension::Zero(), options, nullptr);
}

LmResult refine_lm_extended(const SampleSet& samples, const Vector9d& theta0,
                            const std::vector<Vector6d>& extension_regressors,
                            const LmOptions& options) {
  if (extension_regressors.size() != samples.size()) {
    LmResult res;
    res.message = "extension regressors: one row per sample required";
    return res;
  }
  return refine<6>(samples, theta0, Vector6d::Zero(), options, &extension_regressors);
}

}  // namespace magcal
