// Input screening of a batch refit's samples (pipeline/batch_calibration.hpp): the checks that
// refuse a window before any fit (a sample's values, the window's field magnitude against the
// reference), and the outlier evidence at the published estimate (robust residuals, raw spikes).
// Internal to the batch refit.
#pragma once

#include <string>
#include <vector>

#include "pipeline/acceptance_gates.hpp"
#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal::batch_detail {

// A least-squares fit with a residual beyond this many robust sigmas (as above) is refused: one
// spike of 2 000-10 000 nT in 4 h of paper data moved the bias by up to 35 nT (3.9 sigma) and the
// angles by 5 sigma while the residual RMS stayed within its gate. Clean data, 10 seeds
// each of 3, 12 and 24 h: the largest residual is 3.5 (paper), 3.2 (tumbling), 4.7 (pure model,
// Gaussian) robust sigmas.
inline constexpr double kOutlierGateRobustSigmas = 10.0;
// Robust fits leave out samples with |B| beyond the sensor range (a spike, one wrapped count)
// while they are at most this share of the window; more is a systematic fault (negative counts
// read as unsigned wrap every sample with a negative axis, a wrong unit wraps all of them), and
// a fit of the rest would rest on a biased subset: refused, naming the magnitude.
inline constexpr double kMaxLeftOutBeyondRangeFraction = 0.01;
// Where the fit's own residuals show no outlier (a spike large enough to wreck the fit makes
// every residual large), the raw residuals |B| - |h| are screened: a sample beyond
// kOutlierGateRobustSigmas robust sigmas of their median and beyond this share of the mean |h|
// from it is a spike no sensor error explains (a 30 % scale error moves |B| by 30 % of |h|, and
// it moves every sample).
inline constexpr double kRawSpikeFractionOfField = 0.5;
// A window whose median |B| is beyond this factor of the reference field's median |h| (either
// way) is in another unit (uT, G, mG, raw counts), wrapped on many samples (negative counts of a
// 16-bit sensor read as unsigned: +65536 LSB) or fitted against the wrong reference. No
// calibration error a gate accepts comes near a factor of 5 (scale factors within 0.3; even a
// hard-iron bias of 2/3 of |h| leaves the median near 1), and a fit of such data fails every
// bound at once without naming the cause.
inline constexpr double kMaxFieldMagnitudeRatio = 5.0;

bool beyond_sensor_range(const CalibrationSample& s, double max_field_nT);

// rms of |(I + D) B - b| - |h| at p over the samples, and the residuals themselves.
double residual_rms(const SampleSet& samples, const CalibrationParameters& p,
                    std::vector<double>* residuals);

// r refused with status and message (also among its rejection reasons).
CalibrationResult fail(CalibrationResult r, CalibrationStatus status, std::string message);

// keep[k] = |e_k - median(e)| <= n_sigmas x max(1.4826 MAD(e), floor_nT) (a robust sigma never
// below the nominal noise: on noise-free data the MAD is rounding). Returns whether any keep[k]
// changed. `scratch` is reused.
bool mark_outliers(const std::vector<double>& e, double n_sigmas, double floor_nT,
                   std::vector<double>* scratch, std::vector<char>* keep);

// Input check: the options, the sample count, each sample (sample_input_problem), the window's
// times, the window's field magnitude against the reference. False (r failed) when the data
// cannot enter a fit; else the window's times set in r.
bool check_input(const SampleSet& samples, const BatchCalibrationOptions& options,
                 CalibrationResult* r);

// A failed fit's message with the samples far off the field among its samples named: one sample
// far off the field can leave the centered solution without a solution at all, where the cause is
// the input, and --robust leaves it out.
void name_raw_spikes(const SampleSet& samples, double sigma_nT, CalibrationResult* r);

// Residual evidence at the published b, D: rms of |B_cal| - |h| and the samples the fit rests on
// as outliers (residuals beyond kOutlierGateRobustSigmas robust sigmas of the median).
void residual_evidence(const SampleSet& samples, const BatchCalibrationOptions& options,
                       CalibrationResult* r, GateInputs* gates);

}  // namespace magcal::batch_detail
