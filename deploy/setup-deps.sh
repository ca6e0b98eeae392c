#!/usr/bin/env bash
# Installs the Debian packages magcal needs to build, test and run.
#   deploy/setup-deps.sh           build and run
#   deploy/setup-deps.sh --tests   also what only the tests use (chromium for the page test:
#                                  ~48 s to install on the dev machine, large)
# Idempotent: does nothing (no apt-get at all) when every package is already installed.
set -euo pipefail

packages=(
  build-essential cmake pkg-config ccache
  libeigen3-dev
  liblcm-dev liblcm-bin
  libsqlite3-dev sqlite3
  libspdlog-dev libfmt-dev
  catch2
  libtomlplusplus-dev libcli11-dev nlohmann-json3-dev
  libbenchmark-dev
  liberfa-dev
  libcpp-httplib-dev libjs-chart.js
)
if [ "${1:-}" = "--tests" ]; then
  packages+=(chromium)
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
DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y --no-install-recommends "${missing[@]}"
