// What the online stage-1 filters (magnetometer_ekf, magnetometer_ukf) share: options, the
// serialisable state, process-noise scaling, the covariance guard and the consistency monitor
// (estimation.md sections 3 and 3a). One copy, used by both filters.
//
// Model (estimation.md 3): static state x = p = [b1 b2 b3 D11 D22 D33 D12 D13 D23]
// (nT, nT, nT, 1, 1, 1, 1, 1, 1), x_{k+1} = x_k + w_k, w_k ~ N(0, Q_k),
//   Q_k = diag(q_i^2) * dt_s / 3600       (q_i: 1-sigma random walk per sqrt(hour), per state)
// Scalar measurement y_k = z_k - mu_k = h(x, B_k) + v_k, z_k = |B_k|^2 - |h_k|^2,
//   mu_k = 3 sigma^2, Var v_k = R_k = scalar_noise_variance((I + D_hat) B_k - b_hat, sigma)
// (pipeline/scalar_measurement.hpp).
//
// Innovation gate: an innovation nu with NIS = nu^2 / S > gate_nis (default: chi2(1) upper
// 1e-6 tail, 23.93) is rejected and counted; the state is not touched.
//
// Consistency policy (estimation.md 3a: a wrong estimate must not claim a small sigma):
// the NIS of every valid sample (accepted or gated; gated ones enter clipped to gate_nis so a
// single spike cannot trigger it) is averaged over consecutive, non-overlapping windows of
// nis_window samples. For a consistent filter the mean is ~1 (std ~ sqrt(2/window)). When a
// window's mean exceeds nis_inconsistent_mean the filter declares an inconsistency event:
// the state is kept and the covariance is re-opened (kInflate: P *= inflation_factor, each
// variance capped at the initial one; kReseed: P = initial covariance), the event is counted,
// and `consistent` is false until a later window's mean NIS is back below the threshold.
// A snapshot is only `ok` when the filter is consistent and the bias 1-sigma is below
// converged_bias_sigma_nT on all three axes; otherwise it is `not_converged`.
#pragma once

#include <cstdint>
#include <string>

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

// chi2 with 1 degree of freedom: P(X > 23.928) = 1e-6.
inline constexpr double kChi2OneDofTail1e6 = 23.928;

struct FilterOptions {
  double sigma_nT = 3.0;  // magnetometer white noise, 1-sigma per axis

  // Process noise: 1-sigma random walk per sqrt(hour), per state (nT for b, 1 for D). 0 = static.
  Vector9d process_noise_per_sqrt_hour = Vector9d::Zero();

  // Prior used on the first sample when initialize() was not called (cold start).
  enum class ColdStart : int8_t {
    kZero,              // x0 = 0
    kFirstSampleScale,  // b = 0, D = (|h|/|B| - 1) I from the first valid sample
  };
  ColdStart cold_start = ColdStart::kZero;
  double initial_bias_sigma_nT = 2000.0;
  double initial_D_sigma = 0.05;

  double gate_nis = kChi2OneDofTail1e6;  // innovation gate on nu^2 / S; <= 0 disables gating

  // Consistency monitor (policy in the file comment).
  int nis_window = 100;                // samples per window
  double nis_inconsistent_mean = 3.0;  // window mean NIS above this = inconsistent
  enum class ConsistencyAction : int8_t { kInflate, kReseed };
  ConsistencyAction consistency_action = ConsistencyAction::kInflate;
  double inflation_factor = 100.0;  // kInflate: P *= factor (variances capped at the initial)

  // Snapshot status: ok once every bias 1-sigma is below this (and the filter is consistent).
  double converged_bias_sigma_nT = 10.0;

  // Empty when valid, else what is wrong.
  std::string validate() const;

  // The cold-start covariance diag(initial_bias_sigma^2 x3, initial_D_sigma^2 x6).
  Matrix9d initial_covariance() const;
};

// Everything a filter needs to resume exactly (the daemon stores it in SQLite). Restoring a
// state obtained from state() gives a bit-exact continuation.
struct FilterState {
  Vector9d x = Vector9d::Zero();  // p = [b (nT); D11 D22 D33 D12 D13 D23]
  Matrix9d P = Matrix9d::Zero();  // covariance of x (nT^2, nT, 1)
  bool initialized = false;       // false: the next valid sample starts the filter (cold start)
  bool consistent = true;         // last completed NIS window was consistent
  bool has_time = false;          // a valid sample was seen: first_utime/last_utime are set
  int64_t first_utime = 0;        // first valid sample
  int64_t last_utime = 0;         // time x and P refer to (latest valid sample)
  // Time since which every bias 1-sigma has stayed below converged_bias_sigma_nT; -1 if not now.
  int64_t converged_since_utime = -1;
  int64_t n_accepted = 0;          // measurement updates applied
  int64_t n_rejected_invalid = 0;  // NaN/Inf, |h| <= 0, numerical failure
  int64_t n_rejected_gate = 0;     // innovation outside the gate
  int64_t n_inconsistency_events = 0;
  int64_t n_covariance_repairs = 0;  // covariance guard had to add jitter / clamp eigenvalues
  double nis_window_sum = 0.0;       // current (incomplete) window
  int32_t nis_window_count = 0;
  double last_window_mean_nis = 0.0;  // mean NIS of the last completed window (0: none yet)

  bool operator==(const FilterState& o) const;
};

// Outcome of one update() call (no allocation; for traces and counters).
enum class FilterUpdateStatus : int8_t {
  kAccepted = 0,           // measurement applied
  kRejectedInvalid = 1,    // NaN/Inf input or |h| <= 0: state untouched (not even predicted)
  kRejectedGate = 2,       // innovation outside the gate: predicted only, no measurement update
  kRejectedNumerical = 3,  // S not positive or non-finite numbers: predicted only, no update
};
const char* to_string(FilterUpdateStatus s);

struct FilterUpdate {
  FilterUpdateStatus status = FilterUpdateStatus::kRejectedInvalid;
  double innovation_nT2 = 0.0;           // y - y_hat
  double innovation_variance_nT4 = 0.0;  // S
  double nis = 0.0;                      // innovation^2 / S
  bool inconsistency_event = false;      // this sample closed an inconsistent NIS window
};

// diag(Q) for a step of dt_s: q_i^2 dt_s / 3600 (dt_s <= 0 gives 0).
Vector9d process_noise_diagonal(const Vector9d& q_per_sqrt_hour, double dt_s);

// Makes P symmetric positive definite and returns its lower Cholesky factor in L (P = L L^T).
// Symmetrises P and tries LLT; if that fails, adds a small diagonal jitter (relative to each
// variance), then falls back to clamping eigenvalues of the diagonally scaled P at a floor.
// kOk: P was fine (only symmetrised); kRepaired: P was modified; kNonFinite: P has NaN/Inf,
// P is left unchanged and L is undefined.
enum class CovarianceGuard : int8_t { kOk, kRepaired, kNonFinite };
CovarianceGuard guard_covariance(Matrix9d& P, Matrix9d& L);

// The part of the EKF and UKF that does not depend on how the innovation statistics are
// computed: validation, prediction, gating, the consistency monitor, state I/O and snapshots.
// Not polymorphic (no vtable); the filters derive from it and add update().
class ScalarFilterBase {
 public:
  const FilterOptions& filter_options() const { return options_; }

  // Start from a given prior (e.g. a batch refit) with all counters reset; the next valid
  // sample is the first one (no prediction before it).
  void initialize(const Vector9d& x0, const Matrix9d& P0);
  // After an accepted batch refit: replace x and P, keep time and counters, reset the NIS window
  // and the consistency flag (the refit is trusted).
  void reanchor(const Vector9d& x, const Matrix9d& P);
  // Forget everything (cold start on the next valid sample).
  void reset();

  const FilterState& state() const { return state_; }
  void restore(const FilterState& s) { state_ = s; }

  bool initialized() const { return state_.initialized; }
  bool consistent() const { return state_.consistent; }
  const Vector9d& x() const { return state_.x; }
  const Matrix9d& P() const { return state_.P; }
  CalibrationParameters parameters() const { return CalibrationParameters::from_packed(state_.x); }
  Eigen::Vector3d bias_sigma_nT() const { return state_.P.diagonal().head<3>().cwiseSqrt(); }
  bool converged() const;  // consistent and all bias 1-sigma < converged_bias_sigma_nT

  // The current estimate as a result (method "ekf"/"ukf"; status ok when converged(), else
  // not_converged; failed before the first sample).
  CalibrationResult snapshot() const;

 protected:
  ScalarFilterBase(const FilterOptions& options, const char* method)
      : options_(options), method_(method) {}

  // Shared first half of update(): rejects invalid input (counted, state untouched), starts a
  // cold filter, predicts to utime (P += Q). Returns false if the sample is invalid.
  bool begin_update(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT, int64_t utime);
  // y = z - mu for the sample and the noise variance R at the current (prior) estimate.
  void measurement(const Eigen::Vector3d& b_sensor_nT, double h_norm_nT, double& y,
                   double& R) const;
  // Fills u.nis; if outside the gate counts the rejection, runs the monitor and returns false.
  bool gate(FilterUpdate& u);
  // After a measurement update: guard P, count, convergence time, run the monitor.
  // Commits the posterior (then symmetrises, guards, counts) unless it is not finite, in which
  // case the state is left untouched and the update reported as rejected (numerical).
  void commit_posterior(FilterUpdate& u, const Vector9d& x_new, const Matrix9d& P_new);
  void finish_accepted(FilterUpdate& u);

  FilterOptions options_;
  FilterState state_;
  const char* method_;

 private:
  void monitor(FilterUpdate& u);
  void update_convergence_time();
};

}  // namespace magcal
