#!/usr/bin/env python3
"""Applies a `magcal export --format csv` table to the raw samples of a sample CSV, as on-board
software would, with nothing of magcal but the table (docs/export.md):

    B_cal = M B - o - o_T (T - T0) - o_r (t - t_ref)        (t - t_ref in hours)

and compares the result with
  - the calibrated field of the fit the table came from, B_cal = R^T ((I + D) B - b) with
    b(t, T) = b + k_T (T - T0) + r (t - t_ref) (estimation.md section 1), computed here from the
    fit's JSON (`magcal fit --json`): the largest difference must stay within the table's stated
    rounding error;
  - the simulator's reference field h (the sample CSV's hx_nT..hz_nT): the rms error per axis.

Usage: apply_uplink_table.py TABLE.csv SAMPLES.csv FIT.json
Prints one JSON object; exit 0 when the table reproduces the fit within its stated rounding,
1 otherwise. Python standard library only.
"""
import csv
import json
import math
import sys


def read_table(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {row["name"]: row["value"] for row in rows}


def number(table, name):
    text = table[name]
    return float(text) if text != "" else None


def main():
    table_path, samples_path, fit_path = sys.argv[1:4]
    table = read_table(table_path)
    if table["format"] != "magcal-calibration-table" or table["format_version"] != "1":
        print("unknown table format", file=sys.stderr)
        return 1
    M = [[number(table, f"M{r}{c}") for c in (1, 2, 3)] for r in (1, 2, 3)]
    o = [number(table, f"o_{a}") for a in "xyz"]
    T0 = number(table, "T0")
    o_T = [number(table, f"o_T_{a}") for a in "xyz"]
    t_ref_s = number(table, "t_ref_utime") * 1e-6 if table["t_ref_utime"] else None
    o_r = [number(table, f"o_r_{a}") for a in "xyz"]
    stated_nT = number(table, "rounding_error_at_field")
    stated_field_nT = number(table, "rounding_field")

    with open(fit_path) as f:
        fit = json.load(f)
    b = fit["bias_nT"]
    D = fit["D"]
    R = fit.get("R_sensor_from_body", [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    k_T = fit.get("temperature_coefficient_nT_per_C")
    T0_fit = fit.get("reference_temperature_C")
    rate = fit.get("bias_rate_nT_per_h")
    t_end_s = fit["window_end_utime"] * 1e-6

    worst_vs_fit = 0.0
    worst_field = 0.0
    sum2 = [0.0, 0.0, 0.0]
    n = 0
    with open(samples_path, newline="") as f:
        for row in csv.DictReader(f):
            B = [float(row[f"b{a}_nT"]) for a in "xyz"]
            h = [float(row[f"h{a}_nT"]) for a in "xyz"]
            t_s = float(row["t_s"])
            T = float(row["temperature_C"]) if row.get("temperature_C", "") != "" else None
            # The table alone.
            cal = [sum(M[r][c] * B[c] for c in range(3)) - o[r] for r in range(3)]
            if T0 is not None:
                if T is None:
                    continue
                cal = [cal[r] - o_T[r] * (T - T0) for r in range(3)]
            if t_ref_s is not None:
                cal = [cal[r] - o_r[r] * (t_s - t_ref_s) / 3600.0 for r in range(3)]
            # The fit's model.
            bias = list(b)
            if k_T is not None:
                bias = [bias[r] + k_T[r] * (T - T0_fit) for r in range(3)]
            if rate is not None:
                bias = [bias[r] + rate[r] * (t_s - t_end_s) / 3600.0 for r in range(3)]
            u = [B[r] + sum(D[r][c] * B[c] for c in range(3)) - bias[r] for r in range(3)]
            model = [sum(R[c][r] * u[c] for c in range(3)) for r in range(3)]
            worst_vs_fit = max(worst_vs_fit, math.dist(cal, model))
            worst_field = max(worst_field, math.hypot(*B))
            for r in range(3):
                sum2[r] += (cal[r] - h[r]) ** 2
            n += 1
    rms = [math.sqrt(s / n) for s in sum2] if n else [float("nan")] * 3
    ok = n > 0 and worst_field <= stated_field_nT and worst_vs_fit <= stated_nT
    print(json.dumps({"n": n, "worst_vs_fit_nT": worst_vs_fit, "stated_rounding_nT": stated_nT,
                      "largest_field_nT": worst_field, "rms_vs_reference_nT": rms, "ok": ok}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
