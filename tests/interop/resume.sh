#!/usr/bin/env bash
# Crash and resume (issue 4, must-show 4) with real processes: `axiscomp sim` (its CNC runs the
# part programs) and `axiscomp serve`; a run is started with `axiscomp run start`, the service
# is killed with SIGKILL after KILL_AFTER captures, started again on the same store, and the run
# must finish with every (run, target, direction) capture stored exactly once. Prints the
# figures; exits non-zero with the logs on failure. Needs python3 (for its sqlite3 module).
#   bash tests/interop/resume.sh                # from anywhere in the repository
#   KILL_AFTER=3 KEEP=1 bash tests/interop/resume.sh   # kill earlier; keep the work directory
# DISTURB=fault (issue 24, must-show 1: the new user's scenario) keeps the service up and instead,
# over 0–200 mm at 100 mm/s, gives the follower drive a following error while the carriage moves
# in the middle of a pass (reset as the alarm says), then blocks PSD2 for 1.5 s in a later move:
# the same checks follow (every capture once, labels by the backlash, the truth).
# While the service is down the head is knocked on its mount (KNOCK_URAD of yaw, 8 by default,
# 0: none): the service comes back with the zero reference it had (issue 24) and finds the turn
# at the carriage's first return to the zero; every capture stored is then judged by the twin's
# truth (tests/interop/truth.py), none further from it than its U or 1 µm / 0.4″.
# Each capture's direction is checked against the twin's backlash and reported; STRICT=1 makes a
# mislabelled direction fatal (open: the follower's hunting after a step still misleads the
# approach judgement now and then on a loaded machine, crash or not).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
command -v python3 >/dev/null || { echo "resume.sh: python3 not found" >&2; exit 1; }

kill_after=${KILL_AFTER:-7}
disturb=${DISTURB:-kill}
case "$disturb" in
  kill) end_mm=20 feed=3000 ;;
  fault) end_mm=200 feed=6000 ;;
  *) echo "resume.sh: DISTURB=$disturb: use kill or fault" >&2; exit 2 ;;
esac
# AXISCOMP_BIN: a binary built already (.ci/run builds one for every script).
if [ -n "${AXISCOMP_BIN:-}" ]; then
  bin=$AXISCOMP_BIN
else
  cargo build --locked -q
  bin="${CARGO_TARGET_DIR:-target}/debug/axiscomp"
fi
[ -x "$bin" ] || { echo "resume.sh: no binary at $bin" >&2; exit 1; }

# The twin and the service on free loopback ports, the twin's CNC running the programs.
source tests/interop/twin-configs.sh
harness resume.sh
twin_configs "$work"
sock="$work/control.sock"
db="$work/state/axiscomp.db"

# serve N: start the service (log serve-N.log) and wait until it answers with the follower
# homed and the stitch referenced.
serve() {
  RUST_LOG=${RUST_LOG:-info} "$bin" serve --config "$work/service.toml" >"$work/serve-$1.log" 2>&1 & svc=$!
  for _ in $(seq 1 120); do
    if "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
sys.exit(0 if s["follower"]["homed"] else 1)
' 2>/dev/null; then return 0; fi
    kill -0 "$svc" 2>/dev/null || fail "the service (start $1) exited"
    sleep 0.5
  done
  fail "the service (start $1) did not come up"
}
# field NAME: a field of `axiscomp run status` (empty when it does not answer).
status_field() {
  "$bin" run status --json --socket "$sock" 2>/dev/null | python3 -c "
import json, sys
print(json.load(sys.stdin).get('$1', ''))" 2>/dev/null || true
}

"$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
sleep 1
if [ -n "${TRACE:-}" ]; then
  # The twin's carriage and follower every 50 ms (time, travel, moving, follower), for a look
  # at what the CNC did around the crash.
  python3 - "$ctl" >"$work/truth.log" 2>/dev/null <<'EOF2' &
import json, socket, sys, time
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
f = s.makefile("rw")
while True:
    f.write('{"cmd":"truth"}\n'); f.flush()
    t = json.loads(f.readline())["truth"]
    print(f"{time.time():.3f} {t['travel_mm']:.4f} {int(t['moving'])} {t['follower_encoder_mm']:.4f}", flush=True)
    time.sleep(0.05)
EOF2
fi
serve 1
# Wait for the stitch before starting (a run needs the spot on PSD2).
for _ in $(seq 1 60); do
  "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
sys.exit(0 if s["tracking"]["valid"] and s["tracking"]["at_rest"] else 1)' 2>/dev/null && break
  sleep 0.5
done

# The pre-run check wants the plan's travel (and 1 mm of overrun) aligned.
align_cli -1 $((end_mm + 1)) >"$work/align.txt" 2>&1 || { cat "$work/align.txt" >&2; fail "the alignment check did not pass"; }
# The truth where the alignment took the zero (the carriage has not moved since).
python3 tests/interop/truth.py zero "$twin_ctl" "$work/zero-truth.json" || fail "the twin did not give its truth"
"$bin" run start --json --socket "$sock" --axis X --start-mm 0 --end-mm "$end_mm" --targets 5 --runs 2 \
  --dwell-s 1.5 --feed-mm-min "$feed" --overrun-mm 1 --lead-mm 5 --dialect linuxcnc \
  >"$work/start.json" 2>&1 || { cat "$work/start.json" >&2; fail "run start refused"; }
run_id=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["run_id"])' "$work/start.json")
expected=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["captures_expected"])' "$work/start.json")
t0=$(date +%s.%N)

end=$((SECONDS + 120))
while :; do
  n=$(status_field captures)
  [ -n "$n" ] && [ "$n" -ge "$kill_after" ] && break
  [ "$SECONDS" -ge "$end" ] && fail "no $kill_after captures within 120 s (have ${n:-none})"
  sleep 0.1
done
# in_a_move: wait (up to 60 s) until the twin's carriage moves.
in_a_move() {
  python3 - "$twin_ctl" <<'EOF' || fail "the carriage did not move within 60 s"
import sys, time
sys.path.insert(0, "tests/interop")
from truth import Twin
twin, end = Twin(sys.argv[1]), time.monotonic() + 60
while not twin.cmd({"cmd": "truth"})["truth"]["moving"]:
    if time.monotonic() > end:
        sys.exit(1)
    time.sleep(0.02)
EOF
}
# until_captures N: wait (up to 120 s) until the run reports N captures.
until_captures() {
  local end=$((SECONDS + 120)) m
  while :; do
    m=$(status_field captures)
    [ -n "$m" ] && [ "$m" -ge "$1" ] && return 0
    [ "$SECONDS" -ge "$end" ] && fail "no $1 captures within 120 s (have ${m:-none})"
    sleep 0.1
  done
}
if [ "$disturb" = fault ]; then
  in_a_move
  twin_cmd '{"cmd":"drive","fault":34321}' >/dev/null || fail "the twin did not take the drive fault"
  echo "resume.sh: run $run_id: a following error (EMCY 0x8611) of the follower drive in a move at $n captures"
  # The operator resets the drive as the alarm says, once it is in Fault.
  for _ in $(seq 1 100); do
    st=$("$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
print(json.load(sys.stdin)["follower"].get("state") or "")' 2>/dev/null || true)
    case "$st" in
      Fault) svc_cmd '{"cmd":"follower","action":"fault_reset"}' >/dev/null || true ;;
      "Operation enabled") [ -n "${reset:-}" ] && break ;;
    esac
    [ "$st" = Fault ] && reset=1
    sleep 0.2
  done
  [ "$st" = "Operation enabled" ] || fail "the follower drive did not come back from its fault (state ${st:-unknown})"
  until_captures $((n + 4))
  in_a_move
  twin_cmd '{"cmd":"block","psd":2,"on":true}' >/dev/null || fail "the twin did not block PSD2"
  sleep 1.5
  twin_cmd '{"cmd":"block","psd":2,"on":false}' >/dev/null || fail "the twin did not unblock PSD2"
  echo "resume.sh: run $run_id: PSD2 blocked for 1.5 s in a move after $((n + 4)) captures"
fi
if [ "$disturb" = kill ]; then
kill -9 "$svc"
wait "$svc" 2>/dev/null || true
svc=""
stored_at_kill=$(python3 - "$db" "$run_id" <<'EOF'
import sqlite3, sys
c = sqlite3.connect(sys.argv[1])
print(c.execute("SELECT COUNT(*) FROM captures WHERE run_id = ?", (int(sys.argv[2]),)).fetchone()[0])
EOF
)
echo "resume.sh: run $run_id: SIGKILL of the service at $n captures reported ($stored_at_kill stored)"
# The CNC goes on while the service is down, and the head is knocked; come back a moment later.
knock=${KNOCK_URAD:-8}
if [ "$knock" != 0 ]; then
  python3 - "$twin_ctl" "$knock" <<'EOF' || fail "the twin did not take the knock"
import sys
sys.path.insert(0, "tests/interop")
from truth import Twin
Twin(sys.argv[1]).cmd({"cmd": "knock", "yaw_urad": float(sys.argv[2])})
EOF
  echo "resume.sh: the head knocked by $knock µrad of yaw while the service was down"
fi
sleep "${DOWN_S:-2}"
serve 2
fi

state=""
end=$((SECONDS + 240))
while :; do
  state=$(status_field state)
  [ "$state" = finished ] || [ "$state" = failed ] || [ "$state" = aborted ] && break
  [ "$SECONDS" -ge "$end" ] && fail "the run did not end within 240 s (state ${state:-none})"
  sleep 0.5
done
t1=$(date +%s.%N)

python3 - "$db" "$run_id" "$expected" <<'EOF' || fail "the run did not finish with every capture exactly once (see above)"
import os, sqlite3, sys
db, run_id, expected = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
c = sqlite3.connect(db)
state, notes, plan = c.execute("SELECT state, notes, plan_json FROM runs WHERE id = ?", (run_id,)).fetchone()
import json
plan = json.loads(plan)
targets, runs = len(plan["targets"]), plan["spec"]["runs"]
rows = c.execute("SELECT run, target_index, direction, COUNT(*) FROM captures WHERE run_id = ? "
                 "GROUP BY run, target_index, direction", (run_id,)).fetchall()
have = {(r, t, d): n for r, t, d, n in rows}
want = {(r, t, d) for r in range(1, runs + 1) for t in range(targets) for d in "+-"}
missing = sorted(want - have.keys())
extra = sorted(have.keys() - want)
dup = sorted(k for k, n in have.items() if n != 1)
total = sum(have.values())
print(f"resume.sh: run {run_id} {state}: {total} captures of {expected} expected, "
      f"missing {missing}, duplicated {dup}, not in the plan {extra}; notes: {notes}")
ok = state == "finished" and not missing and not dup and not extra and total == expected
# Each capture under the direction the carriage came from: the twin's 5 µm backlash
# (configs/sim.toml) puts every downward capture of a target above every upward one.
gaps = []
for t in range(targets):
    dy = lambda d: [r[0] * 1e3 for r in c.execute(
        "SELECT dy_mm FROM captures WHERE run_id = ? AND target_index = ? AND direction = ?",
        (run_id, t, d))]
    up, down = dy("+"), dy("-")
    if up and down:
        gaps.append(min(down) - max(up))
        if max(up) >= min(down):
            if os.environ.get("STRICT"):
                ok = False
            print(f"resume.sh: WARNING: target {t}: an upward capture reads above a downward one "
                  f"(dy µm up {up}, down {down}): a direction was mislabelled")
if gaps:
    print(f"resume.sh: backlash gap (lowest downward - highest upward dy) per target: "
          + ", ".join(f"{g:.2f}" for g in gaps) + " µm")
sys.exit(0 if ok else 1)
EOF
grep -h "zero reference\|back at the zero\|knock\|flagged\|re-referenced\|following error" "$work"/serve-*.log | sed 's/^/resume.sh: service: /' | cut -c1-240 || true
python3 tests/interop/truth.py judge --db "$db" --run "$run_id" --twin "$twin_ctl" \
  --zero "$work/zero-truth.json" --within 1,1,1,0.4,0.4,0.4 --out "$work/truth.json" \
  | sed 's/^/resume.sh: /' || fail "captures stored far from the truth after the restart (above)"
awk -v a="$t0" -v b="$t1" -v d="$disturb" 'BEGIN { printf "resume.sh: PASS (run start to finished %.1f s, DISTURB=%s)\n", b - a, d }'
