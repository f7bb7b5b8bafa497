#!/usr/bin/env bash
# The console in a real terminal (issue 6, must-show 3): tmux runs `axiscomp console` at 80×24
# (or CONSOLE_SIZE, e.g. 160x48: .ci/run walks both; issue 29, must-show 5)
# against `axiscomp sim` + `axiscomp serve` (the twin's CNC runs the part programs), keys go in
# with send-keys and every screen is checked with capture-pane: Live, help, Align, the beam
# alignment (issue 13, must-show 4: the twin's head is knocked off the axis, and the script does
# what the Align screen tells a technician — the carriage moved to each end of -1–400 mm, the
# spots read, the targets typed where a spot is off its PSD, the screws turned as the screen
# says — until the screen shows the check passed; the zero taken at 0 mm), the plan typed into
# Measure (its travel inside the alignment: the service's pre-run check lets it start), start,
# progress, the finished run's results, the audit log on Events, quit (the terminal given back,
# exit status 0), then NO_COLOR. Exits non-zero on the first screen that does not show what it
# should, printing that screen. Then the maintenance story (issue 15, must-show 4): the
# commissioning run's tables generated and published on Publish (the PLC's status words and
# active tables checked on screen), the twin's axis aged through its control socket, the plan
# measured again on Measure (under the active tables), the commissioning run found on Results
# by the date its row shows and compared (b) with the re-measurement, the axis's trends shown
# (t: issue 30, must-show 3), the re-measurement's tables, which Publish
# shows composed of the active table and the residual; the positioning one published, the PLC
# then applying its sequence. Then the Calibrate screen (issue 17): a hexapod calibration of
# 40 poses started by keys against the twin's PI controller, followed to its fit and accepted.
# Needs tmux and python3 (.ci/run installs tmux).
#   bash tests/interop/console.sh            # from anywhere in the repository
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
command -v tmux >/dev/null || { echo "console.sh: tmux not found" >&2; exit 1; }
command -v python3 >/dev/null || { echo "console.sh: python3 not found" >&2; exit 1; }

# AXISCOMP_BIN: a binary built already (.ci/run builds one for every script).
if [ -n "${AXISCOMP_BIN:-}" ]; then
  bin=$AXISCOMP_BIN
else
  cargo build --locked -q
  bin="${CARGO_TARGET_DIR:-target}/debug/axiscomp"
fi
[ -x "$bin" ] || { echo "console.sh: no binary at $bin" >&2; exit 1; }

# CONSOLE_SIZE: the terminal the walk runs in (default 80x24; .ci/run also runs it at 160x48).
size=${CONSOLE_SIZE:-80x24}
cols=${size%x*}
rows=${size#*x}
echo "console.sh: the walk at ${cols}×${rows}"
# From 120 columns the screens lay out wider: Results shows every error's figures and charts at
# once, the run list names its columns.
wide=""
[ "$cols" -ge 120 ] && wide=1

work=$(mktemp -d)
tmx=(tmux -L "axiscomp-console-$$" -f /dev/null)
sim=""
svc=""
cleanup() {
  "${tmx[@]}" kill-server 2>/dev/null || true
  [ -n "$svc" ] && kill "$svc" 2>/dev/null
  [ -n "$sim" ] && kill "$sim" 2>/dev/null
  wait 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

fail() {
  echo "console.sh: FAIL: $*" >&2
  echo "---- the screen ----" >&2
  "${tmx[@]}" capture-pane -p -t console >&2 2>/dev/null || true
  echo "---- the service's calibration (the screen may cut it off) ----" >&2
  [ -S "${sock:-}" ] && svc_cmd '{"cmd":"calibration"}' >&2 2>&1 || true
  echo "---- service log (tail) ----" >&2
  tail -n 20 "$work/serve.log" >&2 || true
  exit 1
}

# The twin and the service on free loopback ports, the twin's CNC running the programs. A
# port found free can be taken by another lane before the twin binds it (CI once: the twin
# gone, the service refused on its ports for a minute): a twin that is not running a second
# after it started is started again on other ports, twice at most, its log shown.
source tests/interop/twin-configs.sh
for attempt in 1 2 3; do
  TWIN_HEXAPOD_PORTS=free twin_configs "$work"
  # Handovers and captures quicker than in production so the short plan takes well under a
  # minute.
  cat >> "$work/service.toml" <<EOF

[tracking]
rest_ms = 200
average_frames = 100
settle_ms = 100

[capture]
frames = 100
settle_ms = 200
EOF
  "$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
  sleep 1
  kill -0 "$sim" 2>/dev/null && break
  echo "console.sh: the twin did not start (attempt $attempt):" >&2
  tail -n 5 "$work/sim.log" >&2
  [ "$attempt" = 3 ] && exit 1
done
RUST_LOG=warn "$bin" serve --config "$work/service.toml" >"$work/serve.log" 2>&1 & svc=$!

# The service is up with the follower homed and the stitch referenced.
wait_ready() {
  local ready=""
  for _ in $(seq 1 120); do
    if "$bin" status --socket "$work/control.sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
sys.exit(0 if s["follower"]["homed"] and s["tracking"]["valid"] and s["tracking"]["at_rest"] else 1)
' 2>/dev/null; then ready=1; break; fi
    sleep 0.5
  done
  [ -n "$ready" ] || {
    tail -n 20 "$work/serve.log" >&2
    echo "---- the twin's log (tail) ----" >&2
    tail -n 10 "$work/sim.log" >&2
    echo "console.sh: the service did not come up" >&2
    exit 1
  }
}
wait_ready

source tests/interop/tmux-screen.sh
# field VALUE: type VALUE into the selected plan field, then select the next one.
field() {
  keys Enter
  for _ in $(seq 1 12); do keys BSpace; done
  keys -l "$1"
  keys Enter Down
}

# The pane's shell writes the console's exit status to a file: tmux's own #{pane_dead_status}
# is sometimes empty after the process has been reaped (tmux 3.3a).
"${tmx[@]}" new-session -d -s console -x "$cols" -y "$rows" \
  "$bin console --socket $work/control.sock; echo \$? > $work/console.rc"
"${tmx[@]}" set-option -t console remain-on-exit on >/dev/null

echo "console.sh: Live"
expect 20 "1 Live" "Six errors" "● connected" "operator" "homed" "PSD1 pitch/yaw" "SUM"
expect 10 "dy "

echo "console.sh: help"
keys '?'
expect 5 "Help" "Live screen" "Every screen" "any key closes this help"
keys x
expect 5 "Six errors"

echo "console.sh: Align"
keys 2
expect 5 "Beam and centring" "PSD1 beam on" "Follower and zero" "jog step 0.1 mm"

echo "console.sh: Align, the beam aligned over -1–400 mm (the plan's travel and more) by following the screen"
# twin JSON: one request to the twin's control socket (twin-configs.sh); prints the reply.
twin() { twin_cmd "$1"; }
# psd2_lit: the service sees a spot on PSD2.
psd2_lit() {
  "$bin" status --socket "$work/control.sock" --json 2>/dev/null | python3 -c '
import json, sys
p = json.load(sys.stdin).get("psd") or {}
sys.exit(0 if (p.get("spots_um") or [None, None])[1] is not None else 1)'
}
# follower_to MM: the follower brought to the carriage (the control API's follower move).
sock="$work/control.sock"
follower_to() { svc_cmd "{\"cmd\":\"follower\",\"action\":\"move\",\"mm\":$1}" >/dev/null; }
# panel: the alignment panel's text, its rows joined (a long line may wrap).
panel() {
  screen | python3 -c '
import sys
rows = sys.stdin.read().splitlines()
start = next((i for i, r in enumerate(rows) if "Beam alignment over the travel" in r), None)
out = []
for r in rows[start + 1:] if start is not None else []:
    if r.lstrip().startswith("└"):
        break
    out.append(r.strip().strip("│").strip())
print(" ".join(out))'
}
# no_spot END: the PSDs the screen shows with no spot at the station at END mm.
no_spot() {
  panel | python3 -c '
import re, sys
t = sys.stdin.read()
m = re.search(r"at " + sys.argv[1] + r"\.0 mm: (.*?)(?= at -?\d|\s*span )", t)
print(" ".join(re.findall(r"PSD(\d) no spot", m.group(1))) if m else "")' "$1"
}
# The head knocked 4 mrad in yaw and 1 mrad in pitch: the spots run off the PSDs towards the
# far end (PSD2 still lit here, where the follower found it at start-up).
twin '{"cmd":"knock","yaw_urad":4000,"pitch_urad":-1000}' >/dev/null
mount0=$(twin '{"cmd":"mount"}')
keys 2
keys s
expect 5 "Alignment span"
for _ in $(seq 1 12); do keys BSpace; done
keys -l -- "-1 400"
keys Enter
expect 5 "span -1–400 mm (s)"
align_t0=$SECONDS
passed=""
for round in $(seq 1 8); do
  keys e
  expect 10 "no station read"
  for end in -1 400; do
    twin "{\"cmd\":\"move\",\"mm\":$end}" >/dev/null
    twin '{"cmd":"wait"}' >/dev/null
    sleep 1.5
    if ! psd2_lit; then
      echo "console.sh: round $round: PSD2 lost its spot on the way to $end mm: the follower brought to it"
      follower_to "$end"
      for _ in $(seq 1 60); do psd2_lit && break; sleep 0.5; done
      psd2_lit || fail "PSD2 has no spot at $end mm after the follower move"
      sleep 1.5
    fi
    if [ "$end" = -1 ]; then keys n; else keys f; fi
    expect 10 "at $end.0 mm:"
    # Where a PSD shows no spot, type what its target shows (the twin's target).
    missing=$(no_spot "$end")
    for k in $missing; do
      reading=$(twin '{"cmd":"target"}' | python3 -c '
import json, sys
t = json.load(sys.stdin)["targets"][int(sys.argv[1]) - 1]
print("" if t is None else "%s %s" % (t["x"], t["y"]))' "$k")
      if [ -z "$reading" ]; then
        echo "console.sh: round $round: PSD$k: no beam on its target either"
        continue
      fi
      keys t
      expect 5 "Target reading"
      for _ in $(seq 1 4); do keys BSpace; done
      keys -l "$k $reading"
      keys Enter
      for _ in $(seq 1 50); do
        grep -qw "$k" <<<"$(no_spot "$end")" || break
        sleep 0.2
      done
      grep -qw "$k" <<<"$(no_spot "$end")" && fail "round $round: PSD$k's target reading is not on the screen"
    done
  done
  keys a
  adv=""
  for _ in $(seq 1 50); do
    adv=$(panel)
    grep -qE "CHECK PASSED|check not passed" <<<"$adv" && break
    sleep 0.2
  done
  grep -qE "CHECK PASSED|check not passed" <<<"$adv" || fail "round $round: no advice on the screen"
  if grep -qF "CHECK PASSED" <<<"$adv"; then passed=$round; break; fi
  turns=$(python3 -c '
import re, sys
seen = {}
for screw, n, way in re.findall(r"turn the (yaw|pitch|x|z) screw (\d+\.\d+) turns? (clockwise|anticlockwise)", sys.argv[1]):
    seen.setdefault(screw, float(n) * (1 if way == "clockwise" else -1))
print(" ".join("%s=%s" % kv for kv in seen.items()))' "$adv")
  [ -n "$turns" ] || fail "round $round: the check did not pass and the screen names no screw to turn"
  echo "console.sh: round $round: turning $turns"
  for t in $turns; do
    twin "{\"cmd\":\"turn\",\"screw\":\"${t%%=*}\",\"turns\":${t#*=}}" >/dev/null
  done
done
[ -n "$passed" ] || fail "the check did not pass in 8 rounds"
expect 5 "beam to travel: yaw"
echo "console.sh: the screen says: $(panel)"
echo "console.sh: aligned in $passed rounds, $((SECONDS - align_t0)) s; mount before: $mount0; after: $(twin '{"cmd":"mount"}')"

echo "console.sh: back to 0 mm, the zero taken on the Align screen"
twin '{"cmd":"move","mm":0}' >/dev/null
twin '{"cmd":"wait"}' >/dev/null
sleep 1.5
if ! psd2_lit; then
  follower_to 0
  for _ in $(seq 1 60); do psd2_lit && break; sleep 0.5; done
  psd2_lit || fail "PSD2 has no spot at 0 mm after the follower move"
  sleep 1.5
fi
keys z
expect 15 "zero here"

echo "console.sh: Measure, the plan typed in"
keys 4
expect 5 "Plan (ISO 230-2)" "No run seen yet"
keys Down Down        # start, end
field 8
field 5               # targets
field 2               # runs
field 1               # overrun
field 1.5             # dwell
field 3000            # feed
field 0               # screw lead
expect 5 "✓ 20 captures" "targets (mm): 0.0 2.0 4.0 6.0 8.0"

echo "console.sh: start"
keys s
expect 5 "Start the run?" "Axis X, 0 to 8 mm, 5 targets, 2 bidirectional runs"
keys y
expect 15 "running" "/20" "captures in cycle order"

echo "console.sh: progress"
expect 60 "ETA" "run 1  ↑" "■"
expect 30 "dy positioning (µm)"

echo "console.sh: the run ends, its results"
expect 150 "finished: its results are on screen 5"
keys 5
if [ -n "$wide" ]; then
  expect 15 "X finished, 20 captures" "dy positioning (µm)" "ISO 230-2 / 230-1 figures" "A (accuracy)" "R (repeatability)" \
    "dz vertical straightness (µm)" "straightness (least squares)"
else
  expect 15 "X finished, 20 captures" "dy positioning (µm)" "Figures (←→ error)" "A (accuracy)" "R (repeatability)"
  keys Right
  expect 5 "dz vertical straightness (µm)" "straight LS"
fi
# The commissioning run's date as its row on the run list shows it: what a maintenance
# engineer finds it by years later.
run1_row=$(screen | grep -oE '▶ *(run +)?[0-9]+ +X finished +[0-9]+ (captures +)?[0-9]{4}-[0-9]{2}-[0-9]{2} [0-9]{2}:[0-9]{2}' | head -1)
[ -n "$run1_row" ] || fail "the run list shows no finished run with its date"
run1=$(sed -E 's/^▶ *(run +)?([0-9]+) .*/\2/' <<<"$run1_row")
run1_date=$(grep -oE '[0-9]{4}-[0-9]{2}-[0-9]{2} [0-9]{2}:[0-9]{2}$' <<<"$run1_row")
echo "console.sh: the commissioning run is run $run1 of $run1_date"

echo "console.sh: Events, the audit log"
keys 7
expect 10 "Alarms (UTC, newest first)" "This console's requests" "Audit log" "run_start X 0.0–8.0 mm, 5 targets, 2 runs"

echo "console.sh: maintenance (issue 15, must-show 4): the commissioning run's tables published"
# selected: the text the pane shows highlighted (reverse video), one line per row.
selected() {
  "${tmx[@]}" capture-pane -e -p -t console | python3 -c '
import re, sys
for row in sys.stdin.read().splitlines():
    rev, out = False, []
    for part in re.split(r"(\x1b\[[0-9;]*m)", row):
        if part.startswith("\x1b["):
            ps = [int(x) if x else 0 for x in part[2:-1].split(";")]
            i = 0
            while i < len(ps):
                if ps[i] in (38, 48):
                    i += 3 if ps[i + 1:i + 2] == [5] else 5
                    continue
                if ps[i] in (0, 27):
                    rev = False
                elif ps[i] == 7:
                    rev = True
                i += 1
        elif rev:
            out.append(part)
    if out:
        print("".join(out))'
}
# generate RUN: on the Publish screen, g, RUN picked from the list, Enter; prints the ids of
# the tables generated, the positioning one first (the status bar's "run N: tables 4 EXX,
# 5 EYX, 6 EZX generated").
generate() {
  keys g
  expect 10 "Generate tables from which run?" "run $1 "
  for _ in $(seq 1 6); do
    selected | grep -qE "^run $1 " && break
    keys Down
  done
  selected | grep -qE "^run $1 " || fail "run $1 could not be picked to generate tables from"
  keys Enter
  expect 30 "run $1: tables"
  screen | grep -oE "run $1: tables [0-9A-Z ,]+" | head -1 | grep -oE '[0-9]+ [A-Z]{3}' | cut -d' ' -f1 \
    | paste -sd' ' || true
}
# publish ID: select table ID on the Publish screen, p, its axis name typed as the box asks;
# prints the sequence the PLC committed it as.
publish() {
  local ax
  for _ in $(seq 1 12); do
    screen | grep -qE "Table $1 [A-Z]+ axis" && break
    keys Down
  done
  ax=$(screen | grep -oE "Table $1 [A-Z]+ axis [A-Z]" | grep -oE '[A-Z]$') \
    || fail "table $1 could not be selected"
  keys p
  expect 5 "Type the axis name \"$ax\""
  keys -l "$ax"
  keys Enter
  expect 30 "table $1 committed as sequence"
  screen | grep -oE "table $1 committed as sequence [0-9]+" | head -1 | grep -oE '[0-9]+$'
}
keys 6
expect 10 "Tables (map"
ids=$(generate "$run1")
[ -n "$ids" ] || fail "no table ids in the status bar after generating from run $run1"
seq=""
for id in $ids; do seq=$(publish "$id"); done
# The PLC's status words as the screen reads them back: ready, the last sequence active and
# accepted; every table of the run active, the positioning one named with its date and run.
expect 10 "PLC ready, active sequence $seq;" "commit: accepted sequence $seq" \
  "active: table ${ids%% *} positioning X seq"
pos1=$(screen | grep -oE "active: table [0-9]+ positioning X seq [0-9]+" | head -1) || true
screen | grep -A1 -F "$pos1" | tail -1 | grep -qE "[0-9]{4}-[0-9]{2}-[0-9]{2} [0-9]{2}:[0-9]{2} run $run1" \
  || fail "the active positioning table's date and source run are not on screen"
echo "console.sh: run $run1's tables $(echo $ids) published, the PLC at sequence $seq; $pos1"
plc_active=$(twin '{"cmd":"plc"}' | python3 -c '
import json, sys
print(" ".join(str(a["sequence"]) for a in json.load(sys.stdin)["plc"]["active"] if a))')
[ "$(tr ' ' '\n' <<<"$plc_active" | sort -n | tr '\n' ' ')" = "$(seq -s ' ' 1 "$seq") " ] \
  || fail "the twin's PLC applies sequences $plc_active, not 1..$seq"

echo "console.sh: the axis ages (the twin's control socket), re-measured from the Measure screen"
twin '{"cmd":"age","positioning_um":6,"backlash_um":3,"thermal_um":5}' >/dev/null
# Years pass: at least the minute the run list dates runs by, so that the date finds the
# commissioning run alone.
while [ "$(date -u '+%F %H:%M')" = "$run1_date" ]; do sleep 1; done
keys 4
# The last plan of the axis is still there: start it again.
expect 5 "targets (mm): 0.0 2.0 4.0 6.0 8.0"
keys s
expect 5 "Start the run?" "Axis X, 0 to 8 mm, 5 targets, 2 bidirectional runs"
keys y
expect 15 "running" "/20"
run2=$(screen | grep -oE 'run [0-9]+ running' | head -1 | grep -oE '[0-9]+') || true
[ -n "$run2" ] && [ "$run2" != "$run1" ] || fail "no new run on the Measure screen"
expect 150 "run $run2 finished: its results are on screen 5"

echo "console.sh: Results, the commissioning run found by its date ($run1_date) and compared"
keys 5
expect 10 "run $run2 X finished, 20 captures" "$run1_date"
[ "$(screen | grep -cF "$run1_date")" = 1 ] || fail "not one run dated $run1_date"
for _ in $(seq 1 8); do
  selected | grep -qF "$run1_date" && break
  keys Down
done
row=$(selected | grep -F "$run1_date") || fail "no row dated $run1_date could be selected"
grep -qE "^ *(run +)?$run1 +X finished" <<<"$row" || fail "the row dated $run1_date is not run $run1: $row"
keys b
expect 10 "comparing with run $run1 (before)" "before: run $run1"
grep -qE "^b *(run +)?$run1 +X finished" <<<"$(selected)" || fail "run $run1's row is not marked b"
keys Left
expect 5 "dy positioning (µm) + − ·before" "B̄ "
# The re-measurement ran under the commissioning tables: its mean reversal is the backlash
# the ageing added (3 µm: x↑ − x↓ = −3 µm), where the commissioning run saw the axis' own.
rev=$(screen | grep -oE 'B̄ (mean rev\.|\(mean reversal\)) +[-+0-9.]+ +[-+0-9.]+' | head -1) || true
rev_before=$(awk '{print $(NF - 1)}' <<<"$rev")
rev_after=$(awk '{print $NF}' <<<"$rev")
echo "console.sh: mean reversal B̄ before $rev_before µm (run $run1), after $rev_after µm (run $run2; the ageing added -3 µm)"
python3 -c 'import sys; sys.exit(0 if abs(float(sys.argv[1]) + 3) <= 1.5 else 1)' "$rev_after" \
  || fail "run $run2's mean reversal $rev_after µm is not the ageing's -3 µm (±1.5)"

echo "console.sh: Results' trends (t): every figure of axis X over its runs under the same tables"
keys t
# Run $run2 alone measured under the commissioning tables: too few runs for limits yet.
expect 10 "Trends of axis X: 1 run under the same tables" "dy E (systematic)" "learning" \
  "no limits yet"
keys Down
expect 5 "dy M (mean)"
keys t
expect 5 "run $run2 X finished"

echo "console.sh: Publish, the re-measurement's tables composed with the active ones, published"
keys 6
expect 10 "Tables (map"
ids2=$(generate "$run2")
[ -n "$ids2" ] || fail "no table ids in the status bar after generating from run $run2"
pos2=${ids2%% *}
for _ in $(seq 1 12); do
  screen | grep -qE "Table $pos2 EXX axis" && break
  keys Down
done
# The values panel says what the table is made of: the active positioning table, its
# sequence and CRC, and the residual measured by run 2 (wrapped at 80 columns).
base=$(sed -E 's/active: table ([0-9]+) positioning X seq ([0-9]+)/\1 \2/' <<<"$pos1")
if [ -n "$wide" ]; then
  # Wide enough for the composition on one row of its panel.
  composition=$(screen | tr -s ' \n' '  ')
else
  composition=$(screen | sed -n '/┌ Table '"$pos2"' EXX/,/└/p' | awk -F'│' '{print $2}' | tr -s ' \n' '  ')
fi
grep -qF "composed: table ${base% *} (sequence ${base#* }, CRC 0x" <<<"$composition" \
  && grep -qF "+ the residual measured by run $run2" <<<"$composition" \
  || fail "table $pos2 does not say it is composed of table ${base% *} (sequence ${base#* }) and run $run2"
echo "console.sh: table $pos2: $(grep -oE 'composed: table [0-9]+ \(sequence [0-9]+, CRC 0x[0-9A-F]+\) \+ the residual measured by run [0-9]+' <<<"$composition" | head -1)"
seq2=$(publish "$pos2")
expect 10 "PLC ready, active sequence $seq2;" "commit: accepted sequence $seq2" \
  "active: table $pos2 positioning X seq $seq2"
echo "console.sh: table $pos2 active in the PLC as sequence $seq2 (was sequence ${base#* })"

echo "console.sh: Calibrate, a hexapod run started from the console and followed to the fit"
# The twin serves its PI controller on a free port, where service.toml's [hexapod] points
# (twin_configs with TWIN_HEXAPOD_PORTS=free). A 40-pose plan over the operating window
# (±100 µm, ±1 mm positioning, ±60″).
python3 - "$work/plan.csv" <<'PY2'
import random, sys
r = random.Random(17)
with open(sys.argv[1], "w") as f:
    f.write("x_mm,y_mm,z_mm,u_deg,v_deg,w_deg\n")
    for _ in range(40):
        a = 60 / 3600
        f.write(",".join(f"{v:.7f}" for v in (r.uniform(-0.1, 0.1), r.uniform(-1, 1),
                r.uniform(-0.1, 0.1), r.uniform(-a, a), r.uniform(-a, a), r.uniform(-a, a))) + "\n")
PY2
keys 3
expect 10 "Hexapod run" "No run: h calibrates"
keys h
expect 5 "Calibrate with the hexapod" "Plan CSV on the service's host"
keys -l "$work/plan.csv"
keys Enter
expect 5 "Start the hexapod calibration?" "Keep clear of the platform"
hexapod_t0=$SECONDS
keys y
expect 30 "running" "of 40 (" "machine time" "remaining ~" "PI C-887"
echo "console.sh: $(screen | grep -o 'pose [0-9]* of 40[^│]*' | head -1)"
expect 180 "done" "pose 40 of 40" "hold-out" "C–R bound" "worst" "Pending: $work"
echo "console.sh: hexapod run and fit in $((SECONDS - hexapod_t0)) s; hold-out $(screen | grep -o 'worst [0-9.]*×' | head -1) the bound"
keys a
expect 5 "Accept the calibration?"
keys y
expect 15 "in use   stored calibration"

echo "console.sh: the service restarted under the console, tables generated from the command line"
# Issue 29: the first key after a service restart answered 'control connection: Broken pipe
# (os error 32)' under a connected header, and Publish said nothing of tables generated from
# the command line until r.
keys 1
kill "$svc"
wait "$svc" 2>/dev/null || true
expect 20 "○ no service"
RUST_LOG=warn "$bin" serve --config "$work/service.toml" >>"$work/serve.log" 2>&1 & svc=$!
wait_ready
expect 20 "● connected"
cli_ids=$("$bin" table generate --run "$run2" --socket "$work/control.sock" --json \
  | python3 -c 'import json, sys; print(" ".join(str(t["id"]) for t in json.load(sys.stdin)["tables"]))') \
  || fail "table generate --run $run2 from the command line"
cli_pos=${cli_ids%% *}
keys 6
expect 10 "Tables (map" "${cli_pos}  E" "PLC ready, active sequence $seq2;"
screen | grep -q "Broken pipe" && fail "a request after the restart went to the old connection"
echo "console.sh: tables $cli_ids from the command line listed on Publish, no key but 6"

echo "console.sh: 160×48$([ "$cols" = 160 ] && [ "$rows" = 48 ] || echo " (then back to ${cols}×${rows})")"
"${tmx[@]}" resize-window -t console -x 160 -y 48
expect 10 "Tables (map" "${cli_pos}  E" "PLC ready, active sequence $seq2;" "active: table $pos2 positioning X seq $seq2"
[ "$(screen | wc -l)" -ge 48 ] || fail "the pane is not 48 rows high"
keys 1
expect 10 "Six errors" "● connected" "PSD1 pitch/yaw" "dy "
keys 2
# From 120 columns the follower's map stands beside the beam alignment.
expect 10 "Beam alignment over the travel" "Follower" "✓ CHECK PASSED"
keys 5
expect 10 "run $run2 X finished, 20 captures" "dy positioning (µm)" "A (accuracy)"
keys 4
expect 10 "Plan (ISO 230-2)" "targets (mm): 0.0 2.0 4.0 6.0 8.0"
"${tmx[@]}" resize-window -t console -x "$cols" -y "$rows"
keys 1
expect 10 "Six errors"

echo "console.sh: colours, then quit"
"${tmx[@]}" capture-pane -e -p -t console | grep -qE $'\e\\[[0-9;]*(3[0-7]|38;)' \
  || fail "no colour escapes with colours on"
# The NO_COLOR console's session opens before this one's console quits: a tmux server whose
# last session ends exits, and a session opened while it exits fails (CI: "no server running",
# once, with the new session opened right after the quit).
"${tmx[@]}" new-session -d -s nocolor -x "$cols" -y "$rows" \
  "NO_COLOR=1 $bin console --socket $work/control.sock"
"${tmx[@]}" set-option -t nocolor remain-on-exit on >/dev/null
keys q
for _ in $(seq 1 50); do
  [ -s "$work/console.rc" ] && break
  sleep 0.2
done
rc=$(cat "$work/console.rc" 2>/dev/null || echo "none within 10 s")
[ "$rc" = 0 ] || fail "q did not end the console with status 0 (status: $rc)"

echo "console.sh: NO_COLOR"
"${tmx[@]}" kill-session -t console
"${tmx[@]}" rename-session -t nocolor console
expect 20 "Six errors" "● connected"
if "${tmx[@]}" capture-pane -e -p -t console | grep -qE $'\e\\[[0-9;]*(3[0-7]|38;|4[0-7]|48;)'; then
  fail "NO_COLOR=1 still draws colours"
fi
# A new console, the service restarted since the alignment: Align shows the alignment the
# pre-run check uses (it said 'no advice yet').
keys 2
expect 10 "stored alignment of X over -1–400 mm" "✓ CHECK PASSED"
echo "console.sh: a new console shows the stored alignment: $(screen | grep -o 'stored alignment of X[^│]*' | head -1 | sed 's/ *$//')"
keys q

echo "console.sh: all screens as expected"
