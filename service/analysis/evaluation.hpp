// Monte-Carlo evaluation against the paper (`magcal evaluate`): the paper's protocol on a
// scenario (pipeline/scenario.hpp), N runs with seeds seed, seed+1, ...; offline methods on the
// first offline_hours of each run, online methods on online_hours; one table like the paper's
// Table 8 with the paper's numbers beside ours (paper.md) and the CRLB.
//
// Metrics (estimation.md section 6):
//   bias MSE       mean over runs and axes of (b_hat_i - b_i)^2            (nT^2)
//   mean |e_b|     mean over runs and axes of |b_hat_i - b_i|              (nT)
//   D error        mean over runs of mean_j |D_hat_j - D_j|, 6 unique elements
//   alignment err  mean over runs of the angle of R_hat (C_int R)^T        (deg)
//   CRLB sigma     sqrt(mean over runs and axes of CRLB variance), CRLB at the truth on the
//                  method's own sample set with the scenario's white noise
//   RMS/CRLB       sqrt(mean over runs and axes of (e_i / sigma_CRLB,i)^2)
//   convergence    online: time from the first sample after which every bias 1-sigma stayed
//                  < 10 nT (mean over runs that converged)
//   memory         offline: samples held x sizeof(CalibrationSample); online: sizeof the filter
//                  (its FilterState and a pointer to the options, which a fleet shares)
//   compute        wall time per run of the method (ms)
// Online methods run with their default settings from a data start over the whole online span,
// and warm (seeded, state, covariance and noise, from the centered+LM refit of the offline
// window, then filtering the samples after it), side by side (estimation.md 3a). The thermal
// rows (EvaluationOptions::thermal) run centered+LM on the offline span of a thermal variant.
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "pipeline/scenario.hpp"

namespace magcal {

struct EvaluationOptions {
  Scenario scenario;
  int runs = 10;
  uint64_t seed = 1;
  double offline_hours = 12.0;
  double online_hours = 24.0;
  bool online = true;  // run the EKF/UKF rows
  // Old hand-tuning, off by default: filters' sigma_nT = residual rms of the run's offline
  // centered+LM refit when larger than the white noise. Default: sigma_nT = the white noise and
  // the filters estimate the effective noise themselves (filter_common.hpp).
  bool filter_sigma_from_residual = false;
  // Two more centered+LM rows on a thermal variant of each run (the scenario with an
  // orbit-synchronous temperature of +-thermal_amplitude_C and a bias temperature coefficient
  // thermal_coefficient_nT_per_C): without a temperature channel (every temperature unknown: the
  // refit bounds a swing with the orbit) and with one (the bias temperature model), against the
  // true bias at the samples' mean temperature.
  bool thermal = true;
  double thermal_amplitude_C = 15.0;
  Eigen::Vector3d thermal_coefficient_nT_per_C = Eigen::Vector3d(1.0, -0.8, 1.2);
  std::string validate() const;
};

// The paper's numbers for a row (NaN = not reported).
struct PaperFigures {
  double bias_mse_nT2 = std::numeric_limits<double>::quiet_NaN();
  double mean_abs_bias_nT = std::numeric_limits<double>::quiet_NaN();
  double D_error = std::numeric_limits<double>::quiet_NaN();
  double alignment_error_deg = std::numeric_limits<double>::quiet_NaN();
  double convergence_time_s = std::numeric_limits<double>::quiet_NaN();
  std::string memory;   // as the paper states it
  std::string compute;  // MATLAB
};

struct MethodStats {
  std::string method;     // "centered", "centered+LM", "EKF cold", ...
  std::string data;       // "12 h", "24 h", "12 h + 12 h"
  int runs_ok = 0;        // runs with an estimate
  int runs_failed = 0;    // runs without one (failed / unobservable)
  int runs_rejected = 0;  // estimates refused by the default acceptance gates / not converged
  double bias_mse_nT2 = std::numeric_limits<double>::quiet_NaN();
  double mean_abs_bias_nT = std::numeric_limits<double>::quiet_NaN();
  double D_error = std::numeric_limits<double>::quiet_NaN();
  double alignment_error_deg = std::numeric_limits<double>::quiet_NaN();
  double convergence_time_s = std::numeric_limits<double>::quiet_NaN();
  int runs_converged = 0;
  double memory_bytes = std::numeric_limits<double>::quiet_NaN();
  double compute_ms = std::numeric_limits<double>::quiet_NaN();
  double crlb_sigma_nT = std::numeric_limits<double>::quiet_NaN();
  double crlb_ratio = std::numeric_limits<double>::quiet_NaN();
  double reported_sigma_nT = std::numeric_limits<double>::quiet_NaN();  // mean claimed 1-sigma
  PaperFigures paper;
};

struct EvaluationReport {
  std::string scenario;
  int runs = 0;
  uint64_t seed = 0;
  double noise_sigma_nT = 0.0;
  std::vector<MethodStats> rows;
  double wall_s = 0.0;
};

EvaluationReport run_evaluation(const EvaluationOptions& options);

nlohmann::json evaluation_to_json(const EvaluationReport& report);
std::string format_evaluation_table(const EvaluationReport& report);

}  // namespace magcal
