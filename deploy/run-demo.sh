#!/usr/bin/env bash
# The main job: installs dependencies if missing, builds (Release), then runs deploy/demo.sh:
# magcald replays 24 h of simulated paper-scenario telemetry, and magcal shows the UKF
# converging and the refits next to the truth.
set -euo pipefail
cd "$(dirname "$0")/.."
deploy/setup-deps.sh
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release >/dev/null
cmake --build build -j2 --target magcal magcald
exec deploy/demo.sh "$PWD/build/bin"
