#!/usr/bin/env bash
# magcal demo: simulate a day of the paper scenario, replay it through the daemon (refits on
# the data clock), then show what an operator sees. Builds nothing: run it after the build.
#   deploy/demo.sh [BIN_DIR]      (default: build/bin next to this script's repository)
# Each run uses a fresh temporary directory and database, removed at the end
# (set KEEP=1 to keep it).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bin="$(cd "${1:-${MAGCAL_BIN_DIR:-$here/../build/bin}}" && pwd)"
for exe in magcal magcald; do
  if [[ ! -x "$bin/$exe" ]]; then
    echo "demo.sh: $bin/$exe not found: build first (cmake --build build -j2)" >&2
    exit 1
  fi
done

work="$(mktemp -d -t magcal-demo.XXXXXX)"
if [[ "${KEEP:-0}" != 1 ]]; then trap 'rm -rf "$work"' EXIT; fi
cd "$work"
sat=PAPER-1

echo "== 1. simulate 24 h of the paper scenario (one spacecraft, 10 s samples, 200 per packet)"
"$bin/magcal" sim --scenario paper --hours 24 --seed 1 --out day.lcm --truth truth.json --batch 200

# Everything else is magcald's embedded default: the only setting is what a replay needs, the
# data clock (refits scheduled by sample time), here every 6 h of data. The 02:00 slot of the
# first day has too few samples ([refit] min_samples) and is skipped; 08:00 (an 8 h window),
# 14:00 and 20:00 run. On top of the schedule a new spacecraft gets early refits, at
# [refit] min_samples stored samples and each time they grow by [refit] early_growth (sqrt 2),
# until its data span the 12 h window. The UKF starts from a batch solution of its first
# samples once they observe the parameters, adapts its noise to what the data show, and is
# re-anchored on every accepted refit.
cat > magcald.toml <<'TOML'
[refit]
clock = "data"
every_hours = 6
TOML

echo
echo "== 2. replay it through magcald (file:// replay: same code path as live, exits at the end)"
# The operations server (/metrics, /-/healthy, /-/ready, the API and the page) runs while it
# does (a fraction of a second here), on any free loopback port (a live magcald may hold the
# default 127.0.0.1:9780); `magcal serve` (printed at the end) browses the day afterwards.
"$bin/magcald" --config magcald.toml --db magcal.db --lcm-url "file://$work/day.lcm?speed=0" \
  --http-listen 127.0.0.1:0 --log-level info 2>&1 | sed -e 's/^\[[^]]*\] //'

echo
echo "== 3. magcal status"
"$bin/magcal" status --db magcal.db

echo
echo "== 4. UKF converging (history, every 2 h of data; then the last snapshot)"
"$bin/magcal" history --db magcal.db --sat "$sat" --method ukf --format table \
  | awk 'NR == 1 || (NR - 2) % 120 == 0 { print } { last = $0 } END { print last }'

echo
echo "== 5. refits: early (at [refit] min_samples stored samples, then each x sqrt 2 until a full window) and scheduled (centered + LM + alignment, acceptance gates)"
"$bin/magcal" history --db magcal.db --sat "$sat" --method twostep --format table

echo
echo "== 6. truth (from the simulator)"
flat="$(tr -d ' \n' < truth.json)"
echo "bias_nT $(grep -o '"bias_nT":\[[^]]*\]' <<< "$flat" | cut -d: -f2)"
echo "D       $(grep -o '"D":\[\[[^]]*\],\[[^]]*\],\[[^]]*\]\]' <<< "$flat" | cut -d: -f2)"

echo
# The replay's own operations server ended with it (a replay exits at the end of its log).
if [[ "${KEEP:-0}" == 1 ]]; then
  echo "== the plots page and API over this day: $bin/magcal serve --db $work/magcal.db  (then http://127.0.0.1:9780/)"
else
  echo "== to browse this day in the plots page: KEEP=1 ./deploy/run-demo.sh, then the magcal serve line it prints"
fi
