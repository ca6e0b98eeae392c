// Stage 2 alignment: Procrustes, small-angle LS, linear KF, joint (R, f). Math in the header.
#include "pipeline/alignment.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/SVD>

#include "pipeline/hac_covariance.hpp"

namespace magcal {

namespace {

bool finite(const Eigen::Vector3d& v) {
  return v.allFinite();
}

// Common checks; fills status/message and returns false when the pairs are unusable.
bool check_pairs(const std::vector<AlignmentPair>& pairs, const AlignmentOptions& options,
                 AlignmentResult& out) {
  out.estimate.n_samples = static_cast<int>(pairs.size());
  if (const std::string err = options.validate(); !err.empty()) {
    out.status = AlignmentStatus::kInvalidInput;
    out.message = err;
    return false;
  }
  // One pass: the finiteness check, sum |h|^2 and the information about the identity.
  double h2_sum = 0.0;
  Eigen::Matrix3d J = Eigen::Matrix3d::Zero();
  for (const auto& p : pairs) {
    if (!finite(p.u_sensor_nT) || !finite(p.h_body_nT)) {
      out.status = AlignmentStatus::kInvalidInput;
      out.message = "non-finite alignment input";
      return false;
    }
    h2_sum += p.h_body_nT.squaredNorm();
    J.noalias() -= p.h_body_nT * p.h_body_nT.transpose();
  }
  J.diagonal().array() += h2_sum;
  if (static_cast<int>(pairs.size()) < options.min_samples) {
    out.status = AlignmentStatus::kTooFewSamples;
    out.message = "alignment needs at least " + std::to_string(options.min_samples) +
                  " samples with a reference direction, got " + std::to_string(pairs.size());
    return false;
  }
  const double min_eig = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(J).eigenvalues()(0);
  if (!(h2_sum > 0.0) || min_eig / h2_sum < options.min_information_ratio) {
    out.status = AlignmentStatus::kUnobservable;
    out.message = "reference field directions do not span two dimensions";
    return false;
  }
  return true;
}

// Residuals, sigma and covariance about R (sensor-frame dtheta), and the angle outputs.
void finish(const std::vector<AlignmentPair>& pairs, const Eigen::Matrix3d& R,
            const AlignmentOptions& options, AlignmentResult& out) {
  const std::size_t n = pairs.size();
  std::vector<Eigen::Vector3d> residuals(n), scores(n);
  double ss = 0.0;
  // The information is accumulated in the residuals' pass: finish() runs once per candidate
  // rotation of the lag search and of the axis diagnosis, so a second pass would double its cost.
  // Information of dtheta per unit noise variance: sum_k (|g|^2 I - g g^T) = sum [g x]^T [g x].
  Eigen::Matrix3d information = Eigen::Matrix3d::Zero();
  for (std::size_t k = 0; k < n; ++k) {
    const Eigen::Vector3d g = R * pairs[k].h_body_nT;
    residuals[k] = pairs[k].u_sensor_nT - g;
    scores[k] = cross_matrix(g).transpose() * residuals[k];  // J_k^T e_k
    ss += residuals[k].squaredNorm();
    information.noalias() -= g * g.transpose();
    information.diagonal().array() += g.squaredNorm();
  }
  const auto nd = static_cast<double>(n);
  out.residual_rms_nT = std::sqrt(ss / nd);
  out.sigma_used_nT =
      options.sigma_nT > 0.0 ? options.sigma_nT : std::sqrt(ss / std::max(1.0, 3.0 * nd - 3.0));
  const Eigen::Matrix3d F_inv = information.inverse();
  Eigen::Matrix3d covariance = out.sigma_used_nT * out.sigma_used_nT * F_inv;
  out.residual_autocorrelation = 0.0;
  out.covariance_lag_window = 0;
  if (!(options.sigma_nT > 0.0)) {
    out.residual_autocorrelation = lag1_autocorrelation(residuals);
    out.covariance_lag_window =
        bartlett_lag_window(out.residual_autocorrelation, static_cast<int>(n));
    const Eigen::Matrix3d omega = newey_west_meat<3>(scores, out.covariance_lag_window);
    covariance = covariance_not_below<3>(covariance, F_inv * omega * F_inv);
  }
  out.estimate.R_sensor_from_body = R;
  out.estimate.angle_covariance_rad2 = covariance;
  out.rpy = roll_pitch_yaw_from_dcm(R);
  out.status = AlignmentStatus::kOk;
  out.message.clear();
}

Eigen::Matrix3d procrustes_rotation(const std::vector<AlignmentPair>& pairs) {
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (const auto& p : pairs) M += p.u_sensor_nT * p.h_body_nT.transpose();
  return wahba_rotation(M);
}

// Linear LS for dtheta in u_k - R h_k = [(R h_k) x] dtheta.
Eigen::Vector3d small_angle_step(const std::vector<AlignmentPair>& pairs,
                                 const Eigen::Matrix3d& R) {
  Eigen::Matrix3d N = Eigen::Matrix3d::Zero();
  Eigen::Vector3d rhs = Eigen::Vector3d::Zero();
  for (const auto& p : pairs) {
    const Eigen::Vector3d g = R * p.h_body_nT;
    const Eigen::Matrix3d H = cross_matrix(g);
    N.noalias() += H.transpose() * H;
    rhs.noalias() += H.transpose() * (p.u_sensor_nT - g);
  }
  return N.ldlt().solve(rhs);
}

}  // namespace

Eigen::Matrix3d wahba_rotation(const Eigen::Matrix3d& M) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d& U = svd.matrixU();
  const Eigen::Matrix3d& V = svd.matrixV();
  // The sign flip on the smallest singular direction turns a best reflection into the best
  // proper rotation (det +1).
  const double d = (U * V.transpose()).determinant() < 0.0 ? -1.0 : 1.0;
  return U * Eigen::Vector3d(1.0, 1.0, d).asDiagonal() * V.transpose();
}

std::vector<AlignmentPair> make_alignment_pairs(const SampleSet& samples,
                                                const std::vector<Eigen::Vector3d>& u_sensor_nT,
                                                std::vector<int64_t>* utime) {
  assert(u_sensor_nT.size() == samples.size());
  std::vector<AlignmentPair> pairs;
  pairs.reserve(samples.size());
  if (utime) utime->clear();
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    if (!s.has_reference_direction || !finite(u_sensor_nT[k]) || !finite(s.h_body_nT)) continue;
    pairs.push_back({u_sensor_nT[k], s.h_body_nT});
    if (utime) utime->push_back(s.utime);
  }
  return pairs;
}

std::vector<AlignmentPair> make_alignment_pairs(const SampleSet& samples,
                                                const CalibrationParameters& params) {
  std::vector<Eigen::Vector3d> u(samples.size());
  for (std::size_t k = 0; k < samples.size(); ++k) u[k] = params.apply(samples[k].b_sensor_nT);
  return make_alignment_pairs(samples, u);
}

Eigen::Matrix3d alignment_covariance_from_stage1(const SampleSet& samples, const Eigen::Matrix3d& R,
                                                 const Matrix9d& parameter_covariance,
                                                 const ExtensionInputs* extension,
                                                 const Matrix6d& extension_covariance) {
  assert(!extension || extension->y_nT.size() == samples.size());
  Eigen::Matrix3d F = Eigen::Matrix3d::Zero();
  Eigen::Matrix<double, 3, 9> JtUp = Eigen::Matrix<double, 3, 9>::Zero();
  Eigen::Matrix<double, 3, 6> JtUa = Eigen::Matrix<double, 3, 6>::Zero();
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    if (!s.has_reference_direction || !finite(s.b_sensor_nT) || !finite(s.h_body_nT)) continue;
    const Eigen::Vector3d g = R * s.h_body_nT;
    const Eigen::Matrix3d J = cross_matrix(g);
    const Eigen::Vector3d& B = s.b_sensor_nT;
    // du/dp for u = (I + D) B - b, p = [b1 b2 b3 D11 D22 D33 D12 D13 D23].
    Eigen::Matrix<double, 3, 9> dUp = Eigen::Matrix<double, 3, 9>::Zero();
    dUp.leftCols<3>() = -Eigen::Matrix3d::Identity();
    dUp(0, 3) = B(0);
    dUp(1, 4) = B(1);
    dUp(2, 5) = B(2);
    dUp(0, 6) = B(1), dUp(1, 6) = B(0);
    dUp(0, 7) = B(2), dUp(2, 7) = B(0);
    dUp(1, 8) = B(2), dUp(2, 8) = B(1);
    F.noalias() += J.transpose() * J;
    JtUp.noalias() += J.transpose() * dUp;
    if (extension) {
      Eigen::Matrix<double, 3, 6> dUa = Eigen::Matrix<double, 3, 6>::Zero();
      for (int i = 0; i < 3; ++i) {
        dUa(i, i) = -extension->y_nT[k](i) * extension->y_nT[k](i);
        dUa(i, 3 + i) = -extension->signs[k](i);
      }
      JtUa.noalias() += J.transpose() * dUa;
    }
  }
  if (!(F.trace() > 0.0)) return Eigen::Matrix3d::Zero();
  const Eigen::LDLT<Eigen::Matrix3d> F_ldlt(F);
  const Eigen::Matrix<double, 3, 9> Gp = F_ldlt.solve(JtUp);
  Eigen::Matrix3d C = Gp * parameter_covariance * Gp.transpose();
  if (extension) {
    const Eigen::Matrix<double, 3, 6> Ga = F_ldlt.solve(JtUa);
    C += Ga * extension_covariance * Ga.transpose();
  }
  return 0.5 * (C + C.transpose());
}

std::string AlignmentOptions::validate() const {
  if (!std::isfinite(sigma_nT)) return "alignment sigma_nT must be finite";
  if (min_samples < 2) return "alignment min_samples must be >= 2";
  if (!(min_information_ratio >= 0.0) || min_information_ratio > 2.0 / 3.0)
    return "alignment min_information_ratio must be in [0, 2/3]";
  return {};
}

const char* to_string(AlignmentStatus s) {
  switch (s) {
    case AlignmentStatus::kOk:
      return "ok";
    case AlignmentStatus::kTooFewSamples:
      return "too_few_samples";
    case AlignmentStatus::kInvalidInput:
      return "invalid_input";
    case AlignmentStatus::kUnobservable:
      return "unobservable";
    case AlignmentStatus::kNotConverged:
      return "not_converged";
  }
  return "unknown";
}

Eigen::Matrix3d rotation_from_small_angles(const Eigen::Vector3d& theta_rad) {
  const double angle = theta_rad.norm();
  const Eigen::Matrix3d K = cross_matrix(theta_rad);
  if (angle < 1e-8) return Eigen::Matrix3d::Identity() - K + 0.5 * K * K;
  // exp(-K) = I - sin(a)/a K + (1 - cos(a))/a^2 K^2 (Rodrigues)
  return Eigen::Matrix3d::Identity() - (std::sin(angle) / angle) * K +
         ((1.0 - std::cos(angle)) / (angle * angle)) * K * K;
}

AlignmentResult align_procrustes(const std::vector<AlignmentPair>& pairs,
                                 const AlignmentOptions& options) {
  AlignmentResult out;
  if (!check_pairs(pairs, options, out)) return out;
  finish(pairs, procrustes_rotation(pairs), options, out);
  return out;
}

SmallAngleResult align_small_angle_ls(const std::vector<AlignmentPair>& pairs,
                                      const AlignmentOptions& options) {
  SmallAngleResult out;
  if (!check_pairs(pairs, options, out.single_step)) {
    out.relinearised = out.single_step;
    return out;
  }
  // Single step about I: u - h = [h x] theta, theta read as (roll, pitch, yaw) as in the paper.
  out.theta_single_step_rad = small_angle_step(pairs, Eigen::Matrix3d::Identity());
  const Eigen::Vector3d& t = out.theta_single_step_rad;
  const Eigen::Matrix3d R1 = dcm_from_roll_pitch_yaw({t(0), t(1), t(2)});
  finish(pairs, R1, options, out.single_step);
  // Re-linearise once about R1: the remaining error is second order in the step.
  const Eigen::Matrix3d R2 = rotation_from_small_angles(small_angle_step(pairs, R1)) * R1;
  out.relinearised = out.single_step;
  finish(pairs, R2, options, out.relinearised);
  return out;
}

// ---------------------------------------------------------------------------------------------
// Online linear KF

std::string AlignmentKfOptions::validate() const {
  if (!(sigma_nT > 0.0) || !std::isfinite(sigma_nT)) return "alignment KF sigma_nT must be > 0";
  if (!(initial_sigma_rad > 0.0) || !std::isfinite(initial_sigma_rad))
    return "alignment KF initial_sigma_rad must be > 0";
  if (!R_ref.allFinite() || std::abs(R_ref.determinant() - 1.0) > 1e-6 ||
      !(R_ref * R_ref.transpose()).isIdentity(1e-6))
    return "alignment KF R_ref must be a rotation matrix";
  if (!(relinearise_above_rad >= 0.0)) return "alignment KF relinearise_above_rad must be >= 0";
  return {};
}

AlignmentKalmanFilter::AlignmentKalmanFilter(const Options& options) : options_(options) {
  assert(options_.validate().empty());
  state_.R_ref = options_.R_ref;
  state_.P_rad2 =
      options_.initial_sigma_rad * options_.initial_sigma_rad * Eigen::Matrix3d::Identity();
}

bool AlignmentKalmanFilter::update(const Eigen::Vector3d& u_sensor_nT,
                                   const Eigen::Vector3d& h_body_nT,
                                   const Eigen::Matrix3d& P_att_body_rad2) {
  if (!finite(u_sensor_nT) || !finite(h_body_nT) || !P_att_body_rad2.allFinite()) return false;
  const Eigen::Vector3d g = state_.R_ref * h_body_nT;
  const Eigen::Matrix3d H = cross_matrix(g);
  // Attitude error phi (body): h_true = h + h x phi, so u gains R [h x] phi.
  const Eigen::Matrix3d G = state_.R_ref * cross_matrix(h_body_nT);
  const Eigen::Matrix3d Rn = options_.sigma_nT * options_.sigma_nT * Eigen::Matrix3d::Identity() +
                             G * P_att_body_rad2 * G.transpose();
  const Eigen::Matrix3d& P = state_.P_rad2;
  const Eigen::Matrix3d S = H * P * H.transpose() + Rn;
  const Eigen::LLT<Eigen::Matrix3d> llt(S);
  if (llt.info() != Eigen::Success) return false;
  const Eigen::Matrix3d K = llt.solve(H * P).transpose();  // P H^T S^-1 (S, P symmetric)
  const Eigen::Vector3d innovation = u_sensor_nT - g - H * state_.dtheta_rad;
  state_.dtheta_rad += K * innovation;
  // Joseph form keeps P symmetric positive definite.
  const Eigen::Matrix3d IKH = Eigen::Matrix3d::Identity() - K * H;
  Eigen::Matrix3d P_new = IKH * P * IKH.transpose() + K * Rn * K.transpose();
  state_.P_rad2 = 0.5 * (P_new + P_new.transpose());
  ++state_.n_updates;
  if (options_.relinearise_above_rad > 0.0 &&
      state_.dtheta_rad.norm() > options_.relinearise_above_rad)
    relinearise();
  return true;
}

void AlignmentKalmanFilter::relinearise() {
  state_.R_ref = rotation_from_small_angles(state_.dtheta_rad) * state_.R_ref;
  state_.dtheta_rad.setZero();
}

Eigen::Matrix3d AlignmentKalmanFilter::R_sensor_from_body() const {
  return rotation_from_small_angles(state_.dtheta_rad) * state_.R_ref;
}

AlignmentEstimate AlignmentKalmanFilter::estimate() const {
  AlignmentEstimate e;
  e.R_sensor_from_body = R_sensor_from_body();
  e.angle_covariance_rad2 = state_.P_rad2;
  e.n_samples = static_cast<int>(state_.n_updates);
  return e;
}

// ---------------------------------------------------------------------------------------------
// Joint R and constant reference field

JointAlignmentResult align_with_unknown_reference(
    const std::vector<Eigen::Vector3d>& u_sensor_nT,
    const std::vector<Eigen::Matrix3d>& A_body_from_ref, const JointAlignmentOptions& options) {
  JointAlignmentResult out;
  AlignmentResult& a = out.alignment;
  if (u_sensor_nT.size() != A_body_from_ref.size() || options.max_iterations < 1 ||
      !(options.tolerance_rad >= 0.0)) {
    a.status = AlignmentStatus::kInvalidInput;
    a.message = u_sensor_nT.size() != A_body_from_ref.size()
                    ? "u and attitude arrays differ in length"
                    : "invalid joint alignment options";
    return out;
  }
  for (std::size_t k = 0; k < u_sensor_nT.size(); ++k) {
    if (!finite(u_sensor_nT[k]) || !A_body_from_ref[k].allFinite()) {
      a.status = AlignmentStatus::kInvalidInput;
      a.message = "non-finite joint alignment input";
      return out;
    }
  }
  const auto n = static_cast<double>(u_sensor_nT.size());
  std::vector<AlignmentPair> pairs(u_sensor_nT.size());
  auto field_given = [&](const Eigen::Matrix3d& R) {
    Eigen::Vector3d f = Eigen::Vector3d::Zero();
    for (std::size_t k = 0; k < pairs.size(); ++k)
      f += A_body_from_ref[k].transpose() * (R.transpose() * u_sensor_nT[k]);
    return Eigen::Vector3d(f / std::max(1.0, n));
  };
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d f = field_given(R);
  bool converged = false;
  for (out.iterations = 1; out.iterations <= options.max_iterations; ++out.iterations) {
    for (std::size_t k = 0; k < pairs.size(); ++k)
      pairs[k] = {u_sensor_nT[k], A_body_from_ref[k] * f};
    AlignmentResult step = align_procrustes(pairs, options.procrustes);
    if (!step.ok()) {
      out.alignment = step;
      return out;
    }
    const Eigen::Matrix3d R_new = step.estimate.R_sensor_from_body;
    const double change = rotation_angle(R_new * R.transpose());
    R = R_new;
    f = field_given(R);
    if (change <= options.tolerance_rad) {
      converged = true;
      break;
    }
  }
  out.iterations = std::min(out.iterations, options.max_iterations);
  for (std::size_t k = 0; k < pairs.size(); ++k)
    pairs[k] = {u_sensor_nT[k], A_body_from_ref[k] * f};
  finish(pairs, R, options.procrustes, a);
  out.field_ref_nT = f;
  if (!converged) {
    a.status = AlignmentStatus::kNotConverged;
    a.message = "joint alignment did not converge in " + std::to_string(options.max_iterations) +
                " iterations";
  }
  return out;
}

}  // namespace magcal
