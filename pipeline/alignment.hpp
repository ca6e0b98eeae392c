// Stage 2: installation misalignment R_sensor_from_body (estimation.md section 4).
//
// Input pairs: u_k = (I + D_hat) B_k - b_hat (stage-1 calibrated vector, sensor frame, nT) and
// h_k (reference field, body frame, nT), with the model  u_k = R h_k + eps_k,
// eps_k ~ N(0, sigma^2 I).
//
// Angle convention (estimation.md section 0): R = Rx(roll) Ry(pitch) Rz(yaw) ≈ I - [theta x],
// theta = (roll, pitch, yaw). Every covariance reported here is that of the small rotation
// dtheta (rad^2) in the SENSOR frame about the estimate: R_true = (I - [dtheta x]) R_hat, so
// to first order u_k = R_hat h_k + [(R_hat h_k) x] dtheta. For R_hat near I this is the
// covariance of (roll, pitch, yaw).
//
// Estimators:
//  - align_procrustes: exact orthogonal Procrustes / Wahba, M = sum u_k h_k^T = U S V^T,
//    R_hat = U diag(1, 1, det(U V^T)) V^T (always a proper rotation, det +1). Covariance
//    P = sigma^2 (sum_k (|h_k|^2 I - g_k g_k^T))^-1, g_k = R_hat h_k (the Fisher information
//    of dtheta; equals R_hat (sum |h|^2 I - h h^T)^-1 R_hat^T, the QUEST covariance).
//  - align_small_angle_ls: the paper's linear LS u_k - h_k = [h_k x] theta (single step, theta
//    read as (roll, pitch, yaw): R_1 = Rx Ry Rz(theta); at (1, 2, 1) deg this leaves 0.027 deg
//    of linearisation error, measured), then one re-linearisation about R_1:
//    u_k - R_1 h_k = [(R_1 h_k) x] dtheta, R_2 = rotation(dtheta) R_1.
//  - AlignmentKalmanFilter: online linear KF, static state dtheta about a reference R_ref,
//    measurement y_k = u_k - R_ref h_k = H_k dtheta + noise, H_k = [(R_ref h_k) x], noise
//    Sigma + R_ref [h_k x] P_att [h_k x]^T R_ref^T (P_att: body-frame attitude-knowledge
//    covariance, rad^2). Fixed-size, no allocation per update, state saved/restored exactly.
//  - align_with_unknown_reference: joint R and a constant field f_ref (e.g. ENU) from
//    u_k = R A_k f_ref + eps_k with known attitudes A_k = A_body_from_ref, by alternating
//    Procrustes (h_k = A_k f) and f = mean_k A_k^T R^T u_k.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"
#include "pipeline/model_extension.hpp"
#include "pipeline/rotation.hpp"

namespace magcal {

// One stage-2 observation.
struct AlignmentPair {
  Eigen::Vector3d u_sensor_nT = Eigen::Vector3d::Zero();  // (I + D_hat) B - b_hat
  Eigen::Vector3d h_body_nT = Eigen::Vector3d::Zero();    // reference field, body frame
};

// u_k = params.apply(B_k) for every sample with has_reference_direction and finite values.
std::vector<AlignmentPair> make_alignment_pairs(const SampleSet& samples,
                                                const CalibrationParameters& params);
// The same with the stage-1 calibrated vectors given (one per sample, sample order; e.g.
// extension_corrected_vectors() when the batch fit enabled the sensor-model extension).
// utime: when given, receives each pair's time tag.
std::vector<AlignmentPair> make_alignment_pairs(const SampleSet& samples,
                                                const std::vector<Eigen::Vector3d>& u_sensor_nT,
                                                std::vector<int64_t>* utime = nullptr);

// What stage-1 errors do to the angles (first order): Cov = G_p C_p G_p^T + G_a C_a G_a^T,
// G_p = F^-1 sum_k J_k^T du_k/dp, J_k = [(R h_k) x], du_k/dp = 3 x 9 (-I for b, B_k entries for
// D), over the samples make_alignment_pairs() uses; R = the estimate, C_p = the stage-1 covariance
// of p. With `extension` (the inputs u was corrected with by extension_corrected_vectors) the
// extension's coefficients a = [k; eta] were removed from u too:
// G_a the same with du_k/da = -[diag(y_k^2) diag(s_k)], C_a their covariance (cross-covariance
// of p and a left out). rad^2, sensor frame. Zero when no sample carries a reference direction.
Eigen::Matrix3d alignment_covariance_from_stage1(
    const SampleSet& samples, const Eigen::Matrix3d& R, const Matrix9d& parameter_covariance,
    const ExtensionInputs* extension = nullptr,
    const Matrix6d& extension_covariance = Matrix6d::Zero());

struct AlignmentOptions {
  // Per-axis noise of u (nT) used for the covariance: sigma^2 F^-1 (white noise, known level).
  // <= 0: the covariance comes from the residuals' structure (stage-1 errors, unmodelled effects
  // and attitude noise leave correlated residuals): sigma^2 = sum |u_k - R_hat h_k|^2 / (3N - 3)
  // and a Newey–West sandwich F^-1 Omega F^-1 on the scores J_k^T e_k, J_k = [(R_hat h_k) x],
  // Bartlett lag window from the residuals' lag-1 autocorrelation (hac_covariance.hpp; samples
  // in time order), reported as max(sigma^2 F^-1, sandwich).
  double sigma_nT = 0.0;
  int min_samples = 3;
  // Geometry gate: the field directions must span at least two dimensions, otherwise the
  // rotation about the common direction is unobservable. Fails when the smallest eigenvalue of
  // the normalised information sum(|h|^2 I - h h^T) / sum |h|^2 is below this (max is 2/3).
  double min_information_ratio = 1e-6;

  std::string validate() const;  // empty when valid
};

enum class AlignmentStatus {
  kOk = 0,             // estimate valid
  kTooFewSamples = 1,  // fewer than min_samples usable pairs
  kInvalidInput = 2,   // NaN/Inf in the input or invalid options
  kUnobservable = 3,   // all reference directions (nearly) parallel
  kNotConverged = 4,   // joint (R, f) iteration hit its limit (estimate still returned)
};
const char* to_string(AlignmentStatus s);  // "ok", "too_few_samples", ...

struct AlignmentResult {
  AlignmentStatus status = AlignmentStatus::kInvalidInput;
  std::string message;           // why, when status is not ok
  AlignmentEstimate estimate;    // R_sensor_from_body, angle_covariance_rad2, n_samples
  RollPitchYaw rpy;              // of estimate.R_sensor_from_body (section 0)
  double residual_rms_nT = 0.0;  // rms over k of |u_k - R_hat h_k| (vector norm)
  double sigma_used_nT = 0.0;    // noise level behind the covariance
  // Residual-structure covariance (sigma_nT <= 0): pooled lag-1 autocorrelation of the vector
  // residuals and the Newey–West lag window (samples; 0 = white).
  double residual_autocorrelation = 0.0;
  int covariance_lag_window = 0;

  bool ok() const { return status == AlignmentStatus::kOk; }
};

// The proper rotation R (det +1) that maximises tr(R^T M) for M = sum_k u_k h_k^T (3x3, any
// units): Wahba's problem solved by the SVD M = U S V^T, R = U diag(1, 1, det(U V^T)) V^T
// (Markley 1988). The rotation of align_procrustes, without its checks and covariance, for
// searches that only need the best rotation of many candidate pairings.
Eigen::Matrix3d wahba_rotation(const Eigen::Matrix3d& M);

// Exact orthogonal Procrustes (preferred).
AlignmentResult align_procrustes(const std::vector<AlignmentPair>& pairs,
                                 const AlignmentOptions& options = {});

struct SmallAngleResult {
  AlignmentResult single_step;   // theta from u - h = [h x] theta; R = Rx Ry Rz(theta)
  AlignmentResult relinearised;  // one more step about single_step's R (use this one)
  Eigen::Vector3d theta_single_step_rad = Eigen::Vector3d::Zero();  // raw LS solution
};

// The paper's small-angle linear LS, single step and re-linearised once.
SmallAngleResult align_small_angle_ls(const std::vector<AlignmentPair>& pairs,
                                      const AlignmentOptions& options = {});

// Exact rotation for a small-angle vector with this module's convention:
// R(theta) = exp(-[theta x]) ≈ I - [theta x].
Eigen::Matrix3d rotation_from_small_angles(const Eigen::Vector3d& theta_rad);

// Options of the online linear KF for the misalignment angles.
struct AlignmentKfOptions {
  double sigma_nT = 3.0;                                // per-axis noise of u
  double initial_sigma_rad = 0.1;                       // prior 1-sigma of each angle (about R_ref)
  Eigen::Matrix3d R_ref = Eigen::Matrix3d::Identity();  // linearisation point
  // Fold the state into R_ref (re-linearise, keep P) when |dtheta| exceeds this (rad);
  // 0 = never (the paper's plain linear KF).
  double relinearise_above_rad = 0.0;
  std::string validate() const;
};

// Everything needed to resume the KF exactly (store it, restore() it after a restart).
struct AlignmentKfState {
  Eigen::Vector3d dtheta_rad = Eigen::Vector3d::Zero();
  Eigen::Matrix3d P_rad2 = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d R_ref = Eigen::Matrix3d::Identity();
  long long n_updates = 0;
};

// Online linear KF for the misalignment angles.
class AlignmentKalmanFilter {
 public:
  using Options = AlignmentKfOptions;
  using State = AlignmentKfState;

  explicit AlignmentKalmanFilter(const Options& options = {});

  // One measurement; P_att_body_rad2 = attitude-knowledge covariance (zero if unknown).
  // Returns false (state unchanged) for non-finite input.
  bool update(const Eigen::Vector3d& u_sensor_nT, const Eigen::Vector3d& h_body_nT,
              const Eigen::Matrix3d& P_att_body_rad2 = Eigen::Matrix3d::Zero());
  // R_ref <- rotation(dtheta) R_ref, dtheta <- 0 (P kept: first-order equivalent).
  void relinearise();

  Eigen::Matrix3d R_sensor_from_body() const;  // rotation(dtheta) R_ref
  AlignmentEstimate estimate() const;          // R, P, n_samples
  const State& state() const { return state_; }
  void restore(const State& s) { state_ = s; }

 private:
  Options options_;
  State state_;
};

struct JointAlignmentOptions {
  AlignmentOptions procrustes;  // used for each R step and the final covariance
  int max_iterations = 500;
  double tolerance_rad = 1e-12;  // stop when R changes by less than this angle
};

struct JointAlignmentResult {
  AlignmentResult alignment;  // R_hat; covariance conditional on f (f treated as known)
  Eigen::Vector3d field_ref_nT = Eigen::Vector3d::Zero();  // constant field, reference frame
  int iterations = 0;
};

// Joint estimate of R_sensor_from_body and a constant reference-frame field f from
// u_k ≈ R A_k f, A_k = A_body_from_ref (known attitudes). Starts from R = I.
JointAlignmentResult align_with_unknown_reference(
    const std::vector<Eigen::Vector3d>& u_sensor_nT,
    const std::vector<Eigen::Matrix3d>& A_body_from_ref, const JointAlignmentOptions& options = {});

}  // namespace magcal
