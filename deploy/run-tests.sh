#!/usr/bin/env bash
# Builds magcal and runs every test once: the storage and service tests in a build under
# AddressSanitizer + UndefinedBehaviorSanitizer (linking the Release build's pipeline library),
# the rest (pipeline unit and Monte-Carlo tests, browser, packaging) in a Release build;
# tests/CMakeLists.txt (MAGCAL_TEST_SET) says which.
# Installs the Debian packages first if missing.
#   MAGCAL_SKIP_SANITIZE=1  no sanitizer build: every test runs in the Release build
set -euo pipefail
cd "$(dirname "$0")/.."

deploy/setup-deps.sh --tests
# A compiler cache makes the next run cheap on 2 cores.
launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
# A new build folder uses Ninja, which keeps both cores busy across targets (make waits for a
# whole library before compiling its users); an existing folder keeps its generator.
release_generator=() asan_generator=()
[ -f build/CMakeCache.txt ] || release_generator=(-G Ninja)
[ -f build-asan/CMakeCache.txt ] || asan_generator=(-G Ninja)
release_tests=unsanitized
if [ "${MAGCAL_SKIP_SANITIZE:-0}" = 1 ]; then release_tests=all; fi

echo "== Release build and tests (MAGCAL_TEST_SET=${release_tests})"
cmake -S . -B build "${release_generator[@]}" -DCMAKE_BUILD_TYPE=Release -DMAGCAL_TEST_SET="${release_tests}" \
  "${launcher[@]}" >/dev/null
cmake --build build -j2
ctest --test-dir build --output-on-failure -j2

if [ "${MAGCAL_SKIP_SANITIZE:-0}" != 1 ]; then
  echo "== AddressSanitizer + UndefinedBehaviorSanitizer build and tests (MAGCAL_TEST_SET=sanitized)"
  # -O1 -g1 (line tables for the sanitizers' stack traces; NDEBUG as in Release) compiles 2-4x faster
  # than RelWithDebInfo under the sanitizers; test code is -O0 and the pipeline is not rebuilt
  # (tests/CMakeLists.txt): that is what keeps CI within its 30 minutes.
  cmake -S . -B build-asan "${asan_generator[@]}" -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_FLAGS_DEBUG="-O1 -g1 -DNDEBUG" \
    -DCMAKE_C_FLAGS_DEBUG="-O1 -g1 -DNDEBUG" -DMAGCAL_SANITIZE=ON -DMAGCAL_BUILD_BENCH=OFF \
    -DMAGCAL_TEST_SET=sanitized -DMAGCAL_PIPELINE_LIBRARY="$PWD/build/pipeline/libmagcal_pipeline.a" \
    "${launcher[@]}" >/dev/null
  cmake --build build-asan -j2
  # Three at a time on 2 cores: these tests mostly wait on the processes and servers they
  # start (measured: 1.2 cores busy on average at -j3; 568 s at -j2, 409 s at -j3).
  ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
    ctest --test-dir build-asan --output-on-failure -j3
fi
