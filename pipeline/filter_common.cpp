#include "pipeline/filter_common.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "pipeline/scalar_measurement.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {

constexpr double kSecondsPerHour = 3600.0;
constexpr double kMicrosecondsPerSecond = 1e6;
// Covariance guard: diagonal jitter relative to each variance, then an eigenvalue floor relative
// to the largest eigenvalue of the diagonally scaled (correlation-like) matrix.
constexpr double kRelativeJitter = 1e-12;
constexpr double kRelativeEigenFloor = 1e-14;
constexpr double kTinyVariance = 1e-300;

bool is_finite(const Eigen::Vector3d& v) {
  return v.allFinite();
}

}  // namespace

std::string FilterOptions::validate() const {
  if (!(sigma_nT > 0.0) || !std::isfinite(sigma_nT)) return "sigma_nT must be > 0";
  if (!process_noise_per_sqrt_hour.allFinite() || (process_noise_per_sqrt_hour.array() < 0).any())
    return "process noise must be finite and >= 0";
  if (!(initial_bias_sigma_nT > 0.0) || !std::isfinite(initial_bias_sigma_nT))
    return "initial_bias_sigma_nT must be > 0";
  if (!(initial_D_sigma > 0.0) || !std::isfinite(initial_D_sigma))
    return "initial_D_sigma must be > 0";
  if (std::isnan(gate_nis)) return "gate_nis must not be NaN";
  if (nis_window < 1) return "nis_window must be >= 1";
  if (!(nis_inconsistent_mean > 1.0)) return "nis_inconsistent_mean must be > 1";
  if (!(inflation_factor >= 1.0) || !std::isfinite(inflation_factor))
    return "inflation_factor must be >= 1";
  if (!(converged_bias_sigma_nT > 0.0)) return "converged_bias_sigma_nT must be > 0";
  return {};
}

Matrix9d FilterOptions::initial_covariance() const {
  Vector9d d;
  d.head<3>().setConstant(initial_bias_sigma_nT * initial_bias_sigma_nT);
  d.tail<6>().setConstant(initial_D_sigma * initial_D_sigma);
  return d.asDiagonal();
}

bool FilterState::operator==(const FilterState& o) const {
  return x == o.x && P == o.P && initialized == o.initialized && has_time == o.has_time &&
         consistent == o.consistent && first_utime == o.first_utime && last_utime == o.last_utime &&
         converged_since_utime == o.converged_since_utime && n_accepted == o.n_accepted &&
         n_rejected_invalid == o.n_rejected_invalid && n_rejected_gate == o.n_rejected_gate &&
         n_inconsistency_events == o.n_inconsistency_events &&
         n_covariance_repairs == o.n_covariance_repairs && nis_window_sum == o.nis_window_sum &&
         nis_window_count == o.nis_window_count && last_window_mean_nis == o.last_window_mean_nis;
}

const char* to_string(FilterUpdateStatus s) {
  switch (s) {
    case FilterUpdateStatus::kAccepted:
      return "accepted";
    case FilterUpdateStatus::kRejectedInvalid:
      return "rejected_invalid";
    case FilterUpdateStatus::kRejectedGate:
      return "rejected_gate";
    case FilterUpdateStatus::kRejectedNumerical:
      return "rejected_numerical";
  }
  return "rejected_invalid";
}

Vector9d process_noise_diagonal(const Vector9d& q_per_sqrt_hour, double dt_s) {
  if (!(dt_s > 0.0)) return Vector9d::Zero();
  return q_per_sqrt_hour.cwiseAbs2() * (dt_s / kSecondsPerHour);
}

CovarianceGuard guard_covariance(Matrix9d& P, Matrix9d& L) {
  if (!P.allFinite()) return CovarianceGuard::kNonFinite;
  P = 0.5 * (P + P.transpose()).eval();
  Eigen::LLT<Matrix9d> llt(P);
  if (llt.info() == Eigen::Success) {
    L = llt.matrixL();
    if ((L.diagonal().array() > 0.0).all()) return CovarianceGuard::kOk;
  }

  // Jitter: lifts a matrix that is PSD up to round-off.
  Matrix9d Pj = P;
  const Vector9d d = P.diagonal().cwiseAbs().cwiseMax(kTinyVariance);
  Pj.diagonal() += kRelativeJitter * d;
  llt.compute(Pj);
  if (llt.info() == Eigen::Success) {
    L = llt.matrixL();
    if ((L.diagonal().array() > 0.0).all()) {
      P = Pj;
      return CovarianceGuard::kRepaired;
    }
  }

  // Eigenvalue clamp on the scaled matrix, so nT^2 and dimensionless variances are comparable.
  const Vector9d s = d.cwiseSqrt();
  const Vector9d s_inv = s.cwiseInverse();
  const Matrix9d Ps = s_inv.asDiagonal() * P * s_inv.asDiagonal();
  Eigen::SelfAdjointEigenSolver<Matrix9d> eig(Ps);
  Vector9d lambda = eig.eigenvalues();
  const double floor = std::max(lambda.maxCoeff(), 1.0) * kRelativeEigenFloor;
  lambda = lambda.cwiseMax(floor);
  const Matrix9d V = eig.eigenvectors();
  P = s.asDiagonal() * (V * lambda.asDiagonal() * V.transpose()) * s.asDiagonal();
  P = 0.5 * (P + P.transpose()).eval();
  llt.compute(P);
  L = llt.matrixL();
  return CovarianceGuard::kRepaired;
}

void ScalarFilterBase::initialize(const Vector9d& x0, const Matrix9d& P0) {
  state_ = FilterState{};
  state_.x = x0;
  state_.P = 0.5 * (P0 + P0.transpose());
  state_.initialized = true;
  update_convergence_time();
}

void ScalarFilterBase::reanchor(const Vector9d& x, const Matrix9d& P) {
  state_.x = x;
  state_.P = 0.5 * (P + P.transpose());
  state_.initialized = true;
  state_.consistent = true;
  state_.nis_window_sum = 0.0;
  state_.nis_window_count = 0;
  state_.converged_since_utime = -1;
  update_convergence_time();
}

void ScalarFilterBase::reset() {
  state_ = FilterState{};
}

bool ScalarFilterBase::converged() const {
  return state_.initialized && state_.consistent &&
         (bias_sigma_nT().array() < options_.converged_bias_sigma_nT).all();
}

CalibrationResult ScalarFilterBase::snapshot() const {
  CalibrationResult r;
  r.method = method_;
  r.utime = state_.last_utime;
  r.window_start_utime = state_.first_utime;
  r.window_end_utime = state_.last_utime;
  r.n_samples = static_cast<int>(state_.n_accepted);
  r.parameters = parameters();
  r.covariance = state_.P;
  r.iterations = static_cast<int>(state_.n_accepted);
  r.converged = converged();
  if (!state_.initialized) {
    r.status = CalibrationStatus::kFailed;
    r.message = "no valid sample yet";
  } else if (!state_.consistent) {
    r.status = CalibrationStatus::kNotConverged;
    r.message = "inconsistent innovations (mean NIS " +
                std::to_string(state_.last_window_mean_nis) + "), covariance re-opened";
  } else if (!r.converged) {
    r.status = CalibrationStatus::kNotConverged;
    r.message = "bias 1-sigma above " + std::to_string(options_.converged_bias_sigma_nT) + " nT";
  } else {
    r.status = CalibrationStatus::kOk;
  }
  return r;
}

bool ScalarFilterBase::begin_update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT,
                                    int64_t utime) {
  if (!is_finite(b_sensor_nT) || !std::isfinite(h_norm_nT) || !(h_norm_nT > 0.0)) {
    ++state_.n_rejected_invalid;
    return false;
  }
  if (!state_.initialized) {
    state_.x.setZero();
    if (options_.cold_start == FilterOptions::ColdStart::kFirstSampleScale &&
        b_sensor_nT.norm() > 0.0) {
      state_.x.segment<3>(3).setConstant(h_norm_nT / b_sensor_nT.norm() - 1.0);
    }
    state_.P = options_.initial_covariance();
    state_.initialized = true;
    state_.has_time = true;
    state_.first_utime = utime;
    state_.last_utime = utime;
    return true;
  }
  if (!state_.has_time) {  // first sample after initialize(): no prediction
    state_.has_time = true;
    state_.first_utime = utime;
    state_.last_utime = utime;
    return true;
  }
  if (utime > state_.last_utime) {
    const double dt_s =
        static_cast<double>(saturating_sub(utime, state_.last_utime)) / kMicrosecondsPerSecond;
    state_.P.diagonal() += process_noise_diagonal(options_.process_noise_per_sqrt_hour, dt_s);
    state_.last_utime = utime;
  }
  return true;
}

void ScalarFilterBase::measurement(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT, double& y,
                                   double& R) const {
  y = scalar_measurement(b_sensor_nT, h_norm_nT) - scalar_noise_mean(options_.sigma_nT);
  R = scalar_noise_variance(parameters().apply(b_sensor_nT), options_.sigma_nT);
}

bool ScalarFilterBase::gate(FilterUpdate& u) {
  u.nis = u.innovation_nT2 * u.innovation_nT2 / u.innovation_variance_nT4;
  if (options_.gate_nis > 0.0 && u.nis > options_.gate_nis) {
    ++state_.n_rejected_gate;
    u.status = FilterUpdateStatus::kRejectedGate;
    monitor(u);
    return false;
  }
  return true;
}

void ScalarFilterBase::commit_posterior(FilterUpdate& u, const Vector9d& x_new,
                                        const Matrix9d& P_new) {
  if (!x_new.allFinite() || !P_new.allFinite()) {
    ++state_.n_rejected_invalid;
    u.status = FilterUpdateStatus::kRejectedNumerical;
    return;
  }
  state_.x = x_new;
  state_.P = P_new;
  finish_accepted(u);
}

void ScalarFilterBase::finish_accepted(FilterUpdate& u) {
  state_.P = 0.5 * (state_.P + state_.P.transpose()).eval();
  ++state_.n_accepted;
  u.status = FilterUpdateStatus::kAccepted;
  monitor(u);
  update_convergence_time();
}

void ScalarFilterBase::monitor(FilterUpdate& u) {
  // Gated samples enter clipped to the gate: many of them still trip the monitor (a filter that
  // rejects everything is not consistent), one spike does not.
  const double nis = options_.gate_nis > 0.0 ? std::min(u.nis, options_.gate_nis) : u.nis;
  state_.nis_window_sum += nis;
  if (++state_.nis_window_count < options_.nis_window) return;

  const double mean = state_.nis_window_sum / state_.nis_window_count;
  state_.last_window_mean_nis = mean;
  state_.nis_window_sum = 0.0;
  state_.nis_window_count = 0;
  state_.consistent = mean <= options_.nis_inconsistent_mean;
  if (state_.consistent) return;

  ++state_.n_inconsistency_events;
  u.inconsistency_event = true;
  const Matrix9d P0 = options_.initial_covariance();
  if (options_.consistency_action == FilterOptions::ConsistencyAction::kReseed) {
    state_.P = P0;
  } else {
    state_.P *= options_.inflation_factor;
    // Cap each variance at its cold-start value with a congruence (keeps P positive definite).
    Vector9d scale;
    for (int i = 0; i < 9; ++i)
      scale(i) = state_.P(i, i) > P0(i, i) ? std::sqrt(P0(i, i) / state_.P(i, i)) : 1.0;
    state_.P = scale.asDiagonal() * state_.P * scale.asDiagonal();
  }
  update_convergence_time();
}

void ScalarFilterBase::update_convergence_time() {
  if (converged()) {
    if (state_.converged_since_utime < 0) state_.converged_since_utime = state_.last_utime;
  } else {
    state_.converged_since_utime = -1;
  }
}

}  // namespace magcal
