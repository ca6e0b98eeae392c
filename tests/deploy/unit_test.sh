#!/usr/bin/env bash
# deploy/magcald.service (issue 12, item 5): `systemd-analyze verify` says nothing at all (a
# warning alone would exit 0, so any output fails), with ExecStart pointed at a scratch copy
# of the built magcald (verify needs the binary to exist); the unit is Type=notify with a
# watchdog and runs as the magcal user; and its hardening keeps `systemd-analyze security`
# at "OK" or better.
#   unit_test.sh BIN_DIR SOURCE_DIR
set -euo pipefail
bin_dir="$1"
source_dir="$2"
# shellcheck source-path=SCRIPTDIR source=test_skip.sh
. "$(dirname "$0")/test_skip.sh"
need_tool systemd-analyze
unit="$source_dir/deploy/magcald.service"
[ -x "$bin_dir/magcald" ] || fail "$bin_dir/magcald not built"

scratch="$(mktemp -d -t magcal-unit.XXXXXX)"
trap 'rm -rf "$scratch"' EXIT
mkdir -p "$scratch/usr/bin"
cp "$bin_dir/magcald" "$scratch/usr/bin/magcald"
grep -q '^ExecStart=/usr/bin/magcald ' "$unit" || fail "ExecStart is not /usr/bin/magcald (the .deb's path)"
sed "s|^ExecStart=/usr/bin/magcald |ExecStart=$scratch/usr/bin/magcald |" "$unit" >"$scratch/magcald.service"

if ! systemd-analyze verify "$scratch/magcald.service" >"$scratch/verify.log" 2>&1 ||
  [ -s "$scratch/verify.log" ]; then
  cat "$scratch/verify.log" >&2
  fail "systemd-analyze verify is not clean"
fi
echo "systemd-analyze verify: clean"

value() { sed -n "s/^$1=//p" "$unit" | tail -n 1; }
[ "$(value Type)" = notify ] || fail "Type=$(value Type), expected notify"
[ "$(value NotifyAccess)" = main ] || fail "NotifyAccess=$(value NotifyAccess)"
[ -n "$(value WatchdogSec)" ] || fail "no WatchdogSec="
[ "$(value User)" = magcal ] || fail "User=$(value User)"
[ "$(value StateDirectory)" = magcal ] || fail "StateDirectory=$(value StateDirectory)"
[ "$(value ProtectSystem)" = strict ] || fail "ProtectSystem=$(value ProtectSystem)"
[ "$(value NoNewPrivileges)" = yes ] || fail "NoNewPrivileges=$(value NoNewPrivileges)"
[ "$(value PrivateTmp)" = yes ] || fail "PrivateTmp=$(value PrivateTmp)"
# The watchdog must leave the worker's longest legitimate stall (a commit waiting
# [storage] busy_timeout_ms = 5 s) far inside half of it (the ping period).
watchdog_s="$(value WatchdogSec | sed -n 's/^\([0-9]\+\)s\?$/\1/p')"
if [ -z "$watchdog_s" ] || [ "$watchdog_s" -lt 20 ]; then
  fail "WatchdogSec=$(value WatchdogSec): want >= 20s"
fi

# systemd-analyze security --offline (systemd >= 252): exposure 0 (best) .. 10; 1.4 ("OK") when
# this was written: any hardening line lost raises it.
if systemd-analyze security --help 2>/dev/null | grep -q -- '--offline'; then
  systemd-analyze security --offline=true "$scratch/magcald.service" >"$scratch/security.log" 2>&1 || true
  exposure="$(sed -n 's/.*Overall exposure level for magcald.service: \([0-9.]*\).*/\1/p' "$scratch/security.log")"
  [ -n "$exposure" ] || {
    cat "$scratch/security.log" >&2
    fail "systemd-analyze security printed no exposure level"
  }
  echo "systemd-analyze security exposure: $exposure"
  awk -v e="$exposure" 'BEGIN { exit !(e <= 2.0) }' || fail "exposure $exposure > 2.0"
fi
echo "unit test passed"
