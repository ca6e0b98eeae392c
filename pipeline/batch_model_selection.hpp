// Stage 1 of a batch refit (pipeline/batch_calibration.hpp): the centered solution, the
// Levenberg-Marquardt refinement from the better start, and the model choice by BIC between the
// 9-parameter model, the sensor-model extension (pipeline/model_extension.hpp) and the bias
// temperature model or bias rate (pipeline/temperature_model.hpp). Internal to the batch refit.
#pragma once

#include <vector>

#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"
#include "pipeline/lm_refinement.hpp"

namespace magcal::batch_detail {

// What stage 1 hands on: theta = [c; E], its covariances, and the part of the covariance that
// comes from the model choice.
struct Stage1Solution {
  Vector9d theta = Vector9d::Zero();
  Matrix9d covariance = Matrix9d::Zero();
  Matrix9d covariance_white = Matrix9d::Zero();
  Vector9d refused_extension_shift = Vector9d::Zero();  // p_ext - p_9 when BIC's pick is refused
  double mean_h_nT = 0.0;
  // The model extension's columns when choose_model_by_bic() computed them.
  std::vector<Vector6d> extension_regressors;
  // The temperature model is a candidate (temperature_model_unusable() says nothing against it)
  // about this reference temperature.
  bool temperature_candidate = false;
  double reference_temperature_C = 0.0;
  // The candidate's temperature is the time before the window's end
  // (with_hours_before_window_end()): the model is a bias rate.
  bool bias_rate = false;
};

LmOptions lm_options(const BatchCalibrationOptions& options, int min_samples);

// Stage 1: centered solution, [twostep] LM refinement and model choice. False (r failed) when
// no estimate comes out. s1's temperature fields say whether the temperature model (or the bias
// rate) is a candidate.
bool solve_stage1(const SampleSet& samples, const BatchCalibrationOptions& options,
                  CalibrationResult* r, Stage1Solution* s1);

}  // namespace magcal::batch_detail
