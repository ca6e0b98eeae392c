// How far the current bias can be from a fit's constant bias when the sensor reports no
// temperature: a thermal bias swing that follows the orbit (eclipse, sun angle) is a
// first harmonic of the orbital period, b(t) = b + c cos(w t) + s sin(w t). In a nadir-pointed
// attitude the body-frame field is itself a first harmonic of the orbit on two axes (for a
// dipole: along-track ~ cos u, radial ~ 2 sin u), so such a swing is almost exactly a change of D
// and the 9-parameter fit absorbs it: the residuals show nothing (bias_variability.hpp sees a
// +-10 nT nadir swing in 1 of 4 12 h windows) and the fit's bias sigma says nothing of it. Where
// a temperature channel exists the temperature model bounds the swing; without one, only the
// geometry can: the swing is estimated where the window separates it and its uncertainty
// published where it does not.
//
// For every period of a LEO orbit in [min_period_s, max_period_s] (the orbit is not known to the
// fit), the information of the augmented problem [b, D, a, c, s] (21 parameters: a the
// sensor-model extension, whose hysteresis term is a square wave of the orbit in nadir and took
// half the swing when held; the scalar measurement of estimation.md 2 with the swing's columns
// dz/dc = dz/db cos(w t), dz/ds = dz/db sin(w t)) with a Gaussian prior of prior_amplitude_nT on
// each swing coefficient gives the posterior mean of the swing (one Gauss-Newton step from the fit)
// and the expected squared distance of the current bias b(t), averaged over the orbit phase, from
// the published bias:
//   V = (b_pub - b^)^2 + P_bb + (c^2 + s^2 + P_cc + P_ss) / 2   (per axis; cross terms average
// out; c^2 + P_cc is c's posterior mean square), and the variance the swing adds, V - P_bb
// without the swing, averaged over the periods weighted by their marginal likelihood.
// Whether there is a swing at all is tested, not assumed: the Bayes factor of a swing against none
// (the Savage-Dickey ratio of the swing's prior and posterior densities at zero, averaged over the
// periods) and the stated prior probability give the posterior probability of a swing, and only
// that share of the variance is added, so a window pays for a swing it shows, not for every
// swing it cannot exclude.
// Measured (orbit_synchronous_bias_test "Measure*"): tumbling, a +-10 nT swing estimated at
// 9.8-10.0 nT and its period within 0.1 %; nadir, +-10 nT, rms (bias - current bias) / sigma
// 0.87-1.7. Constant bias (orbit_swing_constant_bias_test "Measure*", 20 seeds a set): bias sigma
// at most 2.5 times the Cramer-Rao bound (paper sensor, nadir and tumbling, 12 h), 1.07 (pure
// model, 6-24 h), rms error / sigma 0.72-1.24 (with the whole swing always added: nadir 12 h 0.38
// / 1.46 / 0.26 -> 2.1-2.3 / 3.7-4.1 / 1.1-1.2 nT, the orbit normal (y) widest). The noise is the
// fit's (sigma x noise scale, with the AR(1) factor of its residuals' lag-1 autocorrelation), as
// bias_variability.hpp weighs its blocks.
#pragma once

#include <Eigen/Core>

#include "pipeline/calibration_result.hpp"
#include "pipeline/calibration_types.hpp"

namespace magcal {

struct OrbitSynchronousBiasOptions {
  double min_period_s = 85.0 * 60.0;   // a 200 km orbit: 88 min
  double max_period_s = 130.0 * 60.0;  // a 2 000 km orbit: 127 min
  // Prior 1-sigma of each swing coefficient (c_i, s_i): a +-30 nT swing is the plausible
  // worst case (2 nT/degC over +-15 degC); what no data constrain comes back at this size.
  double prior_amplitude_nT = 30.0;
  // Prior probability that the bias swings with the orbit at all, before the window's data.
  double prior_probability = 0.5;
};

// samples in any order (utime); fit: the refit whose b, D, noise scale and residual lag-1
// autocorrelation describe them. Nothing is computed (periods_tried = 0) for a window shorter than
// max_period_s (a fragment or a bench capture: an orbit's swing is not considered there) or
// without a finite Fisher information.
UnresolvedBiasSwing unresolved_orbit_synchronous_bias_swing(
    const SampleSet& samples, const CalibrationResult& fit, double sigma_nT,
    const OrbitSynchronousBiasOptions& options = {});

}  // namespace magcal
