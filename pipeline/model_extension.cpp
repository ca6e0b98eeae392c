#include "pipeline/model_extension.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>

#include "pipeline/hac_covariance.hpp"
#include "pipeline/outer_product_sum.hpp"
#include "pipeline/scalar_measurement.hpp"

namespace magcal {
namespace {

// Samples within kTurnDeadbandSigmas noise sigmas of the running extreme do not end a run: a
// reversal shows only once the axis has moved this far back (see the header).
constexpr double kTurnDeadbandSigmas = 4.0;
// The turning point is fitted to the samples within this many noise sigmas of the extreme
// (measured, fast spin and paper scenarios: 12-20 sigmas place it best; 8 leaves too few samples,
// 32 spans more than a parabola describes).
constexpr double kTurnWindowSigmas = 16.0;
// And to at most this many samples on either side: the fit is local, and on data noisier than
// the nominal sigma (turns every few samples, each window spanning many) the cost stays
// O(n kMaxTurnWindowSamples) (BROAD lab recording, 53 000 samples: alignment_test 11 s
// uncapped, 1.6 s capped, 1.4 s with the sample-to-sample signs). The cap leaves the paper and
// fast-spin Monte-Carlo figures unchanged to the third decimal.
constexpr std::size_t kMaxTurnWindowSamples = 32;

// One turning point of y_axis at its run's extreme m, for the run before it with sign `before`.
// Where it lies is fitted (least squares) to the samples around m within window_nT of y(m)
// (contiguous, from `first` on): a parabola plus a step e s_k, s_k = +1 up to the last sample c
// of the old run and -1 after; the step is the hysteresis itself, which jumps y by 2 eta at the
// turn (a parabola alone puts the turn early: measured 1.8 % of the spin axis's signs wrong
// against 0.2 %). Each c has the Gaussian likelihood exp(-RSS_c / (2 sigma^2)); the samples of
// the window get their expected sign under it, before (2 P(c >= k) - 1), appended to `expected`
// (regression calibration: the error of an estimated regressor then has mean zero given the
// data; measured against the hard sign at the most likely c, paper scenario 50 x 12 h: bias MSE
// 0.75 vs 0.83 nT^2, pitch RMS(err/sigma) 0.88 vs 1.05). Returns the most likely c (m when the
// window is too short to fit).
std::size_t turning_point(const std::vector<Eigen::Vector3d>& y, int axis, std::size_t first,
                          std::size_t m, double window_nT, double sigma_nT, double before,
                          std::vector<std::pair<std::size_t, double>>* expected) {
  const double vm = y[m](axis);
  std::size_t left = m, right = m;
  while (left > first && m - left < kMaxTurnWindowSamples &&
         std::abs(y[left - 1](axis) - vm) <= window_nT) {
    --left;
  }
  while (right + 1 < y.size() && right - m < kMaxTurnWindowSamples &&
         std::abs(y[right + 1](axis) - vm) <= window_nT) {
    ++right;
  }
  if (right < left + 4) return m;
  // rss[c - left] for c = left + 1 .. right - 2 (at least two samples on each side). The normal
  // equations of f_k = (1, u, u^2, s_k) split into window totals and, for the s_k = 2 [k <= c] - 1
  // column, running sums up to c: O(1) per c. u in units of the window's half width.
  const double scale = 0.5 * static_cast<double>(right - left);
  Eigen::Matrix4d sums = Eigen::Matrix4d::Zero();  // sum g g^T, g = (1, u, u^2, v)
  for (std::size_t k = left; k <= right; ++k) {
    const double u = (static_cast<double>(k) - static_cast<double>(m)) / scale;
    const Eigen::Vector4d g(1.0, u, u * u, y[k](axis) - vm);
    sums += g * g.transpose();
  }
  std::vector<double> rss(right - left, std::numeric_limits<double>::infinity());
  std::size_t best = m;
  double best_rss = std::numeric_limits<double>::infinity();
  Eigen::Vector4d up_to_c = Eigen::Vector4d::Zero();  // sum_{k <= c} g
  for (std::size_t c = left; c + 1 < right; ++c) {
    const double u = (static_cast<double>(c) - static_cast<double>(m)) / scale;
    up_to_c += Eigen::Vector4d(1.0, u, u * u, y[c](axis) - vm);
    if (c == left) continue;
    const Eigen::Vector4d with_s = 2.0 * up_to_c - sums.col(0);  // sum s g
    Eigen::Matrix4d normal;
    normal.topLeftCorner<3, 3>() = sums.topLeftCorner<3, 3>();
    normal.block<3, 1>(0, 3) = with_s.head<3>();
    normal.block<1, 3>(3, 0) = with_s.head<3>().transpose();
    normal(3, 3) = sums(0, 0);
    Eigen::Vector4d rhs;
    rhs << sums.block<3, 1>(0, 3), with_s(3);
    const Eigen::LDLT<Eigen::Matrix4d> ldlt(normal);
    if (ldlt.info() != Eigen::Success) continue;
    rss[c - left] = sums(3, 3) - rhs.dot(ldlt.solve(rhs));
    if (rss[c - left] < best_rss) {
      best_rss = rss[c - left];
      best = c;
    }
  }
  if (!std::isfinite(best_rss)) return m;
  // P(c >= k) by a running sum from the right.
  std::vector<double> weight(rss.size());
  double total = 0.0;
  const double variance = sigma_nT * sigma_nT;
  for (std::size_t j = 0; j < rss.size(); ++j) {
    weight[j] = std::exp(-(rss[j] - best_rss) / (2.0 * variance));
    total += weight[j];
  }
  double at_or_after = 0.0;
  for (std::size_t k = right; k >= left + 1; --k) {
    if (k - left < weight.size()) at_or_after += weight[k - left];
    expected->emplace_back(k, before * (2.0 * at_or_after / total - 1.0));
  }
  return best;
}

// Hysteresis signs of one axis (see ExtensionInputs): runs between turning points found with a
// deadband of deadband_nT, each turning point located by turning_point().
void hysteresis_signs(const std::vector<Eigen::Vector3d>& y, int axis, double deadband_nT,
                      double window_nT, double sigma_nT, std::vector<Eigen::Vector3d>* signs) {
  const std::size_t n = y.size();
  double sign = 1.0;    // of the current run; +1 before any change
  std::size_t run = 0;  // first sample of the current run
  int direction = 0;    // 0 until the first run is known
  std::size_t i_max = 0, i_min = 0;
  std::vector<std::pair<std::size_t, double>> expected;  // around the turns, set last
  // The run up to (and including) the extreme at m gets the sign `before`; the next starts after
  // the turning point.
  auto end_run = [&](std::size_t m, double before) {
    const std::size_t last = turning_point(y, axis, run, m, window_nT, sigma_nT, before, &expected);
    // A turning point fitted beyond the samples seen so far can leave run at the end: never
    // past it.
    const std::size_t next = std::min(y.size(), std::max(run + 1, last + 1));
    for (std::size_t j = run; j < next; ++j) (*signs)[j](axis) = before;
    run = next;
    sign = -before;
  };
  for (std::size_t k = 0; k < n; ++k) {
    const double v = y[k](axis);
    if (direction >= 0 && v >= y[i_max](axis)) i_max = k;
    if (direction <= 0 && v <= y[i_min](axis)) i_min = k;
    if (direction >= 0 && y[i_max](axis) - v > deadband_nT) {
      end_run(i_max, 1.0);
      direction = -1;
      i_min = k;
    } else if (direction <= 0 && v - y[i_min](axis) > deadband_nT) {
      end_run(i_min, -1.0);
      direction = 1;
      i_max = k;
    }
  }
  for (std::size_t j = run; j < n; ++j) (*signs)[j](axis) = sign;
  for (const auto& [k, s] : expected) (*signs)[k](axis) = s;
}

}  // namespace

ExtensionInputs extension_inputs(const SampleSet& samples, const CalibrationParameters& p,
                                 double sigma_nT) {
  const std::size_t n = samples.size();
  ExtensionInputs in;
  in.y_nT.resize(n);
  in.signs.assign(n, Eigen::Vector3d::Ones());
  for (std::size_t k = 0; k < n; ++k) in.y_nT[k] = p.apply(samples[k].b_sensor_nT);
  for (int axis = 0; axis < 3; ++axis) {
    hysteresis_signs(in.y_nT, axis, kTurnDeadbandSigmas * sigma_nT, kTurnWindowSigmas * sigma_nT,
                     sigma_nT, &in.signs);
  }
  return in;
}

std::vector<Vector6d> model_extension_regressors(const ExtensionInputs& in) {
  std::vector<Vector6d> phi(in.y_nT.size());
  for (std::size_t k = 0; k < phi.size(); ++k) {
    const Eigen::Vector3d& y = in.y_nT[k];
    phi[k] << 2.0 * y.cwiseAbs2().cwiseProduct(y), 2.0 * y.cwiseProduct(in.signs[k]);
  }
  return phi;
}

std::vector<Eigen::Vector3d> extension_corrected_vectors(const ExtensionInputs& in,
                                                         const Eigen::Vector3d& k_per_nT,
                                                         const Eigen::Vector3d& eta_nT) {
  std::vector<Eigen::Vector3d> x(in.y_nT.size());
  for (std::size_t k = 0; k < x.size(); ++k) {
    const Eigen::Vector3d& y = in.y_nT[k];
    x[k] = y - k_per_nT.cwiseProduct(y.cwiseAbs2()) - eta_nT.cwiseProduct(in.signs[k]);
  }
  return x;
}

bool bic_prefers_more_parameters(double chi2_base, double chi2_more, int n_samples,
                                 int n_extra_parameters) {
  if (!(chi2_base > 0.0) || !(chi2_more > 0.0) || n_samples < 20) return false;
  const double n = static_cast<double>(n_samples);
  return n * std::log(chi2_base / chi2_more) > n_extra_parameters * std::log(n);
}

bool bic_prefers_extension(double chi2_base, double chi2_extended, int n_samples) {
  return bic_prefers_more_parameters(chi2_base, chi2_extended, n_samples, 6);
}

bool extension_effects_small(const Vector6d& a, double mean_h_nT, double max_fraction) {
  const double limit_nT = max_fraction * mean_h_nT;
  return (a.head<3>().cwiseAbs() * (mean_h_nT * mean_h_nT)).maxCoeff() <= limit_nT &&
         a.tail<3>().cwiseAbs().maxCoeff() <= limit_nT;
}

ExtensionFitAtEstimate fit_extension_at_estimate(const SampleSet& samples,
                                                 const ExtensionInputs& in, double sigma_nT) {
  ExtensionFitAtEstimate fit;
  const std::size_t n = samples.size();
  if (n < 20 || in.y_nT.size() != n) return fit;
  const std::vector<Vector6d> phi = model_extension_regressors(in);
  const double mu = scalar_noise_mean(sigma_nT);
  std::vector<double> r(n), w(n);
  OuterProductSum<7> normal;  // sum w [phi; r] [phi; r]^T
  double mean_h_nT = 0.0;
  for (std::size_t k = 0; k < n; ++k) {
    const double h = samples[k].h_body_nT.norm();
    mean_h_nT += h;
    r[k] = in.y_nT[k].squaredNorm() - h * h - mu;
    w[k] = 1.0 / scalar_noise_variance(in.y_nT[k], sigma_nT);
    Eigen::Matrix<double, 7, 1> row;
    row << phi[k], r[k];
    normal.add(std::sqrt(w[k]) * row);
  }
  mean_h_nT /= static_cast<double>(n);
  const Eigen::Matrix<double, 7, 7> sum = normal.sum();
  const Matrix6d F = sum.topLeftCorner<6, 6>();
  const Vector6d d = F.diagonal();
  if (!(d.minCoeff() > 0.0) || !d.allFinite()) return fit;
  // k (1/nT) and eta (nT) columns differ by ~1e9: solve in the diagonally scaled form.
  const Vector6d s_inv = d.cwiseSqrt().cwiseInverse();
  const Eigen::SelfAdjointEigenSolver<Matrix6d> eig(s_inv.asDiagonal() * F * s_inv.asDiagonal());
  if (!(eig.eigenvalues()(0) > 1e-12 * eig.eigenvalues()(5))) return fit;
  const Matrix6d F_inv = s_inv.asDiagonal() * eig.eigenvectors() *
                         eig.eigenvalues().cwiseInverse().asDiagonal() *
                         eig.eigenvectors().transpose() * s_inv.asDiagonal();
  fit.a = F_inv * sum.block<6, 1>(0, 6);
  std::vector<Vector6d> scores(n);
  std::vector<double> e(n);
  double chi2_extended = 0.0;
  for (std::size_t k = 0; k < n; ++k) {
    const double residual = r[k] - phi[k].dot(fit.a);
    chi2_extended += w[k] * residual * residual;
    scores[k] = (w[k] * residual) * phi[k];
    e[k] = std::sqrt(w[k]) * residual;
  }
  const double dof = static_cast<double>(n) - 6.0;
  const int lag = bartlett_lag_window(lag1_autocorrelation(e), static_cast<int>(n));
  const Matrix6d hac =
      F_inv * newey_west_meat<6>(scores, lag) * F_inv * (static_cast<double>(n) / dof);
  fit.covariance = covariance_not_below(F_inv, hac);
  fit.supported =
      fit.a.allFinite() && bic_prefers_extension(sum(6, 6), chi2_extended, static_cast<int>(n));
  fit.used = fit.supported && extension_effects_small(fit.a, mean_h_nT);
  return fit;
}

}  // namespace magcal
