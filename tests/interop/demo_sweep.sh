#!/usr/bin/env bash
# The demo on more than its own seed (issue 14: a machine builder judges the instrument on the
# first long axis they bring): `axiscomp demo --seed S --length-mm L` for every S:L in
# DEMO_SWEEP, two at a time, each judged by the twin's truth with demo_check.py (every target
# and direction of the run before compensation against must-show 1's limits, the truth inside
# U at >= 95 % of the points). Prints one line per case and a summary; fails if any case fails.
#   bash tests/interop/demo_sweep.sh                          # the CI cases
#   DEMO_SWEEP="1:500 2:1000 3:2000" bash tests/interop/demo_sweep.sh
#   AXISCOMP_BIN=/path/to/axiscomp KEEP=1 bash tests/interop/demo_sweep.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
# A 500, a 1000 and two 2000 mm axes that are not the README's seeds (those run in the step
# before): seeds 1 and 4 at 2000 mm were the worst of the 15-head sweep before the level's
# stations and the fixed-side approach (roll 0.56 and 0.99 arcsec, positioning 1.53 µm).
DEMO_SWEEP=${DEMO_SWEEP:-"5:500 1:1000 1:2000 4:2000"}
if [ -n "${AXISCOMP_BIN:-}" ]; then
  bin=$AXISCOMP_BIN
else
  cargo build --release --locked --quiet
  bin=$PWD/target/release/axiscomp
fi
work=$(mktemp -d)
cleanup() { if [ -z "${KEEP:-}" ]; then rm -rf "$work"; else echo "kept $work"; fi; }
trap cleanup EXIT

one() {
  local seed=${1%%:*} len=${1##*:}
  local out="$work/s$seed-l$len" t0=$SECONDS
  if ! "$bin" demo --seed "$seed" --length-mm "$len" --out "$out" >"$out.log" 2>&1; then
    echo "seed $seed, $len mm: the demo failed (its output: $out.log)"
    tail -5 "$out.log"
    return 1
  fi
  if python3 tests/interop/demo_check.py "$out" >"$out.check" 2>&1; then
    echo "seed $seed, $len mm: PASS ($((SECONDS - t0)) s)"
  else
    cat "$out.check"
    return 1
  fi
}
export -f one
export bin work

failed=0
printf '%s\n' $DEMO_SWEEP | xargs -P 2 -I{} bash -c 'one {}' || failed=1
# The worst of every DOF over the sweep, against the truth.
python3 - "$work" <<'EOF'
import glob, json, sys
dofs = ["dx", "dy", "dz", "ex", "ey", "ez"]
unit = {"dx": "µm", "dy": "µm", "dz": "µm", "ex": "″", "ey": "″", "ez": "″"}
worst, big, inside, total = {d: 0.0 for d in dofs}, {d: 0.0 for d in dofs}, 0, 0
for f in glob.glob(sys.argv[1] + "/*/summary.json"):
    pts = [p for p in json.load(open(f, encoding="utf-8"))["points"] if p["run"] == "before"]
    for p in pts:
        e = abs(p["measured"] - p["truth"])
        worst[p["dof"]] = max(worst[p["dof"]], e)
        big[p["dof"]] = max(big[p["dof"]], p["U"])
        inside += e <= p["U"]
        total += 1
print("over the sweep, max |measured - truth| / largest U: " + ", ".join(
    f"{d} {worst[d]:.3f}/{big[d]:.3f} {unit[d]}" for d in dofs))
print(f"the truth inside U at {inside} of {total} points")
EOF
if [ "$failed" != 0 ]; then
  echo "demo sweep: FAIL" >&2
  exit 1
fi
echo "demo sweep: PASS"
