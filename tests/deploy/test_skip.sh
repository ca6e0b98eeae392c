# shellcheck shell=bash
# Honest skips for the shell tests, as tests/test_skip.hpp does for the Catch2 ones (sourced).
#   skip_or_fail REASON  CI=true: the input is provisioned there (deploy/setup-deps.sh), so a
#                        missing one fails the test; elsewhere prints the marker CTest reports
#                        as "Skipped" (SKIP_REGULAR_EXPRESSION) and exits.
#   fail MESSAGE         one line on stderr, exit 1.
fail() {
  echo "FAILED: $*" >&2
  exit 1
}

skip_or_fail() {
  if [ "${CI:-}" = true ]; then
    fail "missing in CI (CI=true), where it is provisioned: $*"
  fi
  echo "MAGCAL_TEST_SKIPPED: $*"
  exit 0
}

need_tool() {
  command -v "$1" >/dev/null 2>&1 || skip_or_fail "$1 not found (deploy/setup-deps.sh installs it)"
}
