#include "pipeline/filter_common.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/LU>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/hac_covariance.hpp"
#include "pipeline/parameter_recovery.hpp"
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
// Start attempts regardless of the pre-check at n = this x start_attempt_every x 2^k.
constexpr int64_t kUnconditionalAttemptMultiple = 16;
// Gauss-Newton steps of a block's bias (linear in c but for |b|^2: a few steps converge).
constexpr int kBlockBiasIterations = 4;
// Blocks before the bias trend is tested (its standard error has n - 2 degrees of freedom).
constexpr int kBiasMotionMinBlocks = 6;
constexpr int kBiasMotionFloorMinBlocks = 4;  // two degrees of freedom for the trend's scatter
// Step of the central differences of a block's bias in D (dimensionless): the bias moves by
// ~|B| x step = ~0.5 nT, far above the solve's round-off, far below its curvature in D.
constexpr double kBlockBiasDStep = 1e-5;

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
  if (start.min_samples < 11) return "start min_samples must be >= 11";
  if (!(start.max_condition > 1.0)) return "start max_condition must be > 1";
  if (!(start.max_correlation >= 0.0 && start.max_correlation < 1.0))
    return "start max_correlation must be in [0, 1)";
  if (start_attempt_every < 1) return "start_attempt_every must be >= 1";
  if (!(start_attempt_gap_fraction > 0.0 && start_attempt_gap_fraction <= 1.0))
    return "start_attempt_gap_fraction must be in (0, 1]";
  if (!(start.precheck_margin >= 1.0)) return "start precheck_margin must be >= 1";
  if (!(noise_adaptation_samples >= 1.0) || !std::isfinite(noise_adaptation_samples))
    return "noise_adaptation_samples must be >= 1";
  if (!(max_fisher_condition > 1.0)) return "max_fisher_condition must be > 1";
  if (fisher_every < 1) return "fisher_every must be >= 1";
  if (std::isnan(bias_motion_block_hours)) return "bias_motion_block_hours must not be NaN";
  if (!(bias_motion_chi2 >= 0.0)) return "bias_motion_chi2 must be >= 0";
  if (!(bias_floor_rate_sigmas >= 0.0) || !std::isfinite(bias_floor_rate_sigmas))
    return "bias_floor_rate_sigmas must be finite and >= 0";
  if (!(bias_random_walk_floor_cap_nT_per_sqrt_hour >= 0.0) ||
      !std::isfinite(bias_random_walk_floor_cap_nT_per_sqrt_hour))
    return "bias_random_walk_floor_cap_nT_per_sqrt_hour must be finite and >= 0";
  return {};
}

Matrix9d FilterOptions::initial_covariance() const {
  Vector9d d;
  d.head<3>().setConstant(initial_bias_sigma_nT * initial_bias_sigma_nT);
  d.tail<6>().setConstant(initial_D_sigma * initial_D_sigma);
  return d.asDiagonal();
}

bool BiasBlockStart::operator==(const BiasBlockStart& o) const {
  return m == o.m && n == o.n && utime == o.utime;
}

bool FilterState::operator==(const FilterState& o) const {
  return x == o.x && S == o.S && initialized == o.initialized && has_time == o.has_time &&
         consistent == o.consistent && first_utime == o.first_utime && last_utime == o.last_utime &&
         converged_since_utime == o.converged_since_utime && n_accepted == o.n_accepted &&
         n_rejected_invalid == o.n_rejected_invalid && n_rejected_gate == o.n_rejected_gate &&
         n_inconsistency_events == o.n_inconsistency_events &&
         n_covariance_repairs == o.n_covariance_repairs && nis_window_sum == o.nis_window_sum &&
         nis_window_count == o.nis_window_count && last_window_mean_nis == o.last_window_mean_nis &&
         noise_scale2 == o.noise_scale2 && innovation_c0 == o.innovation_c0 &&
         innovation_c1 == o.innovation_c1 &&
         previous_normalised_innovation == o.previous_normalised_innovation &&
         has_previous_innovation == o.has_previous_innovation && moments == o.moments &&
         fisher_condition == o.fisher_condition && samples_since_fisher == o.samples_since_fisher &&
         period_start_utime == o.period_start_utime && period_n == o.period_n &&
         period_residual_sum2_nT2 == o.period_residual_sum2_nT2 &&
         period_nis_sum == o.period_nis_sum &&
         anchor_information_and_meat == o.anchor_information_and_meat &&
         score_block == o.score_block && score_block_n == o.score_block_n &&
         score_blocks == o.score_blocks && model_error_covariance == o.model_error_covariance &&
         model_error_known == o.model_error_known && lag1_or_block == o.lag1_or_block &&
         bias_motion_n == o.bias_motion_n && bias_motion_sum_t_h == o.bias_motion_sum_t_h &&
         bias_motion_sum_t2_h2 == o.bias_motion_sum_t2_h2 &&
         bias_motion_sum_nT == o.bias_motion_sum_nT &&
         bias_motion_sum_tm_nT_h == o.bias_motion_sum_tm_nT_h &&
         bias_motion_sum_m2_nT2 == o.bias_motion_sum_m2_nT2 &&
         bias_motion_sum_J_nT == o.bias_motion_sum_J_nT &&
         bias_motion_sum_tJ_nT_h == o.bias_motion_sum_tJ_nT_h &&
         bias_motion_sum_Jd_nT == o.bias_motion_sum_Jd_nT &&
         bias_motion_sum_tJd_nT_h == o.bias_motion_sum_tJd_nT_h &&
         bias_random_walk_nT2_per_hour == o.bias_random_walk_nT2_per_hour &&
         refit_bias_rate_nT_per_h == o.refit_bias_rate_nT_per_h &&
         refit_bias_random_walk_nT2_per_hour == o.refit_bias_random_walk_nT2_per_hour;
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
    case FilterUpdateStatus::kCollecting:
      return "collecting";
  }
  return "rejected_invalid";
}

StartAttempt start_attempt_due(int64_t n, const FilterOptions& options) {
  const int64_t every = options.start_attempt_every;
  if (n < options.start.min_samples || n % every != 0) return StartAttempt::kNone;
  const int64_t multiple = n / every;
  if (multiple >= kUnconditionalAttemptMultiple && (multiple & (multiple - 1)) == 0)
    return StartAttempt::kUnconditional;
  const double max_gap = options.start_attempt_gap_fraction * static_cast<double>(n);
  int64_t spacing = every;
  while (static_cast<double>(2 * spacing) <= max_gap) spacing *= 2;
  return n % spacing == 0 ? StartAttempt::kIfObservable : StartAttempt::kNone;
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

void ScalarFilterBase::set_covariance(const Matrix9d& P) {
  Matrix9d Pc = P, L;
  switch (guard_covariance(Pc, L)) {
    case CovarianceGuard::kOk:
      break;
    case CovarianceGuard::kRepaired:
      ++state_.n_covariance_repairs;
      break;
    case CovarianceGuard::kNonFinite:  // refuse a NaN covariance: fall back to the prior
      ++state_.n_covariance_repairs;
      L = options_->initial_covariance().diagonal().cwiseSqrt().asDiagonal();
      break;
  }
  state_.S = L.triangularView<Eigen::Lower>();
}

void ScalarFilterBase::anchor_sandwich() {
  // A = P^-1 = S^-T S^-1, from the factor (no explicit inverse of P).
  const Matrix9d S_inv = state_.S.triangularView<Eigen::Lower>().solve(Matrix9d::Identity());
  state_.anchor_information_and_meat = packed_upper<9>(Matrix9d(S_inv.transpose() * S_inv));
  state_.score_block.setZero();
  state_.score_block_n = 0;
  state_.score_blocks = 0;
}

void ScalarFilterBase::initialize(const Vector9d& x0, const Matrix9d& P0) {
  state_ = FilterState{};
  state_.x = x0;
  set_covariance(P0);
  anchor_sandwich();
  mark_started();
  update_convergence_time();
}

void ScalarFilterBase::reanchor(const Vector9d& x, const Matrix9d& P,
                                const Matrix9d& model_error_covariance) {
  set_model_error_covariance(model_error_covariance);
  state_.x = x;
  set_covariance(P);
  anchor_sandwich();
  mark_started();
  state_.consistent = true;
  state_.nis_window_sum = 0.0;
  state_.nis_window_count = 0;
  state_.converged_since_utime = -1;
  if (state_.moments.n > 0) {
    state_.fisher_condition = moments_fisher_condition(state_.moments.matrix(), state_.x);
    state_.samples_since_fisher = 0;
  }
  update_convergence_time();
}

void ScalarFilterBase::set_model_error_covariance(const Matrix9d& model_error_covariance) {
  // Kept symmetric (packed): an exactly symmetric input, such as the refit's, is kept exactly.
  state_.model_error_covariance =
      model_error_covariance.allFinite()
          ? packed_upper<9>(
                Matrix9d(0.5 * (model_error_covariance + model_error_covariance.transpose())))
          : PackedTriangle<9>::Zero();
  state_.model_error_known = true;
}

void ScalarFilterBase::seed_bias_rate(const Eigen::Vector3d& rate_nT_per_h,
                                      const Eigen::Matrix3d& rate_covariance) {
  state_.refit_bias_rate_nT_per_h = rate_nT_per_h;
  state_.refit_bias_random_walk_nT2_per_hour =
      3.0 * rate_covariance.diagonal() * options_->bias_motion_block_hours;
}

void ScalarFilterBase::seed_noise(double measurement_noise_nT, double residual_autocorrelation) {
  if (std::isfinite(residual_autocorrelation)) {
    state_.innovation_c0 = 1.0;
    state_.innovation_c1 = std::clamp(residual_autocorrelation, -1.0, 1.0);
  }
  if (!(measurement_noise_nT > 0.0) || !std::isfinite(measurement_noise_nT)) return;
  const double ratio = measurement_noise_nT / options_->sigma_nT;
  state_.noise_scale2 = std::max(1.0, ratio * ratio);
}

void ScalarFilterBase::reset() {
  state_ = FilterState{};
}

void ScalarFilterBase::restore(const FilterState& s) {
  state_ = s;
  // A state that breaks the one-or-the-other rule of lag1_or_block (not one from state()) gets
  // the empty alternative it should hold.
  if (state_.initialized && !std::holds_alternative<BiasBlockStart>(state_.lag1_or_block))
    state_.lag1_or_block.emplace<BiasBlockStart>();
  if (!state_.initialized && !std::holds_alternative<ScalarLag1Moments>(state_.lag1_or_block))
    state_.lag1_or_block.emplace<ScalarLag1Moments>();
}

void ScalarFilterBase::mark_started() {
  if (!state_.initialized) state_.lag1_or_block.emplace<BiasBlockStart>();
  state_.initialized = true;
}

void ScalarFilterBase::reset_period() {
  state_.period_start_utime = state_.last_utime;
  state_.period_n = 0;
  state_.period_residual_sum2_nT2 = 0.0;
  state_.period_nis_sum = 0.0;
}

Matrix9d ScalarFilterBase::P() const {
  return state_.S * state_.S.transpose();
}

Matrix9d ScalarFilterBase::reported_covariance() const {
  const Matrix9d P = this->P();
  const Matrix9d model_error = symmetric_from_packed<9>(state_.model_error_covariance);
  if (options_->sandwich_block_samples <= 0 || state_.score_blocks == 0) {
    return P + model_error;
  }
  const Matrix9d C = P * symmetric_from_packed<9>(state_.anchor_information_and_meat) * P;
  return covariance_not_below(P, Matrix9d(0.5 * (C + C.transpose()))) + model_error;
}

Eigen::Vector3d ScalarFilterBase::bias_sigma_nT() const {
  return state_.S.topRows<3>().rowwise().norm();
}

bool ScalarFilterBase::converged() const {
  return state_.initialized && state_.consistent &&
         (state_.model_error_known || !options_->ok_needs_model_error) &&
         state_.fisher_condition <= options_->max_fisher_condition &&
         (bias_sigma_nT().array() < options_->converged_bias_sigma_nT).all();
}

double ScalarFilterBase::measurement_noise_nT() const {
  return options_->sigma_nT * std::sqrt(state_.noise_scale2);
}

double ScalarFilterBase::innovation_autocorrelation() const {
  return state_.innovation_c0 > 0.0 ? state_.innovation_c1 / state_.innovation_c0 : 0.0;
}

double ScalarFilterBase::correlation_inflation() const {
  if (!options_->start.correlation_inflation) return 1.0;
  return ar1_variance_factor(innovation_autocorrelation(), options_->start.max_correlation);
}

CalibrationResult ScalarFilterBase::snapshot() const {
  CalibrationResult r;
  r.method = method_;
  r.utime = state_.last_utime;
  r.window_start_utime = state_.first_utime;
  r.window_end_utime = state_.last_utime;
  r.n_samples = static_cast<int>(state_.moments.n);
  r.parameters = parameters();
  r.covariance = state_.initialized ? reported_covariance() : options_->initial_covariance();
  const Eigen::Vector3d bias_sigma = r.covariance.diagonal().head<3>().cwiseSqrt();
  r.iterations = static_cast<int>(state_.n_accepted);
  r.converged = converged();
  if (state_.period_n > 0) {
    r.residual_rms_nT =
        std::sqrt(state_.period_residual_sum2_nT2 / static_cast<double>(state_.period_n));
    r.nis_mean = state_.period_nis_sum / static_cast<double>(state_.period_n);
  } else {
    r.residual_rms_nT = std::numeric_limits<double>::quiet_NaN();
  }
  r.measurement_noise_nT = measurement_noise_nT();
  r.noise_scale = std::sqrt(state_.noise_scale2);
  r.residual_autocorrelation = innovation_autocorrelation();
  r.fisher_condition_number = state_.initialized && state_.moments.n >= 10
                                  ? moments_fisher_condition(state_.moments.matrix(), state_.x)
                                  : state_.fisher_condition;
  char buf[200];
  if (!state_.has_time) {
    r.status = CalibrationStatus::kFailed;
    r.message = "no valid sample yet";
  } else if (!state_.initialized) {
    r.status = CalibrationStatus::kNotConverged;
    std::snprintf(buf, sizeof buf,
                  "collecting data for the start: %lld samples, scaled Fisher condition %.3g "
                  "(start needs <= %.3g)",
                  static_cast<long long>(state_.moments.n), state_.fisher_condition,
                  options_->start.max_condition);
    r.message = buf;
  } else if (!(r.fisher_condition_number <= options_->max_fisher_condition)) {
    r.status = CalibrationStatus::kUnobservable;
    std::snprintf(buf, sizeof buf,
                  "scaled Fisher condition %.3g > %.3g: the data seen do not observe every "
                  "parameter",
                  r.fisher_condition_number, options_->max_fisher_condition);
    r.message = buf;
  } else if (!state_.consistent) {
    r.status = CalibrationStatus::kNotConverged;
    std::snprintf(buf, sizeof buf, "inconsistent innovations (mean NIS %.3g), covariance re-opened",
                  state_.last_window_mean_nis);
    r.message = buf;
  } else if (options_->ok_needs_model_error && !state_.model_error_known) {
    r.status = CalibrationStatus::kNotConverged;
    r.message = "waiting for the first refit to measure the model error";
  } else if (!(bias_sigma.array() < options_->converged_bias_sigma_nT).all()) {
    r.status = CalibrationStatus::kNotConverged;
    if (bias_random_walk_nT_per_sqrt_hour() > 0.0) {
      std::snprintf(buf, sizeof buf,
                    "bias 1-sigma above %.3g nT: the bias moves (random walk %.3g nT/sqrt(h) "
                    "measured) faster than the data observe it",
                    options_->converged_bias_sigma_nT, bias_random_walk_nT_per_sqrt_hour());
    } else {
      std::snprintf(buf, sizeof buf, "bias 1-sigma above %.3g nT",
                    options_->converged_bias_sigma_nT);
    }
    r.message = buf;
  } else {
    r.status = CalibrationStatus::kOk;
  }
  return r;
}

CalibrationResult ScalarFilterBase::snapshot_and_reset_period() {
  CalibrationResult r = snapshot();
  reset_period();
  return r;
}

void ScalarFilterBase::start_from(const FilterStartResult& start) {
  state_.x = start.p;
  set_covariance(start.covariance);
  anchor_sandwich();
  mark_started();
  state_.noise_scale2 = std::max(state_.noise_scale2, start.noise_scale2);
  state_.innovation_c0 = 1.0;
  state_.innovation_c1 = start.residual_autocorrelation;
  state_.has_previous_innovation = false;
  state_.fisher_condition = start.fisher_condition;
  state_.samples_since_fisher = 0;
  update_convergence_time();
}

bool ScalarFilterBase::begin_update(FilterUpdate& u, const Eigen::Vector3d& b_sensor_nT,
                                    double h_norm_nT, int64_t utime) {
  u.status = FilterUpdateStatus::kRejectedInvalid;
  if (!is_finite(b_sensor_nT) || !std::isfinite(h_norm_nT) || !(h_norm_nT > 0.0)) {
    ++state_.n_rejected_invalid;
    return false;
  }
  if (!state_.has_time) {  // first valid sample: no prediction before it
    state_.has_time = true;
    state_.first_utime = utime;
    state_.last_utime = utime;
    state_.period_start_utime = utime;
  } else if (utime > state_.last_utime) {
    if (state_.initialized) {
      const double dt_s =
          static_cast<double>(saturating_sub(utime, state_.last_utime)) / kMicrosecondsPerSecond;
      state_.x.head<3>() += state_.refit_bias_rate_nT_per_h * (dt_s / kSecondsPerHour);
      Vector9d q = process_noise_diagonal(options_->process_noise_per_sqrt_hour, dt_s);
      const double isotropic_nT2_per_hour =
          std::max(state_.bias_random_walk_nT2_per_hour, bias_random_walk_floor_nT2_per_hour());
      q.head<3>().array() +=
          state_.refit_bias_random_walk_nT2_per_hour.array().max(isotropic_nT2_per_hour) *
          (dt_s / kSecondsPerHour);
      if ((q.array() > 0.0).any()) {
        // P + Q re-factorised (one 9x9 LLT is cheaper than nine serial rank-1 updates).
        Matrix9d P = state_.S * state_.S.transpose();
        P.diagonal() += q;
        const Eigen::LLT<Matrix9d> llt(P);
        if (llt.info() == Eigen::Success) state_.S = llt.matrixL();
      }
    }
    state_.last_utime = utime;
  }
  if (state_.initialized) return true;

  if (options_->cold_start == FilterOptions::ColdStart::kFromData) {
    const double y =
        scalar_measurement(b_sensor_nT, h_norm_nT) - scalar_noise_mean(options_->sigma_nT);
    // Not started: lag1_or_block holds the lag-1 products (mark_started()).
    auto& lag1 = std::get<ScalarLag1Moments>(state_.lag1_or_block);
    state_.moments.add(b_sensor_nT, y, 1.0 / scalar_noise_variance(b_sensor_nT, options_->sigma_nT),
                       &lag1);
    u.status = FilterUpdateStatus::kCollecting;
    const StartAttempt due = start_attempt_due(state_.moments.n, *options_);
    if (due == StartAttempt::kUnconditional ||
        (due == StartAttempt::kIfObservable &&
         start_precheck_condition(state_.moments) <=
             options_->start.precheck_margin * options_->start.max_condition)) {
      const FilterStartResult start = solve_filter_start(state_.moments, lag1, options_->start);
      if (start.status != FilterStartStatus::kTooFewSamples)
        state_.fisher_condition = start.fisher_condition;
      if (start.status == FilterStartStatus::kOk) {
        start_from(start);
        u.started = true;
      }
    }
    return false;
  }
  // Prior start (estimation.md 3): the first valid sample is also the first update.
  state_.x.setZero();
  if (options_->cold_start == FilterOptions::ColdStart::kFirstSampleScale &&
      b_sensor_nT.norm() > 0.0) {
    state_.x.segment<3>(3).setConstant(h_norm_nT / b_sensor_nT.norm() - 1.0);
  }
  state_.S = options_->initial_covariance().diagonal().cwiseSqrt().asDiagonal();
  mark_started();
  return true;
}

void ScalarFilterBase::finish_update(FilterUpdate& u, const Eigen::Vector3d& b_sensor_nT,
                                     double h_norm_nT, const Eigen::Vector3d& b_cal, double y_hat,
                                     double hph, const Vector9d& Pxz_white) {
  const double sigma = options_->sigma_nT;
  const Vector9d Pxz = lower_triangular_times(state_.S, Pxz_white);
  const double y = scalar_measurement(b_sensor_nT, h_norm_nT) - scalar_noise_mean(sigma);
  const double R1 = scalar_noise_variance(b_cal, sigma);
  const double R_white = R1 * state_.noise_scale2;
  const double S_white = hph + R_white;
  const double S_gain = hph + R_white * correlation_inflation();
  const double nu = y - y_hat;
  u.innovation_nT2 = nu;
  u.innovation_variance_nT4 = S_white;
  if (!(S_white > 0.0) || !std::isfinite(S_white) || !std::isfinite(nu) || !Pxz.allFinite()) {
    ++state_.n_rejected_invalid;
    u.status = FilterUpdateStatus::kRejectedNumerical;
    return;
  }
  u.nis = nu * nu / S_white;
  const bool gating = options_->gate_nis > 0.0;

  // Evidence over the snapshot period (prior estimate, every valid sample).
  const double residual_nT = b_cal.norm() - h_norm_nT;
  state_.period_residual_sum2_nT2 += residual_nT * residual_nT;
  state_.period_nis_sum += gating ? std::min(u.nis, options_->gate_nis) : u.nis;
  ++state_.period_n;

  if (options_->adaptive_noise) {
    // Gated samples enter clipped to the gate: a real noise increase still raises a, a spike
    // moves it by at most gate / N.
    const double nu2 = gating ? std::min(nu * nu, options_->gate_nis * S_white) : nu * nu;
    const double lambda = 1.0 / options_->noise_adaptation_samples;
    state_.noise_scale2 += lambda * ((nu2 - hph) / R1 - state_.noise_scale2);
    state_.noise_scale2 = std::max(1.0, state_.noise_scale2);
    double e = nu / std::sqrt(S_white);
    if (gating) {
      const double lim = std::sqrt(options_->gate_nis);
      e = std::clamp(e, -lim, lim);
    }
    state_.innovation_c0 += lambda * (e * e - state_.innovation_c0);
    if (state_.has_previous_innovation)
      state_.innovation_c1 +=
          lambda * (e * state_.previous_normalised_innovation - state_.innovation_c1);
    state_.previous_normalised_innovation = e;
    state_.has_previous_innovation = true;
  }

  if (gating && u.nis > options_->gate_nis) {
    ++state_.n_rejected_gate;
    u.status = FilterUpdateStatus::kRejectedGate;
    monitor(u);
    return;
  }

  // Kalman update: x += K nu, P -= Pxz Pxz^T / S, i.e. S S^T - (S p)(S p)^T with
  // p = S^-1 Pxz / sqrt(S): a rank-1 downdate of S in place. With R > 0, |p| < 1 and it cannot
  // fail; if round-off ever made it, the update is refused and S left untouched.
  const double inv_sqrt_S = 1.0 / std::sqrt(S_gain);
  const Vector9d x_new = state_.x + Pxz * (nu * inv_sqrt_S * inv_sqrt_S);
  // The sample's score for the reported covariance (H: the measurement Jacobian at the prior).
  const Vector9d score =
      scalar_measurement_jacobian_at(b_cal, b_sensor_nT).transpose() * (nu / (S_gain - hph));
  if (!x_new.allFinite() ||
      !cholesky_downdate_whitened(state_.S, Pxz_white * inv_sqrt_S, Pxz * inv_sqrt_S)) {
    ++state_.n_rejected_invalid;
    u.status = FilterUpdateStatus::kRejectedNumerical;
    return;
  }
  state_.x = x_new;
  if (options_->sandwich_block_samples > 0 && score.allFinite()) {
    state_.score_block += score;
    if (++state_.score_block_n >= options_->sandwich_block_samples) {
      add_outer_product<9>(state_.anchor_information_and_meat, state_.score_block);
      ++state_.score_blocks;
      state_.score_block.setZero();
      state_.score_block_n = 0;
    }
  }
  ++state_.n_accepted;
  u.status = FilterUpdateStatus::kAccepted;
  state_.moments.add(b_sensor_nT, y, 1.0 / scalar_noise_variance(b_sensor_nT, sigma));
  track_bias_motion();
  if (++state_.samples_since_fisher >= options_->fisher_every) {
    state_.fisher_condition = moments_fisher_condition(state_.moments.matrix(), state_.x);
    state_.samples_since_fisher = 0;
  }
  monitor(u);
  update_convergence_time();
}

void ScalarFilterBase::monitor(FilterUpdate& u) {
  // Gated samples enter clipped to the gate: many of them still trip the monitor (a filter that
  // rejects everything is not consistent), one spike does not.
  const double nis = options_->gate_nis > 0.0 ? std::min(u.nis, options_->gate_nis) : u.nis;
  state_.nis_window_sum += nis;
  if (++state_.nis_window_count < options_->nis_window) return;

  const double mean = state_.nis_window_sum / state_.nis_window_count;
  state_.last_window_mean_nis = mean;
  state_.nis_window_sum = 0.0;
  state_.nis_window_count = 0;
  state_.consistent = mean <= options_->nis_inconsistent_mean;
  if (state_.consistent) return;

  ++state_.n_inconsistency_events;
  u.inconsistency_event = true;
  const Vector9d p0 = options_->initial_covariance().diagonal();
  if (options_->consistency_action == FilterOptions::ConsistencyAction::kReseed) {
    state_.S = p0.cwiseSqrt().asDiagonal();
  } else {
    state_.S *= std::sqrt(options_->inflation_factor);
    // Cap each variance at its prior value by scaling its row of S (keeps S lower triangular).
    for (int i = 0; i < 9; ++i) {
      const double var = state_.S.row(i).squaredNorm();
      if (var > p0(i)) state_.S.row(i) *= std::sqrt(p0(i) / var);
    }
  }
  anchor_sandwich();  // the re-opened P forgets; so do the blocks
  update_convergence_time();
}

bool ScalarFilterBase::block_bias_given_scale(const Matrix11d& block, const Vector9d& scale,
                                              Eigen::Vector3d& bias_nT) {
  // Gauss-Newton on c = (I + D) b with E held at that of `scale` (file comment).
  const CalibrationParameters p = CalibrationParameters::from_packed(scale);
  Vector9d theta = theta_from_parameters(p);
  Matrix9d F;
  Vector9d g;
  for (int iteration = 0; iteration < kBlockBiasIterations; ++iteration) {
    if (!moments_cost(block, theta, nullptr, &F, &g)) return false;
    const Eigen::LDLT<Eigen::Matrix3d> ldlt(F.topLeftCorner<3, 3>());
    if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().array() > 0.0).all()) return false;
    theta.head<3>() -= ldlt.solve(g.head<3>());
  }
  bias_nT = (Eigen::Matrix3d::Identity() + p.D).inverse() * theta.head<3>();
  return bias_nT.allFinite();
}

bool ScalarFilterBase::bias_trend(Eigen::Array3d& rate_nT_per_h,
                                  Eigen::Array3d& se2_nT2_per_h2) const {
  // Per axis: the least-squares trend of the block biases and its standard error from their own
  // scatter about it (block noise, stationary model error and aliased fast motion alike). The
  // scatter is that of the biases as solved: at the current D it would need their squares'
  // sensitivity to D (84 more sums); as solved it also holds the earlier D's errors, so the
  // standard error is on the safe side for the motion test.
  const int n = state_.bias_motion_n;
  if (n < 3) return false;
  const double Stt =
      state_.bias_motion_sum_t2_h2 - state_.bias_motion_sum_t_h * state_.bias_motion_sum_t_h / n;
  if (!(Stt > 0.0)) return false;
  const Eigen::Array3d Stm = state_.bias_motion_sum_tm_nT_h.array() -
                             state_.bias_motion_sum_t_h * state_.bias_motion_sum_nT.array() / n;
  const Eigen::Array3d Smm =
      state_.bias_motion_sum_m2_nT2.array() - state_.bias_motion_sum_nT.array().square() / n;
  const Eigen::Array3d rate_as_solved = Stm / Stt;
  se2_nT2_per_h2 = ((Smm - rate_as_solved * Stm) / (n - 2)).max(1e-300) / Stt;
  // The biases at the current D d: m_k + J_k (d - d_k) (linear in D: its steps are small).
  const Vector6d d = state_.x.tail<6>();
  const Eigen::Vector3d sum_m =
      state_.bias_motion_sum_nT + state_.bias_motion_sum_J_nT * d - state_.bias_motion_sum_Jd_nT;
  const Eigen::Vector3d sum_tm = state_.bias_motion_sum_tm_nT_h +
                                 state_.bias_motion_sum_tJ_nT_h * d -
                                 state_.bias_motion_sum_tJd_nT_h;
  rate_nT_per_h = (sum_tm.array() - state_.bias_motion_sum_t_h * sum_m.array() / n) / Stt;
  return true;
}

double ScalarFilterBase::bias_random_walk_floor_nT2_per_hour() const {
  if (!(options_->bias_floor_rate_sigmas > 0.0) || state_.bias_motion_n < kBiasMotionFloorMinBlocks)
    return 0.0;
  Eigen::Array3d rate, se2;
  if (!bias_trend(rate, se2)) return 0.0;
  // The pooled standard error (the same physics moves all three axes), as a random walk (q^2 =
  // 3 r^2 L, file comment).
  const double k = options_->bias_floor_rate_sigmas;
  const double cap = options_->bias_random_walk_floor_cap_nT_per_sqrt_hour;
  return std::min(cap * cap, 3.0 * k * k / se2.inverse().sum() * options_->bias_motion_block_hours);
}

void ScalarFilterBase::track_bias_motion() {
  if (!(options_->bias_motion_block_hours > 0.0)) return;
  // Started: lag1_or_block holds the block start (mark_started()).
  auto& block_start = std::get<BiasBlockStart>(state_.lag1_or_block);
  if (block_start.utime < 0) {
    block_start.m = state_.moments.m;
    block_start.n = state_.moments.n;
    block_start.utime = state_.last_utime;
    return;
  }
  const double block_hours = options_->bias_motion_block_hours;
  const double elapsed_h = static_cast<double>(state_.last_utime - block_start.utime) /
                           (kMicrosecondsPerSecond * kSecondsPerHour);
  if (elapsed_h < block_hours) return;
  // The block's own moments: the sums since its start.
  ScalarMoments block;
  block.m = state_.moments.m - block_start.m;
  block.n = state_.moments.n - block_start.n;
  block_start.m = state_.moments.m;
  block_start.n = state_.moments.n;
  block_start.utime = state_.last_utime;
  const Matrix11d M = block.matrix();
  Eigen::Vector3d m;
  if (!block_bias_given_scale(M, state_.x, m)) return;
  // Its sensitivity to D, by central differences (13 small solves every block_hours).
  Eigen::Matrix<double, 3, 6> J;
  for (int j = 0; j < 6; ++j) {
    Vector9d plus = state_.x, minus = state_.x;
    plus(3 + j) += kBlockBiasDStep;
    minus(3 + j) -= kBlockBiasDStep;
    Eigen::Vector3d m_plus, m_minus;
    if (!block_bias_given_scale(M, plus, m_plus) || !block_bias_given_scale(M, minus, m_minus))
      return;
    J.col(j) = (m_plus - m_minus) / (2.0 * kBlockBiasDStep);
  }
  const double t_h = static_cast<double>(state_.last_utime - state_.first_utime) /
                         (kMicrosecondsPerSecond * kSecondsPerHour) -
                     0.5 * elapsed_h;  // block centre
  const Eigen::Vector3d Jd = J * state_.x.tail<6>();
  state_.bias_motion_n += 1;
  state_.bias_motion_sum_t_h += t_h;
  state_.bias_motion_sum_t2_h2 += t_h * t_h;
  state_.bias_motion_sum_nT += m;
  state_.bias_motion_sum_tm_nT_h += t_h * m;
  state_.bias_motion_sum_m2_nT2 += m.cwiseAbs2();
  state_.bias_motion_sum_J_nT += J;
  state_.bias_motion_sum_tJ_nT_h += t_h * J;
  state_.bias_motion_sum_Jd_nT += Jd;
  state_.bias_motion_sum_tJd_nT_h += t_h * Jd;
  if (state_.bias_motion_n < kBiasMotionMinBlocks) return;
  Eigen::Array3d rate, se2;
  if (!bias_trend(rate, se2)) return;
  rate -= state_.refit_bias_rate_nT_per_h.array();  // the motion the filter already predicts
  const double chi2 = (rate.square() / se2).sum();
  if (!(chi2 > options_->bias_motion_chi2)) {
    state_.bias_random_walk_nT2_per_hour = 0.0;
    return;
  }
  // Inverse-variance pooled rate^2 (unbiased: minus its variance), as the random walk with the
  // same block-to-block excess: q^2 = 3 r^2 L (file comment).
  const Eigen::Array3d w = se2.inverse();
  const double rate2 = std::max(0.0, (w * (rate.square() - se2)).sum() / w.sum());
  state_.bias_random_walk_nT2_per_hour = 3.0 * rate2 * block_hours;
}

double ScalarFilterBase::bias_random_walk_nT_per_sqrt_hour() const {
  return std::sqrt(std::max(state_.bias_random_walk_nT2_per_hour,
                            state_.refit_bias_random_walk_nT2_per_hour.maxCoeff()));
}

void ScalarFilterBase::update_convergence_time() {
  if (converged()) {
    if (state_.converged_since_utime < 0) state_.converged_since_utime = state_.last_utime;
  } else {
    state_.converged_since_utime = -1;
  }
}

}  // namespace magcal
