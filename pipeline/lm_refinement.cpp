#include "pipeline/lm_refinement.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include <Eigen/Dense>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/levenberg_marquardt.hpp"
#include "pipeline/outer_product_sum.hpp"
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

bool theta_positive_definite(const Vector9d& theta) {
  const Eigen::Matrix3d I_E = Eigen::Matrix3d::Identity() + unpack_symmetric(theta.tail<6>());
  return Eigen::LLT<Eigen::Matrix3d>(I_E).info() == Eigen::Success;
}

namespace {

// Passes over the samples (moments about the latest estimate) before a non-robust refinement
// is declared not converged.
constexpr int kMaxMomentPasses = 5;

// The samples as the scalar problem with NE model-extension and NT temperature columns (NX in
// all) sees them: the regressor row v_k (scalar_moments_cost), the weight w_k and the robust
// weights u_k.
template <int NE, int NT>
class ScalarProblem {
 public:
  static constexpr int NX = NE + NT;
  static constexpr int P = 9 + NX;
  static constexpr int N = 11 + NX;
  using VectorP = Eigen::Matrix<double, P, 1>;
  using MatrixP = Eigen::Matrix<double, P, P>;
  using VectorN = Eigen::Matrix<double, N, 1>;
  using MatrixN = Eigen::Matrix<double, N, N>;
  using Phi = std::vector<Vector6d>;

  ScalarProblem(const SampleSet& samples, const LmOptions& options, const Phi* phi)
      : samples_(samples),
        options_(options),
        phi_(phi),
        mu_(scalar_noise_mean(options.sigma_nT)),
        s2_(options.sigma_nT * options.sigma_nT) {
    if (options.robust) u_.assign(samples.size(), 1.0);
  }

  std::size_t size() const { return samples_.size(); }

  // v_k about the reference (moments_reference) and the total weight u_k w_k.
  VectorN row(std::size_t k, const VectorN& c_ref, double* weight) const {
    const CalibrationSample& s = samples_[k];
    const double h2 = s.h_body_nT.squaredNorm();
    VectorN v;
    v.template head<9>() = scalar_regressor(s.b_sensor_nT).transpose();
    v(9) = 1.0;
    v(10) = s.b_sensor_nT.squaredNorm() - h2 - mu_;
    if constexpr (NE > 0) v.template segment<NE>(11) = (*phi_)[k].template head<NE>();
    if constexpr (NT > 0) {
      v.template tail<NT>() = temperature_columns_at(s, options_.temperature_linearisation,
                                                     options_.reference_temperature_C);
    }
    v(10) = v.dot(c_ref);  // r_k at the reference (c_ref(10) = 1)
    if (options_.robust) {
      // Robust: |y_k|^2 = r_k + |h_k|^2 + mu at the reference estimate (estimation.md 2, second
      // line; |B|^2 if not positive), refreshed with every re-weighting: a spike in B then also
      // loses weight through its |y|^2, which the Huber weight alone does not give (measured:
      // 600 nT sensor with 3 G spikes, bias error 80 nT with |h|, 20 nT like this).
      double y2 = v(10) + h2 + mu_;
      if (!(y2 > 0.0)) y2 = s.b_sensor_nT.squaredNorm();
      *weight = u_[k] / (4.0 * s2_ * y2 + 6.0 * s2_ * s2_);
    } else {
      *weight = 1.0 / (4.0 * s2_ * h2 + 6.0 * s2_ * s2_);
    }
    return v;
  }

  // The reference x_ref of the moments (scalar_moments_cost) and c(x_ref) about zero.
  static bool reference(const VectorP& x_ref, MomentsReference<NX>* ref, VectorN* c_ref) {
    ref->x = x_ref;
    Vector9d gb;
    if (!residual_vector(x_ref, c_ref, &gb)) return false;
    ref->bsq = (*c_ref)(9);
    return true;
  }

  // M = sum u w v^T v about the reference (one pass). base: its leading 11 x 11 block, already
  // known about the same reference (no robust weights).
  MatrixN moments(const VectorN& c_ref, const Eigen::Matrix<double, 11, 11>* base = nullptr) const {
    if (NX > 0 && base && !options_.robust) {
      OuterProductSum<N, 11> sum;
      for (std::size_t k = 0; k < samples_.size(); ++k) {
        double w = 0.0;
        const VectorN v = row(k, c_ref, &w);
        sum.add(std::sqrt(w) * v);
      }
      MatrixN M = sum.sum();
      M.template topLeftCorner<11, 11>() = *base;
      return M;
    }
    OuterProductSum<N> sum;
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      double w = 0.0;
      const VectorN v = row(k, c_ref, &w);
      sum.add(std::sqrt(w) * v);
    }
    return sum.sum();
  }

  // c(x) about zero (v_k c = r_k with v_k(10) = z_k - mu_k) and the |b|^2 gradient at x; false
  // if I + E is singular.
  static bool residual_vector(const VectorP& x, VectorN* c, Vector9d* gb) {
    double bsq = 0.0;
    if (!bias_norm_squared(x.template head<9>(), &bsq, gb)) return false;
    c->template head<9>() = -x.template head<9>();
    (*c)(9) = bsq;
    (*c)(10) = 1.0;
    if constexpr (NX > 0) c->template tail<NX>() = -x.template tail<NX>();
    return true;
  }

  // Robust weights u_k at x (one pass); returns the number below 1.
  int update_robust_weights(const VectorP& x) {
    if (!options_.robust) return 0;
    VectorN c;
    Vector9d gb;
    if (!residual_vector(x, &c, &gb)) return 0;
    std::fill(u_.begin(), u_.end(), 1.0);
    abs_e_.resize(samples_.size());
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      double w = 0.0;
      const VectorN v = row(k, c, &w);  // v(10) = r_k at x; u = 1 here
      abs_e_[k] = u_[k] = std::abs(v(10)) * std::sqrt(w);
    }
    auto mid = abs_e_.begin() + static_cast<std::ptrdiff_t>(abs_e_.size() / 2);
    std::nth_element(abs_e_.begin(), mid, abs_e_.end());
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

  // Per-sample scores u w r J^T and normalised residuals sqrt(u w) r at x, in sample order
  // (HAC covariance; one pass).
  void scores(const VectorP& x, std::vector<VectorP>* scores, std::vector<double>* e) const {
    VectorN c = VectorN::Zero();
    Vector9d gb = Vector9d::Zero();
    residual_vector(x, &c, &gb);  // x is feasible here (checked by the caller)
    scores->resize(samples_.size());
    e->resize(samples_.size());
    for (std::size_t k = 0; k < samples_.size(); ++k) {
      double w = 0.0;
      const VectorN v = row(k, c, &w);
      const double r = v(10);
      VectorP J;  // dr/dx = v G
      J.template head<9>() = gb - v.template head<9>();
      if constexpr (NX > 0) J.template tail<NX>() = -v.template tail<NX>();
      (*scores)[k] = (w * r) * J;
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
  double s2_;
  std::vector<double> u_;
  std::vector<double> abs_e_;
  double scale_ = 1.0;
};

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

template <int NE, int NT>
LmResult refine(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options,
                const std::vector<Vector6d>* phi, const LmResult* base) {
  using Problem = ScalarProblem<NE, NT>;
  constexpr int NX = Problem::NX;
  constexpr int P = Problem::P;
  using VectorP = typename Problem::VectorP;
  using MatrixP = typename Problem::MatrixP;
  using VectorN = typename Problem::VectorN;
  using MatrixN = typename Problem::MatrixN;
  LmResult res;
  if (std::string err = check_inputs(samples, theta0, options, &res); !err.empty()) {
    res.message = err;
    return res;
  }

  VectorP x = VectorP::Zero();
  x.template head<9>() = theta0;
  if (!theta_positive_definite(theta0)) x.template segment<6>(3).setZero();  // fallback start

  Problem problem(samples, options, phi);
  LmDriverOptions driver;
  driver.max_iterations = options.max_iterations;
  driver.max_lambda_increases = options.max_lambda_increases;
  driver.initial_lambda = options.initial_lambda;
  driver.step_tolerance = options.tolerance;
  auto feasible = [](const VectorP& v) { return theta_positive_definite(v.template head<9>()); };

  // Without robust weights M depends on x only through its reference: one pass, then LM on M;
  // another pass about the result only when rounding kept LM from meeting the tolerance (the
  // moments lose precision far from their reference). Robust: IRLS, u at the current
  // estimate, LM on the moments with those u, until the Gauss–Newton decrement with the weights
  // of the estimate is below the tolerance.
  MomentsReference<NX> ref;
  VectorN c_ref;
  MatrixN M;
  int n_down = 0;
  const bool reuse_base = NX > 0 && base != nullptr && !options.robust;
  if (reuse_base) {
    x.template head<9>() = base->moments_reference;
    if constexpr (NX > 0) x.template tail<NX>().setZero();
  }
  auto prepare = [&](bool with_base) {
    n_down = problem.update_robust_weights(x);
    if (!problem.reference(x, &ref, &c_ref)) return false;
    M = problem.moments(c_ref, with_base ? &base->moments : nullptr);
    return true;
  };
  if (!prepare(reuse_base)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: I + E singular at the start";
    return res;
  }
  if (reuse_base) {  // the base's reference; the refinement starts from theta0
    x.template head<9>() = theta0;
    if (!theta_positive_definite(theta0)) x.template segment<6>(3).setZero();
  }
  const int max_passes = options.robust ? options.max_iterations : kMaxMomentPasses;
  for (int pass = 0; pass < max_passes; ++pass) {
    auto evaluate = [&M, &ref](const VectorP& v, double* cost, MatrixP* F, VectorP* g) {
      return scalar_moments_cost<NX>(M, v, cost, F, g, ref);
    };
    if (pass > 0) {
      if (!prepare(false)) break;
      double cost = 0.0;
      MatrixP F;
      VectorP g;
      if (evaluate(x, &cost, &F, &g) && gauss_newton_decrement<P>(F, g) < options.tolerance) {
        res.converged = true;
        break;
      }
    }
    // Robust: one LM iteration per re-weighting (as IRLS; a full solve with the weights of a
    // start far from the solution can settle on the outliers), the damping carried over.
    if (options.robust) driver.max_iterations = 1;
    const LmDriverResult<P> run = levenberg_marquardt<P>(evaluate, feasible, &x, driver);
    driver.initial_lambda = run.lambda;
    if (!run.evaluated) {
      res.status = LmStatus::kSingular;
      res.message = "refinement: non-finite cost";
      return res;
    }
    res.iterations += run.iterations;
    res.converged = run.converged && !options.robust;  // robust: until the weights at x agree
    if (res.converged) break;
    if (options.robust && run.iterations == 0) break;  // no step possible: not converged
  }
  if (!res.converged) prepare(false);  // weights and moments about the returned estimate

  // The undamped information at the solution, with the weights evaluated there.
  double chi2 = 0.0;
  MatrixP F;
  VectorP g;
  if (!scalar_moments_cost<NX>(M, x, &chi2, &F, &g, ref) || !std::isfinite(chi2)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: non-finite cost";
    return res;
  }
  res.n_downweighted = n_down;
  res.robust_scale = problem.scale();
  res.theta = x.template head<9>();
  if constexpr (NE > 0) res.extension = x.template segment<NE>(9);
  if constexpr (NT > 0) res.temperature_coefficient = x.template tail<NT>();
  res.cost = 0.5 * chi2;
  const VectorP d = F.diagonal();
  if (!(d.minCoeff() > 0.0)) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular";
    return res;
  }
  const VectorP s_inv = d.cwiseSqrt().cwiseInverse();
  const MatrixP Fs = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<MatrixP> eig(Fs);
  if (!(eig.eigenvalues()(0) > 1e-14 * eig.eigenvalues()(P - 1))) {
    res.status = LmStatus::kSingular;
    res.message = "refinement: information matrix is singular (geometry)";
    return res;
  }
  const MatrixP F_inv = s_inv.asDiagonal() * eig.eigenvectors() *
                        eig.eigenvalues().cwiseInverse().asDiagonal() *
                        eig.eigenvectors().transpose() * s_inv.asDiagonal();
  res.theta_covariance_white = F_inv.template topLeftCorner<9, 9>();
  res.theta_covariance = res.theta_covariance_white;
  if constexpr (NE > 0) res.extension_covariance = F_inv.template block<NE, NE>(9, 9);
  if constexpr (NT > 0) {
    res.temperature_covariance = F_inv.template bottomRightCorner<NT, NT>();
  }
  const double dof = static_cast<double>(samples.size()) - P;
  res.n_parameters = P;
  res.noise_scale = std::sqrt(chi2 / dof);
  if (options.robust) res.robust_weights = problem.robust_weights();
  if constexpr (NX == 0) {
    res.moments = M;
    res.moments_reference = ref.x;
  }
  {
    std::vector<VectorP> scores;
    std::vector<double> e;
    problem.scores(x, &scores, &e);
    res.residual_autocorrelation = lag1_autocorrelation(e);
    if (options.hac) {
      res.lag_window =
          bartlett_lag_window(res.residual_autocorrelation, static_cast<int>(samples.size()));
      // Small-sample correction n / (n - p), as for the reduced chi-square.
      const MatrixP omega =
          newey_west_meat<P>(scores, res.lag_window) * (static_cast<double>(samples.size()) / dof);
      const MatrixP hac_full = F_inv * omega * F_inv;
      const Matrix9d hac = hac_full.template topLeftCorner<9, 9>();
      res.theta_covariance = covariance_not_below(res.theta_covariance_white, hac);
      if constexpr (NE > 0) {
        const Matrix6d hac_extension = hac_full.template block<NE, NE>(9, 9);
        res.extension_covariance = covariance_not_below(res.extension_covariance, hac_extension);
      }
      if constexpr (NT > 0) {
        const Eigen::Matrix3d hac_temperature = hac_full.template bottomRightCorner<NT, NT>();
        res.temperature_covariance =
            covariance_not_below(res.temperature_covariance, hac_temperature);
      }
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

LmResult refine_lm(const SampleSet& samples, const Vector9d& theta0, const LmOptions& options,
                   const LmResult* base) {
  if (options.temperature_model) return refine<0, 3>(samples, theta0, options, nullptr, base);
  return refine<0, 0>(samples, theta0, options, nullptr, nullptr);
}

LmResult refine_lm_extended(const SampleSet& samples, const Vector9d& theta0,
                            const std::vector<Vector6d>& extension_regressors,
                            const LmOptions& options, const LmResult* base) {
  if (extension_regressors.size() != samples.size()) {
    LmResult res;
    res.message = "extension regressors: one row per sample required";
    return res;
  }
  if (options.temperature_model) {
    return refine<6, 3>(samples, theta0, options, &extension_regressors, base);
  }
  return refine<6, 0>(samples, theta0, options, &extension_regressors, base);
}

}  // namespace magcal
