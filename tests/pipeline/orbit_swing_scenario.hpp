// A scenario preset whose sensor's bias swings with the orbit (issue 20 item 3): a temperature of
// +-amplitude_nT degC about T0 at the orbital period and k_T = 1 nT/degC on every axis, so the
// bias swings +-amplitude_nT nT on each. The tests that use it drop the temperature from the
// samples (no temperature channel).
#pragma once

#include <cstdint>

#include <Eigen/Core>

#include "pipeline/scenario.hpp"

namespace magcal::test {

inline Scenario orbit_swing_scenario(const char* preset, uint64_t seed, double amplitude_nT,
                                     double hours) {
  Scenario sc = *scenario_preset(preset);
  sc.seed = seed;
  sc.duration_s = hours * 3600.0;
  sc.sensor.temperature_amplitude_C = amplitude_nT;
  sc.sensor.temperature_coefficient_nT_per_C = Eigen::Vector3d::Ones();
  return sc;
}

}  // namespace magcal::test
