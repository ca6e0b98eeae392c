#!/usr/bin/env bash
# Builds magcal and runs every test: a Release build with all tests, then a build under
# AddressSanitizer + UndefinedBehaviorSanitizer with the storage, service and low-level pipeline
# tests (tests/CMakeLists.txt says which). Installs the Debian packages first if missing.
#   MAGCAL_SKIP_SANITIZE=1  skips the sanitizer pass (quicker local runs)
set -euo pipefail
cd "$(dirname "$0")/.."

deploy/setup-deps.sh --tests
# A compiler cache makes the second build (and the next run) cheap on 2 cores.
launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)

echo "== Release build and tests"
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release "${launcher[@]}" >/dev/null
cmake --build build -j2
ctest --test-dir build --output-on-failure -j2

if [ "${MAGCAL_SKIP_SANITIZE:-0}" != 1 ]; then
  echo "== AddressSanitizer + UndefinedBehaviorSanitizer build and tests"
  # -O1 -g1 (line tables for the sanitizers' stack traces; NDEBUG as in Release) compiles 2-4x faster
  # than RelWithDebInfo under the sanitizers, which is what keeps CI within its 30 minutes.
  cmake -S . -B build-asan -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS_DEBUG="-O1 -g1 -DNDEBUG" \
    -DCMAKE_C_FLAGS_DEBUG="-O1 -g1 -DNDEBUG" -DMAGCAL_SANITIZE=ON -DMAGCAL_BUILD_BENCH=OFF \
    "${launcher[@]}" >/dev/null
  cmake --build build-asan -j2
  ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
    ctest --test-dir build-asan --output-on-failure -j2 \
    -E "^deploy/|page_browser_test"  # packaging and the page's JavaScript: no C++ memory to check
fi
