#!/usr/bin/env bash
# Every system file the build used and every program the tests and the demo run comes from a
# package deploy/setup-deps.sh installs (or their dependencies, or Priority required); with its
# self-check, that dropping prometheus-cpp-dev from the list is caught (dependency_check.py).
#   dependency_test.sh BUILD_DIR SOURCE_DIR
set -euo pipefail
# shellcheck source=tests/deploy/test_skip.sh
. "$(dirname "$0")/test_skip.sh"

build_dir=$1 source_dir=$2
need_tool dpkg
need_tool apt-cache
need_tool ninja
# Debian's python3 (deploy/setup-deps.sh --tests), whatever else is on PATH.
[ -x /usr/bin/python3 ] || skip_or_fail "/usr/bin/python3 (Debian python3)"
/usr/bin/python3 "$(dirname "$0")/dependency_check.py" --build-dir "$build_dir" \
  --source-dir "$source_dir"
