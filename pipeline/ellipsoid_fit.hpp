// Algebraic ellipsoid fit: a starting point for the Levenberg–Marquardt refinement when the
// centered solution is degenerate (estimation.md section 7: with a constant reference
// magnitude E = -I, c = 0 fits the centered data exactly) or not positive definite.
//
// Model: every calibrated vector y_k = (I + D) B_k - b has |y_k| = |h_k|, i.e. B_k lies on the
// quadric B^T A B - 2 a^T B + alpha = 0 with A = (I + E) / s, a = c / s, alpha = (|b|^2 - H^2) / s
// for a constant H. Homogeneous least squares over the 10 coefficients (the eigenvector of the
// smallest eigenvalue of sum phi_k phi_k^T, phi_k = [B1^2 B2^2 B3^2 2B1B2 2B1B3 2B2B3 -2B1 -2B2
// -2B3 1] with B scaled by the rms |B| so the columns are O(1)) fixes the shape and centre
// v = A^-1 a; the scale comes from the reference magnitude: I + E = H^2 A / (v^T A v - alpha),
// H^2 = mean |h_k|^2, c = (I + E) v. With a varying |h| this is the best single-radius
// ellipsoid: a start, not an estimate (the refinement uses every |h_k|).
// Returns false (theta untouched) when the quadric is not an ellipsoid (samples in a plane,
// indefinite A), i.e. the data do not determine a start.
#pragma once

#include "pipeline/calibration_types.hpp"

namespace magcal {

bool ellipsoid_fit_start(const SampleSet& samples, Vector9d* theta);

}  // namespace magcal
