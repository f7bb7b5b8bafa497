#!/usr/bin/env bash
# Issue 30's must-shows 1 and 4 on twins the trend was not tuned on: `axiscomp demo --trend
# --seed S` for every S in TREND_SEEDS, two at a time (about 2.5 min each alone), each judged by
# the twin's truth with trend_check.py: the positioning drift alarmed within 3 checks of its
# onset and not before, the forecast's stated interval holding the twin's day, a composed table
# proposed, published and the check after it within the limits; must-show 1's 1 % false alarms
# per figure over a stable machine's 200 checks and its forecast within ±20 % are judged and
# printed OPEN where they miss (issue 30). Fails if any seed fails.
#   bash tests/interop/trend_sweep.sh                         # the CI seeds
#   TREND_SEEDS="5 6" AXISCOMP_BIN=/path/to/axiscomp KEEP=1 bash tests/interop/trend_sweep.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
# Seeds 7, 11 and 23 are the ones the trend demo was developed on; these are not.
TREND_SEEDS=${TREND_SEEDS:-"31 47 59"}
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
  local seed=$1 out="$work/s$1" t0=$SECONDS
  if ! "$bin" demo --trend --seed "$seed" --out "$out" >"$out.log" 2>&1; then
    echo "seed $seed: demo --trend failed (its output: $out.log)"
    tail -5 "$out.log"
    return 1
  fi
  if python3 tests/interop/trend_check.py "$out" >"$out.check" 2>&1; then
    echo "seed $seed: PASS ($((SECONDS - t0)) s)"
    grep -E 'alarmed|forecast on|interval|composed table|OPEN|passed' "$out.check" | sed 's/^/  /'
  else
    echo "seed $seed: FAIL"
    cat "$out.check"
    return 1
  fi
}
export -f one
export bin work

if printf '%s\n' $TREND_SEEDS | xargs -P 2 -I{} bash -c 'one {}'; then
  echo "trend sweep: PASS"
else
  echo "trend sweep: FAIL" >&2
  exit 1
fi
