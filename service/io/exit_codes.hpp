// Process exit codes of magcal and magcald (design.md "CLI"; one table for both binaries).
#pragma once

namespace magcal {

inline constexpr int kExitOk = 0;
inline constexpr int kExitUsage = 1;          // bad arguments or config
inline constexpr int kExitData = 2;           // data, file, database or LCM error (at start)
inline constexpr int kExitStorageFailed = 3;  // magcald: storage broken for [storage] max_failure_s
inline constexpr int kExitThreadDied = 4;     // magcald: a worker or refit thread died

}  // namespace magcal
