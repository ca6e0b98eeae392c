#include "pipeline/orbit_synchronous_bias.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <vector>

#include <Eigen/Cholesky>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/model_extension.hpp"
#include "pipeline/scalar_measurement.hpp"
#include "pipeline/scaled_inverse.hpp"

namespace magcal {

namespace {

// [b, D] (9), the sensor-model extension (6: pipeline/model_extension.hpp), the swing (6).
constexpr int kModel = 15;
constexpr int kAll = 21;
using ModelRow = Eigen::Matrix<double, 1, kModel>;
using ModelMatrix = Eigen::Matrix<double, kModel, kModel>;
using AllMatrix = Eigen::Matrix<double, kAll, kAll>;

}  // namespace

UnresolvedBiasSwing unresolved_orbit_synchronous_bias_swing(
    const SampleSet& samples, const CalibrationResult& fit, double sigma_nT,
    const OrbitSynchronousBiasOptions& options) {
  UnresolvedBiasSwing out;
  if (samples.size() < 16) return out;
  const auto [first, last] = std::minmax_element(
      samples.begin(), samples.end(),
      [](const CalibrationSample& a, const CalibrationSample& b) { return a.utime < b.utime; });
  const double span_s = static_cast<double>(last->utime - first->utime) * 1e-6;
  if (!(span_s >= options.max_period_s) || !(options.min_period_s > 0.0)) return out;

  const double scale = std::isfinite(fit.noise_scale) ? std::max(1.0, fit.noise_scale) : 1.0;
  const double noise_sigma_nT = sigma_nT * scale;
  const double ar1 = ar1_variance_factor(fit.residual_autocorrelation);

  // Per sample: sqrt(w) [H, phi] (the 9-parameter row and the extension's columns, which take an
  // orbit-periodic swing too: the hysteresis term is a square wave of the orbit in nadir), sqrt(w)
  // times the scalar residual |y|^2 - |h|^2 at the fit (the extension, when fitted, removed from
  // y) and its time; the 15x15 block once.
  const ExtensionInputs in = extension_inputs(samples, fit.parameters, sigma_nT);
  const std::vector<Eigen::Vector3d> y_nT =
      fit.has_nonlinearity ? extension_corrected_vectors(in, fit.nonlinearity_k3, fit.hysteresis_nT)
                           : in.y_nT;
  const std::vector<Vector6d> phi = model_extension_regressors(in);
  std::vector<ModelRow> rows;
  std::vector<double> residuals, t_s;
  rows.reserve(samples.size());
  residuals.reserve(samples.size());
  t_s.reserve(samples.size());
  ModelMatrix F_model = ModelMatrix::Zero();
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const CalibrationSample& s = samples[k];
    const Eigen::Vector3d& y = y_nT[k];
    const double w = 1.0 / (scalar_noise_variance(y, noise_sigma_nT) * ar1);
    ModelRow h;
    h << scalar_measurement_jacobian_at(in.y_nT[k], s.b_sensor_nT), phi[k].transpose();
    h *= std::sqrt(w);
    const double r = std::sqrt(w) * (y.squaredNorm() - s.h_body_nT.squaredNorm());
    if (!h.allFinite() || !std::isfinite(r)) continue;
    F_model.selfadjointView<Eigen::Lower>().rankUpdate(h.transpose());
    rows.push_back(h);
    residuals.push_back(r);
    t_s.push_back(static_cast<double>(s.utime - first->utime) * 1e-6);
  }
  F_model = F_model.selfadjointView<Eigen::Lower>();
  ModelMatrix P_model;
  if (!scaled_inverse<kModel>(F_model, &P_model, nullptr)) return out;
  // The model's own Gauss-Newton step: not zero where the published parameters are not the
  // least-squares optimum (the estimator-bias correction moved them); only what the swing adds to
  // it counts below.
  Eigen::Matrix<double, kModel, 1> model_gradient = Eigen::Matrix<double, kModel, 1>::Zero();
  for (std::size_t k = 0; k < rows.size(); ++k)
    model_gradient += rows[k].transpose() * residuals[k];
  const Eigen::Matrix<double, kModel, 1> model_step = P_model * model_gradient;

  // Frequencies 1/16 of a cycle over the window apart. In nadir the estimate is that sensitive
  // to the period: the separation rests on small departures of the field from a first harmonic
  // of the orbit (paper, +-10 nT, 24 h: the x swing 9.5 nT at the true period, 95.65 min, 5.8
  // nT at 96.09 min, 1/4 of a cycle apart).
  const double f_min = 1.0 / options.max_period_s, f_max = 1.0 / options.min_period_s;
  const int n = std::max(2, static_cast<int>(std::ceil((f_max - f_min) * 16.0 * span_s)) + 1);
  const double prior_information = 1.0 / (options.prior_amplitude_nT * options.prior_amplitude_nT);
  struct Period {
    double period_s = 0.0, log_weight = 0.0;
    Eigen::Vector3d added_nT2, amplitude_nT, amplitude_sigma_nT;
  };
  std::vector<Period> periods;
  periods.reserve(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) {
    const double f = f_min + (f_max - f_min) * i / (n - 1);
    const double omega = 2.0 * std::numbers::pi * f;
    AllMatrix F = AllMatrix::Zero();
    F.topLeftCorner<kModel, kModel>() = F_model;
    Eigen::Matrix<double, kModel, 6> cross = Eigen::Matrix<double, kModel, 6>::Zero();
    Eigen::Matrix<double, 6, 6> swing = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, kAll, 1> gradient = Eigen::Matrix<double, kAll, 1>::Zero();
    for (std::size_t k = 0; k < rows.size(); ++k) {
      Eigen::Matrix<double, 6, 1> g;
      g << rows[k].head<3>().transpose() * std::cos(omega * t_s[k]),
          rows[k].head<3>().transpose() * std::sin(omega * t_s[k]);
      cross.noalias() += rows[k].transpose() * g.transpose();
      swing.selfadjointView<Eigen::Lower>().rankUpdate(g);
      gradient.tail<6>() += g * residuals[k];
    }
    gradient.head<kModel>() = model_gradient;
    F.topRightCorner<kModel, 6>() = cross;
    F.bottomLeftCorner<6, kModel>() = cross.transpose();
    F.bottomRightCorner<6, 6>() = swing.selfadjointView<Eigen::Lower>();
    F.bottomRightCorner<6, 6>().diagonal().array() += prior_information;
    AllMatrix P;
    if (!scaled_inverse<kAll>(F, &P, nullptr)) continue;
    // One Gauss-Newton step from the fit (c = s = 0): the swing's posterior mean and the shift of b
    // it brings. The period's weight is its marginal likelihood against no swing,
    //   ln BF = 1/2 g^T P_gg^-1 g + 1/2 ln det P_gg + const   (g = [c; s], P_gg its covariance).
    const Eigen::Matrix<double, kAll, 1> step = P * gradient;
    const Eigen::Matrix<double, 6, 1> g = step.tail<6>();
    const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> P_gg(P.bottomRightCorner<6, 6>());
    if (P_gg.info() != Eigen::Success || !(P_gg.vectorD().array() > 0.0).all()) continue;
    Period period;
    period.period_s = 1.0 / f;
    period.log_weight = 0.5 * g.dot(P_gg.solve(g)) + 0.5 * P_gg.vectorD().array().log().sum();
    for (int a = 0; a < 3; ++a) {
      const int ci = kModel + a, si = kModel + 3 + a;
      const double shift = step(a) - model_step(a);  // of b, by the swing
      period.added_nT2(a) = shift * shift + P(a, a) - P_model(a, a) +
                            0.5 * (g(a) * g(a) + g(3 + a) * g(3 + a) + P(ci, ci) + P(si, si));
      period.amplitude_nT(a) = std::hypot(g(a), g(3 + a));
      period.amplitude_sigma_nT(a) = std::sqrt(0.5 * (P(ci, ci) + P(si, si)));
    }
    periods.push_back(period);
  }
  if (periods.empty()) return out;
  // The period unknown: the average over the periods, weighted by their posterior probability
  // (a uniform prior over the grid). Where no swing is present the weights spread and the noise
  // of one period's estimate is not picked out of many (the largest of 50 would be); a real swing
  // takes the weight at its period.
  const auto best = std::max_element(
      periods.begin(), periods.end(),
      [](const Period& a, const Period& b) { return a.log_weight < b.log_weight; });
  double total = 0.0;
  for (const Period& p : periods) {
    const double w = std::exp(p.log_weight - best->log_weight);
    total += w;
    out.variance_nT2 += w * p.added_nT2.cwiseMax(0.0);
  }
  out.variance_nT2 /= total;
  // Whether there is a swing at all: its Bayes factor against none, averaged over the periods
  // (ln BF = the log weight - 1/2 ln det of the prior's covariance, 6 ln prior_amplitude_nT), and
  // the posterior probability from the stated prior odds. The variance the swing adds enters in
  // that proportion, so a constant bias, whose data put the swing well inside the prior, keeps the
  // fit's own sigma, while a swing the data show keeps the whole of it.
  const double log_bayes_factor = best->log_weight +
                                  std::log(total / static_cast<double>(periods.size())) -
                                  6.0 * std::log(options.prior_amplitude_nT);
  const double prior_odds = options.prior_probability / (1.0 - options.prior_probability);
  out.probability = 1.0 / (1.0 + std::exp(-log_bayes_factor) / prior_odds);
  out.variance_nT2 *= out.probability;
  out.period_s = best->period_s;
  out.period_probability = 1.0 / total;
  out.amplitude_nT = best->amplitude_nT;
  out.amplitude_sigma_nT = best->amplitude_sigma_nT;
  out.periods_tried = static_cast<int>(periods.size());
  return out;
}

}  // namespace magcal
