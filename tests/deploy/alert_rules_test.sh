#!/usr/bin/env bash
# deploy/prometheus/magcal-alerts.yml (issue 12, item 5): `promtool check rules` (syntax, PromQL),
# `promtool test rules` (magcal-alerts.test.yml: each alert fires on a synthetic series and
# stays quiet on healthy ones) and alert_rules_check.py (YAML parse; every metric name and label
# one of design.md's; every alert tested both ways).
#   alert_rules_test.sh SOURCE_DIR
set -euo pipefail
source_dir="$1"
here="$(cd "$(dirname "$0")" && pwd)"
# shellcheck source-path=SCRIPTDIR source=test_skip.sh
. "$here/test_skip.sh"
rules="$source_dir/deploy/prometheus/magcal-alerts.yml"

# Debian's python3 with python3-yaml (deploy/setup-deps.sh), whatever else is on PATH.
python=/usr/bin/python3
[ -x "$python" ] || python=python3
"$python" -c 'import yaml' 2>/dev/null || skip_or_fail "python3 with the yaml module (python3-yaml)"
"$python" "$here/alert_rules_check.py" "$rules" "$here/magcal-alerts.test.yml" \
  "$source_dir/../shared/spec/design.md" || fail "alert_rules_check.py"

need_tool promtool
promtool check rules "$rules" || fail "promtool check rules"
promtool test rules "$here/magcal-alerts.test.yml" || fail "promtool test rules"
echo "alert rules test passed"
