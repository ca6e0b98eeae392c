// The one Levenberg–Marquardt driver of the pipeline (estimation.md 2b; the paper's TWOSTEP
// step 2): the batch refinement (lm_refinement.cpp) and the online filters' start from data
// (filter_start.cpp) both run it on the weighted moments of their samples.
//
// The problem is two callables:
//   evaluate(x, &cost, &F, &g) -> bool   cost = sum w r^2 (chi-square units), Gauss–Newton
//                                        information F = sum w J^T J and gradient g = sum w J^T r
//                                        at x (P-vectors, PxP); false when x has no cost
//   feasible(x) -> bool                  x is admissible (I + E positive definite)
// Step: (F + lambda diag F) dx = -g, solved in the diagonally scaled form by Cholesky; a step
// that does not raise the cost is accepted (lambda / 10), else lambda x 10, at most
// max_lambda_increases trials per iteration.
// Converged when, before a step, the Gauss–Newton decrement g^T F^-1 g (the chi-square the full
// step would still gain) is below step_tolerance (checked first: at the minimum no trial lowers
// the cost to rounding), when an accepted step has dx^T F dx < step_tolerance, or when no step
// lowers the cost and the decrement is below decrement_tolerance.
// Fixed-size Eigen types only: no allocation.
#pragma once

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Core>

namespace magcal {

struct LmDriverOptions {
  int max_iterations = 50;
  int max_lambda_increases = 12;  // per iteration, before giving up on lowering the cost
  double initial_lambda = 1e-3;
  double step_tolerance = 1e-10;      // chi-square units (dx^T F dx, g^T F^-1 g)
  double decrement_tolerance = 1e-6;  // g^T F^-1 g when no step lowers the cost
};

template <int P>
struct LmDriverResult {
  bool evaluated = false;  // the start had a cost (else nothing below is set)
  bool converged = false;
  int iterations = 0;   // iterations that tried a step
  double cost = 0.0;    // at the returned x
  double lambda = 0.0;  // damping at the end (a continuation may start from it)
  Eigen::Matrix<double, P, P> information = Eigen::Matrix<double, P, P>::Zero();  // F at x
  Eigen::Matrix<double, P, 1> gradient = Eigen::Matrix<double, P, 1>::Zero();     // g at x
};

// Solves (F + lambda diag F) x = rhs in the diagonally scaled form (Cholesky); false when F has
// a non-positive diagonal or the damped matrix is not positive definite.
template <int P>
bool solve_damped_scaled(const Eigen::Matrix<double, P, P>& F, double lambda,
                         const Eigen::Matrix<double, P, 1>& rhs, Eigen::Matrix<double, P, 1>* x) {
  using V = Eigen::Matrix<double, P, 1>;
  const V d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return false;
  const V s_inv = d.cwiseSqrt().cwiseInverse();
  Eigen::Matrix<double, P, P> A = s_inv.asDiagonal() * F * s_inv.asDiagonal();
  A.diagonal().array() += lambda;  // the scaled diag(F) is the identity
  const Eigen::LLT<Eigen::Matrix<double, P, P>> llt(A);
  if (llt.info() != Eigen::Success) return false;
  *x = s_inv.asDiagonal() * llt.solve(s_inv.asDiagonal() * rhs);
  return x->allFinite();
}

// Gauss–Newton decrement g^T F^-1 g (+inf when F is singular).
template <int P>
double gauss_newton_decrement(const Eigen::Matrix<double, P, P>& F,
                              const Eigen::Matrix<double, P, 1>& g) {
  Eigen::Matrix<double, P, 1> step;
  if (!solve_damped_scaled<P>(F, 0.0, g, &step)) return HUGE_VAL;
  return g.dot(step);
}

// Refines x in place (x must be feasible).
template <int P, class Evaluate, class Feasible>
LmDriverResult<P> levenberg_marquardt(const Evaluate& evaluate, const Feasible& feasible,
                                      Eigen::Matrix<double, P, 1>* x,
                                      const LmDriverOptions& options) {
  using V = Eigen::Matrix<double, P, 1>;
  using M = Eigen::Matrix<double, P, P>;
  LmDriverResult<P> res;
  if (!evaluate(*x, &res.cost, &res.information, &res.gradient) || !std::isfinite(res.cost)) {
    return res;
  }
  res.evaluated = true;
  double& lambda = res.lambda;
  lambda = options.initial_lambda;
  for (int iter = 0; iter < options.max_iterations; ++iter) {
    if (iter > 0 &&
        gauss_newton_decrement<P>(res.information, res.gradient) < options.step_tolerance) {
      res.converged = true;
      return res;
    }
    res.iterations = iter + 1;
    bool accepted = false;
    double step_chi2 = 0.0;
    for (int trial = 0; trial < options.max_lambda_increases; ++trial) {
      V step;
      if (!solve_damped_scaled<P>(res.information, lambda, V(-res.gradient), &step)) {
        lambda = std::max(lambda * 10.0, 1e-6);
        continue;
      }
      const V candidate = *x + step;
      double cost = 0.0;
      M F;
      V g;
      if (feasible(candidate) && evaluate(candidate, &cost, &F, &g) && std::isfinite(cost) &&
          cost <= res.cost) {
        step_chi2 = step.dot(res.information * step);
        *x = candidate;
        res.cost = cost;
        res.information = F;
        res.gradient = g;
        lambda = std::max(lambda * 0.1, 1e-12);
        accepted = true;
        break;
      }
      lambda = std::max(lambda * 10.0, 1e-6);
    }
    if (!accepted) {
      res.converged =
          gauss_newton_decrement<P>(res.information, res.gradient) < options.decrement_tolerance;
      return res;
    }
    if (step_chi2 < options.step_tolerance) {
      res.converged = true;
      return res;
    }
  }
  return res;
}

}  // namespace magcal
