#!/usr/bin/env python3
"""Independent ISO 230-2 calculation (plain Python, no numpy) of a raw positioning fixture.

Input: CSV with '#' comment lines and the header
    target_index,target_mm,run,direction,measured_mm
(direction '+' or '-'). Output on stdout: JSON in the shape of `axiscomp evaluate --json`,
in micrometres:
    {"targets": [{"x_up", "x_down", "x_mean", "B", "s_up", "s_down", "R_up", "R_down", "R"}...],
     "axis": {"A", "A_up", "A_down", "B", "B_mean", "R", "R_up", "R_down", "E", "E_up", "E_down", "M"}}

Written from the ISO 230-2 definitions (DESIGN.md section 7), not from the Rust code:
x_ij = P_ij - P_i; per target the mean and the sample standard deviation (n - 1) per
direction; B_i = mean_up - mean_down; R_i = max(2 s_up + 2 s_down + |B_i|, 4 s_up, 4 s_down).

With --against FILE (our JSON), compares every figure and exits 1 on a difference
larger than --tol micrometres (default 1e-9).

Usage: python3 tests/interop/iso230_2_check.py FIXTURE.csv [--against OURS.json] [--tol 1e-9]
"""

import json
import math
import sys


def read_fixture(path):
    header = None
    rows = []
    with open(path, encoding="utf-8") as f:
        for raw in f:
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = [x.strip() for x in line.split(",")]
            if header is None:
                header = fields
                continue
            rows.append(dict(zip(header, fields)))
    return rows


def evaluate(rows):
    # deviations[target][direction] -> {run: x in micrometres}
    targets = {}
    position = {}
    for r in rows:
        t = int(r["target_index"])
        p = float(r["target_mm"])
        x_um = (float(r["measured_mm"]) - p) * 1000.0
        position[t] = p
        targets.setdefault(t, {"+": {}, "-": {}})[r["direction"]][int(r["run"])] = x_um

    def mean(v):
        return math.fsum(v) / len(v)

    def sd(v):
        m = mean(v)
        return math.sqrt(math.fsum((x - m) ** 2 for x in v) / (len(v) - 1))

    per = []
    for t in sorted(targets, key=lambda k: position[k]):
        up = [targets[t]["+"][k] for k in sorted(targets[t]["+"])]
        dn = [targets[t]["-"][k] for k in sorted(targets[t]["-"])]
        xu, xd = mean(up), mean(dn)
        su, sdn = sd(up), sd(dn)
        b = xu - xd
        per.append({
            "x_up": xu, "x_down": xd, "x_mean": (xu + xd) / 2.0, "B": b,
            "s_up": su, "s_down": sdn, "R_up": 4.0 * su, "R_down": 4.0 * sdn,
            "R": max(2.0 * su + 2.0 * sdn + abs(b), 4.0 * su, 4.0 * sdn),
        })

    col = lambda k: [p[k] for p in per]
    hi_up = [p["x_up"] + 2.0 * p["s_up"] for p in per]
    lo_up = [p["x_up"] - 2.0 * p["s_up"] for p in per]
    hi_dn = [p["x_down"] + 2.0 * p["s_down"] for p in per]
    lo_dn = [p["x_down"] - 2.0 * p["s_down"] for p in per]
    axis = {
        "A": max(hi_up + hi_dn) - min(lo_up + lo_dn),
        "A_up": max(hi_up) - min(lo_up),
        "A_down": max(hi_dn) - min(lo_dn),
        "B": max(abs(b) for b in col("B")),
        "B_mean": mean(col("B")),
        "R": max(col("R")),
        "R_up": max(col("R_up")),
        "R_down": max(col("R_down")),
        "E": max(col("x_up") + col("x_down")) - min(col("x_up") + col("x_down")),
        "E_up": max(col("x_up")) - min(col("x_up")),
        "E_down": max(col("x_down")) - min(col("x_down")),
        "M": max(col("x_mean")) - min(col("x_mean")),
    }
    return {"targets": per, "axis": axis}


def compare(mine, ours, tol):
    bad = []
    if len(mine["targets"]) != len(ours["targets"]):
        bad.append("target count %d vs %d" % (len(mine["targets"]), len(ours["targets"])))
    for i, (a, b) in enumerate(zip(mine["targets"], ours["targets"])):
        for k, v in a.items():
            if b.get(k) is None or abs(v - b[k]) > tol:
                bad.append("target %d %s: python %r, axiscomp %r" % (i, k, v, b.get(k)))
    for k, v in mine["axis"].items():
        w = ours["axis"].get(k)
        if w is None or abs(v - w) > tol:
            bad.append("axis %s: python %r, axiscomp %r" % (k, v, w))
    return bad


def main(argv):
    if len(argv) < 2:
        sys.stderr.write(__doc__)
        return 2
    mine = evaluate(read_fixture(argv[1]))
    if "--against" in argv:
        tol = float(argv[argv.index("--tol") + 1]) if "--tol" in argv else 1e-9
        with open(argv[argv.index("--against") + 1], encoding="utf-8") as f:
            ours = json.load(f)
        bad = compare(mine, ours, tol)
        for b in bad:
            print(b)
        print("%d differences" % len(bad))
        return 1 if bad else 0
    json.dump(mine, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
