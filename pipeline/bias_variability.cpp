#include "pipeline/bias_variability.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/LU>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/model_extension.hpp"

namespace magcal {

namespace {

constexpr double kMicrosecondsPerSecond = 1e6;

// The bias of samples [begin, end) with D and the extension held: x_k + b_fit are the vectors
// (I + D) B_k - n(y_k). False when the block does not determine it.
bool block_bias(const SampleSet& samples, const std::vector<Eigen::Vector3d>& x,
                const Eigen::Vector3d& bias_fit_nT, std::size_t begin, std::size_t end,
                int iterations, Eigen::Vector3d& bias_nT, Eigen::Matrix3d& information) {
  bias_nT = bias_fit_nT;
  for (int iteration = 0; iteration < iterations; ++iteration) {
    information.setZero();
    Eigen::Vector3d gradient = Eigen::Vector3d::Zero();
    for (std::size_t k = begin; k < end; ++k) {
      const Eigen::Vector3d v = x[k] + bias_fit_nT - bias_nT;
      const double norm = v.norm();
      if (!(norm > 0.0)) return false;
      const Eigen::Vector3d J = -v / norm;
      information += J * J.transpose();
      gradient += J * (norm - samples[k].h_body_nT.norm());
    }
    const Eigen::LDLT<Eigen::Matrix3d> ldlt(information);
    if (ldlt.info() != Eigen::Success || !(ldlt.vectorD().array() > 0.0).all()) return false;
    bias_nT -= ldlt.solve(gradient);
  }
  return bias_nT.allFinite();
}

}  // namespace

Eigen::Vector3d BiasVariability::excess_nT2() const {
  return significant ? Eigen::Vector3d((scatter_nT2 - noise_nT2).cwiseMax(0.0))
                     : Eigen::Vector3d::Zero();
}

BiasVariability measure_bias_variability(const SampleSet& samples, const CalibrationResult& fit,
                                         double sigma_nT, const BiasVariabilityOptions& options) {
  BiasVariability out;
  if (samples.empty()) return out;
  const CalibrationParameters& p = fit.parameters;
  const ExtensionInputs in = extension_inputs(samples, p, sigma_nT);
  const std::vector<Eigen::Vector3d> x =
      fit.has_nonlinearity ? extension_corrected_vectors(in, fit.nonlinearity_k3, fit.hysteresis_nT)
                           : in.y_nT;
  const double scale = std::isfinite(fit.noise_scale) ? std::max(1.0, fit.noise_scale) : 1.0;
  const double noise_variance =
      sigma_nT * sigma_nT * scale * scale * ar1_variance_factor(fit.residual_autocorrelation);

  Eigen::Vector3d sum = Eigen::Vector3d::Zero(), sum2 = Eigen::Vector3d::Zero();
  const auto block_us = static_cast<int64_t>(options.block_s * kMicrosecondsPerSecond);
  std::size_t begin = 0;
  while (begin < samples.size()) {
    std::size_t end = begin;
    while (end < samples.size() && samples[end].utime - samples[begin].utime < block_us) ++end;
    Eigen::Vector3d b;
    Eigen::Matrix3d information = Eigen::Matrix3d::Zero();
    if (static_cast<int>(end - begin) >= options.min_block_samples &&
        block_bias(samples, x, p.bias_nT, begin, end, options.gauss_newton_iterations, b,
                   information)) {
      sum += b;
      sum2 += b.cwiseAbs2();
      out.noise_nT2 += noise_variance * information.inverse().diagonal();
      ++out.blocks;
    }
    begin = end;
  }
  if (out.blocks < std::max(2, options.min_blocks)) return out;
  const double n = out.blocks;
  out.scatter_nT2 = (sum2 - sum.cwiseAbs2() / n) / (n - 1.0);
  out.noise_nT2 /= n;
  const double limit = chi_square_upper_quantile(n - 1.0, options.tail_probability);
  out.significant = ((n - 1.0) * out.scatter_nT2.array() > limit * out.noise_nT2.array()).all();
  return out;
}

}  // namespace magcal
