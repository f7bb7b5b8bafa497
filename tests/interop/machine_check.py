#!/usr/bin/env python3
"""`axiscomp demo --machine`'s summary.json judged by the twin's truth (issue 27, must-show 1):
every squareness within 1.0 arcsec of the truth and inside its U; the volumetric error after
the Beckhoff file was applied at most a tenth of before (largest over the points) and its RMS
at most 1.5 um; every set-up's six component errors within issue 14's limits (1 um positioning,
0.5 um straightness, 0.5 arcsec roll, 0.3 arcsec pitch and yaw); and (must-show 2) each
control's files applied give the model's own after-figures: Beckhoff's and HEIDENHAIN's within
0.01 um, FANUC's grid within 0.15 um largest and 0.02 um RMS (Siemens's, without the angles,
reported).

  machine_check.py DIR     # DIR holds summary.json
Prints one line per check that fails and a summary; exits 1 on any failure."""
import json
import sys
from pathlib import Path


def limits(axis, name):
    # ISO 230-1 names: E<error><axis>; positioning is E<axis><axis>, roll EA for X, EB for Y, EC for Z.
    err = name[1]
    if err == axis:
        return 1.0, "um"
    if err in "XYZ":
        return 0.5, "um"
    if "XYZ".index(axis) == "ABC".index(err):
        return 0.5, "arcsec"
    return 0.3, "arcsec"


def main():
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    path = Path(sys.argv[1]) / "summary.json"
    try:
        m = json.loads(path.read_text())["machine"]
    except (OSError, ValueError, KeyError) as e:
        print(f"{path}: not a machine demo's summary ({e})", file=sys.stderr)
        return 1
    bad = []
    for a in m["axes"]:
        for name, v in a["worst_off"].items():
            lim, unit = limits(a["axis"], name)
            if abs(v) > lim:
                bad.append(f"{a['axis']} ({a['setup']}): {name} {v:.2f} {unit} off the truth, beyond {lim} {unit}")
    for s in m["squareness"]:
        off = abs(s["measured_arcsec"] - s["truth_arcsec"])
        if off > 1.0 or off > s["U_arcsec"]:
            bad.append(f"{s['name']} ({s['pair']}): {s['measured_arcsec']:+.2f} against the truth "
                       f"{s['truth_arcsec']:+.2f} arcsec, {off:.2f} off with U {s['U_arcsec']:.2f}")
    v = m["volumetric"]
    if v["after_max_um"] > 0.1 * v["before_max_um"]:
        bad.append(f"volumetric: {v['after_max_um']:.2f} um largest after, more than a tenth of {v['before_max_um']:.1f}")
    if v["after_rms_um"] > 1.5:
        bad.append(f"volumetric: {v['after_rms_um']:.2f} um RMS after, beyond 1.5 um")
    if abs(v["after_rms_um"] - v["model_after_rms_um"]) > 0.01 or abs(v["after_max_um"] - v["model_after_max_um"]) > 0.01:
        bad.append(f"the file applied gives {v['after_max_um']:.3f}/{v['after_rms_um']:.3f} um, "
                   f"the model {v['model_after_max_um']:.3f}/{v['model_after_rms_um']:.3f} um")
    # Must-show 2: each control's files, read back and applied by the twin's CNC, against the
    # model itself. Beckhoff's and HEIDENHAIN's carry the 21 errors (the same figures within
    # 0.01 um); FANUC's 10 mm grid (its corners curvature-balanced) blends between its corners,
    # which moves the largest a little either way (within 0.15 um largest and 0.02 um RMS:
    # seeds 101-105 and 7 by -0.04 to +0.09 um, RMS by at most 0.01 um);
    # Siemens's EEC and CEC tables carry no angles (reported, not bounded).
    exports = {e["control"].split()[0]: e for e in m.get("exports", [])}
    for name, (dmax, drms) in {"Beckhoff": (0.01, 0.01), "HEIDENHAIN": (0.01, 0.01), "FANUC": (0.15, 0.02)}.items():
        e = exports.get(name)
        if e is None:
            bad.append(f"no {name} export in the summary")
            continue
        if not Path(e["path"]).exists():
            bad.append(f"{name}: {e['path']} is missing")
        if abs(e["after_max_um"] - v["model_after_max_um"]) > dmax or abs(e["after_rms_um"] - v["model_after_rms_um"]) > drms:
            bad.append(f"{name}'s files applied give {e['after_max_um']:.3f}/{e['after_rms_um']:.3f} um, "
                       f"the model {v['model_after_max_um']:.3f}/{v['model_after_rms_um']:.3f} um")
    for b in bad:
        print(f"machine_check: {b}")
    sq = ", ".join(f"{s['name']} {abs(s['measured_arcsec'] - s['truth_arcsec']):.2f}/{s['U_arcsec']:.2f}"
                   for s in m["squareness"])
    print(f"machine_check: {path}: squareness off/U (arcsec) {sq}; volumetric {v['before_max_um']:.1f} -> "
          f"{v['after_max_um']:.2f} um largest, {v['before_rms_um']:.1f} -> {v['after_rms_um']:.2f} um RMS; "
          f"machine time {m['machine_time_s'] / 60:.1f} min; applied from the files (largest/RMS um): "
          + ", ".join(f"{k} {e['after_max_um']:.2f}/{e['after_rms_um']:.2f}" for k, e in exports.items())
          + f"; {'FAILED' if bad else 'passed'}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
