// The generated LCM message types (package magcal). Include this instead of the generated
// headers: GCC 12 reports -Wmaybe-uninitialized inside lcm-gen's decode() even from a SYSTEM
// include directory, so the warning is silenced for the generated code only.
#pragma once

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <magcal/calibration_t.hpp>
#include <magcal/daemon_status_t.hpp>
#include <magcal/mag_batch_t.hpp>
#include <magcal/mag_sample_t.hpp>
#pragma GCC diagnostic pop
