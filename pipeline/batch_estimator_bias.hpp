// The estimator-bias correction of a twostep batch refit (pipeline/batch_calibration.hpp, header
// comment "Estimator bias"): a parametric bootstrap measures the bias of the estimator that runs
// and removes it where it can matter. Internal to the batch refit.
#pragma once

#include "pipeline/batch_calibration.hpp"
#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal::batch_detail {

// Removes the estimator's bias from r (twostep) where the noise is large against the coverage;
// the covariance takes the bootstrap's scatter and the correction's own uncertainty.
void correct_estimator_bias(const SampleSet& samples, const BatchCalibrationOptions& options,
                            CalibrationResult* r);

}  // namespace magcal::batch_detail
