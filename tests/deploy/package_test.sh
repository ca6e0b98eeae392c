#!/usr/bin/env bash
# The .deb (issue 12, item 6): cpack on the existing build tree (no rebuild) makes
# magcal_<version>_<arch>.deb; its control data, file list, copyright file (copyright_check.py)
# and maintainer scripts are checked;
# `dpkg -x` into a scratch root, magcald --version runs from there; the maintainer scripts run
# against that root (DPKG_ROOT) with the system-changing commands replaced by recorders. With
# CI=true as root: a real dpkg -i (twice: upgrade path), dpkg -r and dpkg --purge.
#   package_test.sh BUILD_DIR SOURCE_DIR VERSION [CPACK]
set -euo pipefail
build_dir="$1"
source_dir="$2"
version="$3"
cpack_cmd="${4:-cpack}"
# shellcheck source-path=SCRIPTDIR source=test_skip.sh
. "$(dirname "$0")/test_skip.sh"

need_tool dpkg-deb
need_tool dpkg
need_tool dpkg-shlibdeps # CPACK_DEBIAN_PACKAGE_SHLIBDEPS
[ -x "$cpack_cmd" ] || command -v "$cpack_cmd" >/dev/null || fail "cpack not found: $cpack_cmd"
[ -f "$build_dir/CPackConfig.cmake" ] || fail "no $build_dir/CPackConfig.cmake"
for exe in magcal magcald; do
  [ -x "$build_dir/bin/$exe" ] || fail "$build_dir/bin/$exe not built"
done

scratch="$(mktemp -d -t magcal-package.XXXXXX)"
installed_here=0
cleanup() {
  if [ "$installed_here" = 1 ]; then dpkg --purge magcal >/dev/null 2>&1 || true; fi
  rm -rf "$scratch"
}
trap cleanup EXIT

# --- build: package what is built (CMAKE_SKIP_INSTALL_ALL_DEPENDENCY: no build of all)
"$cpack_cmd" --config "$build_dir/CPackConfig.cmake" -G DEB -B "$scratch/out" \
  >"$scratch/cpack.log" 2>&1 || {
  cat "$scratch/cpack.log" >&2
  fail "cpack failed"
}
arch="$(dpkg --print-architecture)"
deb="$scratch/out/magcal_${version}_${arch}.deb"
[ -f "$deb" ] || fail "expected $(basename "$deb"), cpack made: $(ls "$scratch/out")"
echo "built $(basename "$deb") ($(stat -c %s "$deb") bytes)"

# --- control data
field() { dpkg-deb -f "$deb" "$1"; }
[ "$(field Package)" = magcal ] || fail "Package: $(field Package)"
[ "$(field Version)" = "$version" ] || fail "Version: $(field Version)"
[ "$(field Architecture)" = "$arch" ] || fail "Architecture: $(field Architecture)"
depends="$(field Depends)"
echo "Depends: $depends"
# adduser and init-system-helpers for the scripts; the rest from dpkg-shlibdeps.
for dep in adduser init-system-helpers libc6 libstdc++6 libsqlite3-0 liblcm1 libspdlog; do
  case ", $depends" in
    *", $dep"*) ;;
    *) fail "Depends lacks $dep" ;;
  esac
done
mkdir "$scratch/control"
dpkg-deb -e "$deb" "$scratch/control"
for script in postinst prerm postrm; do
  [ -x "$scratch/control/$script" ] || fail "control script $script missing or not executable"
  sh -n "$scratch/control/$script" || fail "$script: sh -n"
done
if command -v shellcheck >/dev/null; then
  shellcheck -s sh "$scratch/control/postinst" "$scratch/control/prerm" "$scratch/control/postrm" ||
    fail "shellcheck of the maintainer scripts"
else
  skip_or_fail "shellcheck not found (deploy/setup-deps.sh installs it)"
fi
[ "$(cat "$scratch/control/conffiles")" = /etc/magcal/magcald.toml ] ||
  fail "conffiles: $(cat "$scratch/control/conffiles")"

# --- file list
dpkg-deb -c "$deb" >"$scratch/contents"
# The documents README.md links to (docs/), so its links work in the installed copy too.
linked_docs=()
for doc in "$source_dir"/docs/*.md "$source_dir"/docs/*.png; do
  linked_docs+=("./usr/share/doc/magcal/docs/$(basename "$doc")")
done
for path in ./usr/bin/magcal ./usr/bin/magcald ./usr/lib/systemd/system/magcald.service \
  ./etc/magcal/magcald.toml ./var/lib/magcal/ ./usr/share/magcal/prometheus/magcal-alerts.yml \
  ./usr/share/doc/magcal/README.md ./usr/share/doc/magcal/magcald.example.toml \
  ./usr/share/doc/magcal/copyright "${linked_docs[@]}"; do
  awk -v p="$path" '$6 == p { found = 1 } END { exit !found }' "$scratch/contents" ||
    fail "$path not in the package"
done
# Nothing else (no build path, no /usr/local).
allowed='^\./(etc|etc/magcal|etc/magcal/magcald\.toml|usr|usr/bin|usr/bin/magcald?|usr/lib|usr/lib/systemd|usr/lib/systemd/system|usr/lib/systemd/system/magcald\.service|usr/share|usr/share/doc|usr/share/doc/magcal(/.*)?|usr/share/magcal(/.*)?|var|var/lib|var/lib/magcal)?$'
if awk '{ print $6 }' "$scratch/contents" | sed 's|/$||' | grep -Ev "$allowed"; then
  fail "unexpected paths in the package (above)"
fi

# --- extract into a scratch root and run from it
root="$scratch/root"
dpkg -x "$deb" "$root"
got="$("$root/usr/bin/magcald" --version)"
[ "$got" = "$version" ] || fail "magcald --version says '$got', expected '$version'"
got="$("$root/usr/bin/magcal" --version)"
[ "$got" = "$version" ] || fail "magcal --version says '$got', expected '$version'"
echo "magcald --version from the extracted package: $got"
# Debian policy 12.5: /usr/share/doc/magcal/copyright, here in the machine-readable format.
copyright="$root/usr/share/doc/magcal/copyright"
[ "$(stat -c %a "$copyright")" = 644 ] || fail "copyright mode $(stat -c %a "$copyright")"
cmp "$copyright" "$source_dir/deploy/debian/copyright" ||
  fail "/usr/share/doc/magcal/copyright is not deploy/debian/copyright"
# Debian's python3 (deploy/setup-deps.sh --tests), whatever else is on PATH.
[ -x /usr/bin/python3 ] || skip_or_fail "/usr/bin/python3 (Debian python3)"
/usr/bin/python3 "$(dirname "$0")/copyright_check.py" "$copyright" ||
  fail "/usr/share/doc/magcal/copyright is not a valid machine-readable copyright file"
echo "copyright: machine-readable (copyright-format 1.0), $(grep -c '^Files:' "$copyright") Files paragraphs"
cmp "$root/etc/magcal/magcald.toml" "$source_dir/deploy/magcald.example.toml" ||
  fail "/etc/magcal/magcald.toml is not deploy/magcald.example.toml"
cmp "$root/usr/lib/systemd/system/magcald.service" "$source_dir/deploy/magcald.service" ||
  fail "the packaged unit differs from deploy/magcald.service (prefix /usr: no rewrite expected)"
exec_start="$(sed -n 's/^ExecStart=//p' "$root/usr/lib/systemd/system/magcald.service")"
exe="${exec_start%% *}"
[ -x "$root$exe" ] || fail "ExecStart binary $exe is not in the package"
# The example config is what the unit starts with: magcald accepts it (it gets as far as LCM).
set +e
"$root$exe" --config "$root/etc/magcal/magcald.toml" --db "$scratch/probe.db" \
  --lcm-url "file://$scratch/no-such.lcm?speed=0" 2>"$scratch/probe.err"
rc=$?
set -e
if [ "$rc" != 2 ] || ! grep -q "cannot open LCM URL" "$scratch/probe.err"; then
  fail "magcald with the packaged config: exit $rc, $(cat "$scratch/probe.err")"
fi

# --- maintainer scripts against the scratch root, system-changing commands recorded
stubs="$scratch/stubs"
calls="$scratch/calls"
mkdir "$stubs"
: >"$calls"
for cmd in adduser chown deb-systemd-helper deb-systemd-invoke systemctl useradd; do
  cat >"$stubs/$cmd" <<STUB
#!/bin/sh
echo "$cmd \$*" >>"$calls"
[ "$cmd" = adduser ] && : >"$scratch/user-exists"
exit 0
STUB
  chmod +x "$stubs/$cmd"
done
cat >"$stubs/getent" <<STUB
#!/bin/sh
echo "getent \$*" >>"$calls"
[ "\$1 \$2" = "passwd magcal" ] && [ -e "$scratch/user-exists" ] && echo "magcal:x:999:999::/var/lib/magcal:/usr/sbin/nologin" && exit 0
exit 2
STUB
chmod +x "$stubs/getent"
run_script() {
  env PATH="$stubs:$PATH" DPKG_ROOT="$root" sh "$scratch/control/$1" "${@:2}" ||
    fail "$1 $* exited non-zero"
}
expect_call() { grep -qxF -- "$1" "$calls" || fail "expected '$1' from $2; calls: $(cat "$calls")"; }
refuse_call() { ! grep -q -- "$1" "$calls" || fail "unexpected '$1' from $2; calls: $(cat "$calls")"; }

state="$root/var/lib/magcal"
rmdir "$state" # a first install where dpkg did not create it: postinst must
run_script postinst configure
expect_call "adduser --system --group --home /var/lib/magcal --no-create-home --gecos magcal calibration daemon magcal" "postinst (install)"
expect_call "chown magcal:magcal $state" "postinst (install)"
expect_call "deb-systemd-helper enable magcald.service" "postinst (install)"
[ "$(stat -c %a "$state")" = 750 ] || fail "state directory mode $(stat -c %a "$state")"
# Never into a foreign root's running systemd (DPKG_ROOT set): nothing started.
refuse_call "deb-systemd-invoke" "postinst (DPKG_ROOT)"
refuse_call "systemctl" "postinst (DPKG_ROOT)"

# Upgrade: the user exists, the database stays.
echo data >"$state/magcal.db"
: >"$calls"
run_script postinst configure 0.0.9
refuse_call "adduser" "postinst (upgrade, user exists)"
expect_call "chown magcal:magcal $state" "postinst (upgrade)"
[ "$(cat "$state/magcal.db")" = data ] || fail "postinst touched the database"

: >"$calls"
run_script prerm remove
run_script postrm remove
expect_call "deb-systemd-helper mask magcald.service" "postrm remove"
run_script postrm purge
expect_call "deb-systemd-helper purge magcald.service" "postrm purge"
[ "$(cat "$state/magcal.db")" = data ] || fail "remove/purge deleted the database"
refuse_call "deb-systemd-invoke" "prerm/postrm (DPKG_ROOT)"
echo "maintainer scripts: install, upgrade, remove, purge as expected against $root"

# --- the real thing, where it is safe: CI runs as root on a throw-away machine
if [ "${CI:-}" = true ] && [ "$(id -u)" = 0 ]; then
  # A magcal left installed (an earlier run killed mid-test) is upgraded, then purged too.
  installed_here=1
  dpkg -i "$deb" >"$scratch/dpkg.log" 2>&1 || {
    cat "$scratch/dpkg.log" >&2
    fail "dpkg -i"
  }
  getent passwd magcal >/dev/null || fail "dpkg -i: no magcal user"
  [ "$(stat -c %U:%G:%a /var/lib/magcal)" = magcal:magcal:750 ] ||
    fail "/var/lib/magcal is $(stat -c %U:%G:%a /var/lib/magcal)"
  [ "$(/usr/bin/magcald --version)" = "$version" ] || fail "installed magcald --version"
  wants=/etc/systemd/system/multi-user.target.wants/magcald.service
  [ -L "$wants" ] || fail "dpkg -i did not enable magcald.service"
  dpkg -i "$deb" >>"$scratch/dpkg.log" 2>&1 || {
    cat "$scratch/dpkg.log" >&2
    fail "dpkg -i over itself (upgrade path)"
  }
  touch /var/lib/magcal/package-test-marker
  dpkg -r magcal >>"$scratch/dpkg.log" 2>&1 || fail "dpkg -r"
  [ ! -e /usr/bin/magcald ] || fail "dpkg -r left /usr/bin/magcald"
  [ -e /var/lib/magcal/package-test-marker ] || fail "dpkg -r deleted /var/lib/magcal content"
  [ -e /etc/magcal/magcald.toml ] || fail "dpkg -r removed the conffile (only purge does)"
  [ "$(readlink /etc/systemd/system/magcald.service)" = /dev/null ] ||
    fail "dpkg -r did not disable (mask) magcald.service"
  dpkg --purge magcal >>"$scratch/dpkg.log" 2>&1 || fail "dpkg --purge"
  installed_here=0
  [ ! -e /etc/magcal/magcald.toml ] || fail "dpkg --purge left the conffile"
  if [ -L "$wants" ] || [ -L /etc/systemd/system/magcald.service ]; then
    fail "dpkg --purge left systemd links"
  fi
  [ -e /var/lib/magcal/package-test-marker ] || fail "dpkg --purge deleted /var/lib/magcal content"
  rm -f /var/lib/magcal/package-test-marker
  echo "dpkg -i (twice), -r, --purge on this machine: ok"
else
  echo "not CI as root: no real dpkg -i (the scripts ran against $root only)"
fi
echo "package test passed"
