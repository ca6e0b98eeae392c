#!/usr/bin/env bash
# Installs the Debian packages magcal needs to build, test and run.
#   deploy/setup-deps.sh           build and run
#   deploy/setup-deps.sh --tests   also what only the tests use (chromium for the page test:
#                                  ~48 s to install on the dev machine, large)
#   deploy/setup-deps.sh --list [--tests]
#                                  prints the package names, one a line, and installs nothing
#                                  (tests/deploy/dependency_test.sh checks that every file the
#                                  build uses and every program the tests and the demo run
#                                  comes from one of them or from what they depend on)
# Idempotent: does nothing (no apt-get at all) when every package is already installed.
set -euo pipefail

with_tests=0 list_only=0
for arg in "$@"; do
  case "$arg" in
    --tests) with_tests=1 ;;
    --list) list_only=1 ;;
    *) echo "setup-deps: unknown option '$arg' (use --tests, --list)" >&2; exit 2 ;;
  esac
done

packages=(
  build-essential cmake ninja-build pkg-config ccache
  libeigen3-dev
  liblcm-dev liblcm-bin
  libsqlite3-dev sqlite3
  # the PostgreSQL backend (fleet mode): libpq and its pg_config
  libpq-dev
  libspdlog-dev libfmt-dev
  catch2
  libtomlplusplus-dev libcli11-dev nlohmann-json3-dev
  libbenchmark-dev
  liberfa-dev
  # systemd notify (sd_notify); cpack's dpkg-shlibdeps for the .deb
  libsystemd-dev dpkg-dev
  # the operations server (cpp-httplib), its metrics exposition (prometheus-cpp) and the page's
  # plotting library (Chart.js, embedded)
  libcpp-httplib-dev prometheus-cpp-dev libjs-chart.js
)
# Only for the tests (deploy/run-tests.sh passes --tests): the browser test's Chromium; the
# .deb (cpack's dpkg-shlibdeps); the tests of deploy/: systemd-analyze, promtool (prometheus:
# ~13 s to install, 12 packages), shellcheck, PyYAML; the PostgreSQL server the storage and fleet
# tests start in a temporary directory (initdb, pg_ctl; installing it starts no server when
# services may not start, see policy-rc.d below) and psql to look into it.
if [ "$with_tests" = 1 ]; then
  packages+=(chromium systemd prometheus shellcheck python3 python3-yaml
    postgresql-15 postgresql-client-15)
fi

if [ "$list_only" = 1 ]; then
  printf '%s\n' "${packages[@]}"
  exit 0
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi

echo "setup-deps: installing ${missing[*]}" >&2
sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
"${sudo_cmd[@]}" apt-get update
# prometheus ships a service: it must not start here. Where the machine has no policy-rc.d
# (containers usually do), one that refuses every start is in place for this install only.
if [ ! -e /usr/sbin/policy-rc.d ]; then
  printf '#!/bin/sh\nexit 101\n' | "${sudo_cmd[@]}" tee /usr/sbin/policy-rc.d >/dev/null
  "${sudo_cmd[@]}" chmod 755 /usr/sbin/policy-rc.d
  trap '"${sudo_cmd[@]}" rm -f /usr/sbin/policy-rc.d' EXIT
fi
DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y --no-install-recommends "${missing[@]}"
