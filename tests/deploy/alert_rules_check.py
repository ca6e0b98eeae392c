#!/usr/bin/env python3
"""Checks deploy/prometheus/magcal-alerts.yml against design.md's metric names.

  alert_rules_check.py RULES.yml RULES_TEST.yml [DESIGN.md]

- The rules file parses as YAML, every rule is an alert with expr, severity and summary.
- Every metric an expression names is one of design.md "Operations surface" (the list below,
  copied from there; a histogram adds _bucket/_sum/_count), with only that metric's labels in
  its matchers; every other word in an expression is PromQL or a label name.
- Every alert has a promtool unit test in RULES_TEST.yml that expects it to fire and one that
  expects it quiet.
- With DESIGN.md given and present, the list below is exactly the names design.md pins.
Prints one line per problem and exits 1 if there is any.
"""
import re
import sys

import yaml

# design.md, "Operations surface", GET /metrics: name -> labels.
DESIGN_METRICS = {
    "magcal_samples_received_total": {"sat"},
    "magcal_samples_stored_total": {"sat"},
    "magcal_samples_rejected_total": {"reason"},
    "magcal_samples_missing_total": {"sat"},
    "magcal_queue_depth": set(),
    "magcal_queue_overflow_total": set(),
    "magcal_sqlite_commit_seconds": set(),  # histogram
    "magcal_ukf_bias_nT": {"sat", "axis"},
    "magcal_ukf_bias_sigma_nT": {"sat", "axis"},
    "magcal_refits_total": {"sat", "verdict"},
    "magcal_last_refit_success_timestamp_seconds": {"sat"},
    "magcal_build_info": {"version"},
}
HISTOGRAMS = {"magcal_sqlite_commit_seconds"}
# Labels Prometheus adds to every scraped series.
TARGET_LABELS = {"job", "instance"}
PROMQL_WORDS = {
    # functions used or plausible in these rules
    "abs", "absent", "absent_over_time", "avg_over_time", "changes", "delta", "deriv",
    "histogram_quantile", "increase", "irate", "max_over_time", "min_over_time", "rate",
    "resets", "time", "timestamp", "vector", "scalar", "clamp_min", "clamp_max",
    # aggregations, operators and modifiers
    "sum", "min", "max", "avg", "count", "by", "without", "on", "ignoring", "group_left",
    "group_right", "and", "or", "unless", "bool", "offset",
}


def metric_names(expr):
    """(metric, set of matcher label names) for every series selector in a PromQL expression,
    and the other words (functions, keywords, grouping labels)."""
    selectors, words = [], []
    text = re.sub(r"\[[^\]]*\]", " ", expr)  # ranges [10m] and subqueries
    for m in re.finditer(r"([A-Za-z_:][A-Za-z0-9_:]*)\s*(\{[^}]*\})?", text):
        name, matchers = m.group(1), m.group(2)
        if name in PROMQL_WORDS and not matchers:
            words.append(name)
            continue
        if name.startswith("magcal_") or matchers:
            labels = set(re.findall(r"([A-Za-z_][A-Za-z0-9_]*)\s*(?:=~|!~|!=|=)", matchers or ""))
            selectors.append((name, labels))
        else:
            words.append(name)
    # Label names in by (...) / without (...) / on (...) / ignoring (...).
    grouping = set()
    for g in re.finditer(r"\b(?:by|without|on|ignoring)\s*\(([^)]*)\)", text):
        grouping.update(x.strip() for x in g.group(1).split(",") if x.strip())
    return selectors, words, grouping


def design_names(path):
    text = open(path, encoding="utf-8").read()
    start = text.find("## Operations surface")
    section = text[start:] if start >= 0 else text
    return set(re.findall(r"`(magcal_[A-Za-z0-9_]+)", section))


def main():
    rules_path, tests_path = sys.argv[1], sys.argv[2]
    design_path = sys.argv[3] if len(sys.argv) > 3 else None
    problems = []
    rules = yaml.safe_load(open(rules_path, encoding="utf-8"))
    alerts = []
    for group in rules["groups"]:
        for rule in group["rules"]:
            name = rule.get("alert")
            if not name:
                problems.append(f"not an alert rule: {rule}")
                continue
            alerts.append(name)
            if rule.get("labels", {}).get("severity") not in ("warning", "critical"):
                problems.append(f"{name}: severity must be warning or critical")
            if not rule.get("annotations", {}).get("summary"):
                problems.append(f"{name}: no summary annotation")
            selectors, words, grouping = metric_names(str(rule["expr"]))
            if not selectors:
                problems.append(f"{name}: names no magcal metric")
            for metric, labels in selectors:
                base = metric
                for suffix in ("_bucket", "_sum", "_count"):
                    if metric.endswith(suffix) and metric[: -len(suffix)] in HISTOGRAMS:
                        base = metric[: -len(suffix)]
                if base not in DESIGN_METRICS:
                    problems.append(f"{name}: metric {metric} is not one of design.md's")
                    continue
                allowed = DESIGN_METRICS[base] | TARGET_LABELS | ({"le"} if base != metric else set())
                for label in labels - allowed:
                    problems.append(f"{name}: {metric} has no label '{label}'")
            known_labels = set().union(*DESIGN_METRICS.values()) | TARGET_LABELS | {"le"}
            for label in grouping - known_labels:
                problems.append(f"{name}: groups by unknown label '{label}'")
            for word in set(words) - PROMQL_WORDS - known_labels:
                problems.append(f"{name}: unknown word '{word}' (a misspelt metric?)")

    tests = yaml.safe_load(open(tests_path, encoding="utf-8"))
    fires, quiet = set(), set()
    for test in tests["tests"]:
        for case in test.get("alert_rule_test", []):
            (fires if case.get("exp_alerts") else quiet).add(case["alertname"])
    for name in alerts:
        if name not in fires:
            problems.append(f"{name}: no promtool test where it fires")
        if name not in quiet:
            problems.append(f"{name}: no promtool test where it stays quiet")

    if design_path:
        try:
            pinned = design_names(design_path)
        except OSError:
            print(f"note: {design_path} not found; the metric list was not re-checked against it")
        else:
            if pinned != set(DESIGN_METRICS):
                problems.append(
                    f"the test's metric list differs from design.md: only in design.md "
                    f"{sorted(pinned - set(DESIGN_METRICS))}, only here "
                    f"{sorted(set(DESIGN_METRICS) - pinned)}")
            else:
                print(f"metric list matches {design_path} ({len(pinned)} names)")

    for p in problems:
        print(p)
    print(f"{len(alerts)} alerts checked, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
