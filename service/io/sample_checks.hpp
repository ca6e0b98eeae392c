// Checks of incoming samples that the file readers (`magcal fit`, sample_files.hpp) and magcald's
// ingest (lcm_ingest, sample_validator) both apply, so that a sample means the same to either:
// the byte lengths inside an encoded LCM frame, the readability of an LCM log, and the plausible
// range of a sensor temperature.
#pragma once

#include <string>

namespace magcal {

// A sensor temperature outside this range (deg C) is a telemetry fault, not a reading: beyond
// what space-qualified parts survive (-55..125 deg C) with a wide margin. One such value among
// thousands moves a thermal fit's bias by several sigma.
inline constexpr double kMinPlausibleTemperature_C = -150.0;
inline constexpr double kMaxPlausibleTemperature_C = 200.0;
// temperature_C when plausible, else NaN (unknown); NaN stays NaN.
double plausible_temperature_C(double temperature_C);

// True when an encoded magcal.mag_sample_t (batch false) or mag_batch_t (batch true) frame of
// `size` bytes (from its 8-byte fingerprint on, which is not checked here) has every length
// inside it fitting the bytes. lcm-gen's decoders trust those lengths: a string length <= 0
// overflows `length - 1` (undefined behaviour) and std::string::assign throws; a batch's n
// sizes `samples` before any sample is read (2^31 - 1 would ask for hundreds of GB). Decode only
// frames for which this holds (magcald's ingest, `magcal fit` on a log).
bool well_formed_lcm_frame(const void* data, int size, bool batch);

// Why `path` cannot be read as an LCM log: the OS error (missing, unreadable, a directory), an
// empty file, or a file in which no LCM event can be read (no valid event header: not an LCM
// log, or corrupt). Empty when its first event reads. Shared by `magcal fit` and magcald's
// replay start error.
std::string unreadable_lcm_log_reason(const std::string& path);

}  // namespace magcal
