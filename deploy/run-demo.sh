#!/usr/bin/env bash
# The main job: installs dependencies if missing, builds (Release), then runs deploy/demo.sh:
# magcald replays 24 h of simulated paper-scenario telemetry, and magcal shows the UKF
# converging and the refits next to the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
deploy/setup-deps.sh
# As deploy/run-tests.sh: the compiler cache, and Ninja for a new build folder (an existing one
# keeps its generator), so the two commands share one build tree and its cache.
generator=()
[ -f build/CMakeCache.txt ] || generator=(-G Ninja)
cmake -S . -B build "${generator[@]}" -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_CXX_COMPILER_LAUNCHER=ccache >/dev/null
cmake --build build -j2 --target magcal magcald
exec deploy/demo.sh "$PWD/build/bin"
