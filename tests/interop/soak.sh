#!/usr/bin/env bash
# A soak (issue 18): `axiscomp sim` and `axiscomp serve` (release build, 500 Hz acquisition) for
# SOAK_SECONDS (default 600; the hour: SOAK_SECONDS=3600) with the console attached in a real
# terminal (tmux, 80x24, the Live screen) and a control-API subscriber (soak_subscriber.py, 10
# snapshots/s), and an ISO 230-2 run started every RUN_EVERY seconds (default 600: one run in
# the ten minutes, six in the hour), each of which must finish with every capture. Every
# SAMPLE_S seconds (default 10) the service's RSS, its CPU time (/proc/PID/stat) and psd.seq are
# sampled into samples.tsv in the work directory.
#
# Figures printed: RSS at the start (the service up and steady, before the first run), at the
# end and at the peak, the drift after the first run (KiB/h, least squares over the samples
# after it), the frames acquired against the 500 Hz schedule (psd.seq; a tick the scheduler
# made the service miss is skipped, never bunched), frames lost after acquisition or on the
# link (frames the core fell behind the acquisition by, from its log, and failed reads: one
# frame each), frames the core was too late to decouple (psd.late_frames), the service's CPU in % of one core (and the twin's, the console's,
# the machine's load average), runs completed, snapshots the subscriber got and its longest gap.
#
# Fails on a clear regression: RSS growth start to end above MAX_RSS_GROWTH_KIB (default 4096),
# a peak above MAX_RSS_KIB (default 30720, the issue's 30 MB), frames lost above MAX_LOST_PCT
# (default 0.1 % of the schedule), fewer than MIN_FPS frames/s acquired (default 250, half
# the schedule: a stalling acquisition, not a busy machine; the issue's 495 holds on a quiet
# machine, while on this shared 2-core machine at a load of 13 to 17 the scheduler made the
# service miss 5 to 35 % of its ticks), a run not finishing or missing captures, the subscriber's or the
# console's stream stopping (a gap above 5 s, the console's screen not showing the Live
# screen), the service or the twin exiting. CPU figures are reported, not asserted: on a shared
# 2-core machine they follow the neighbours' load.
#   bash tests/interop/soak.sh                     # the ten minutes (.ci/run)
#   SOAK_SECONDS=3600 bash tests/interop/soak.sh   # the hour; KEEP=1 keeps the work directory
#   AXISCOMP_BIN=/path/to/axiscomp bash tests/interop/soak.sh   # a binary built already
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
command -v python3 >/dev/null || { echo "soak.sh: python3 not found" >&2; exit 1; }
command -v tmux >/dev/null || { echo "soak.sh: tmux not found" >&2; exit 1; }
soak_s=${SOAK_SECONDS:-600}
run_every=${RUN_EVERY:-600}
sample_s=${SAMPLE_S:-10}
max_growth=${MAX_RSS_GROWTH_KIB:-4096}
max_rss=${MAX_RSS_KIB:-30720}
max_lost_pct=${MAX_LOST_PCT:-0.1}
min_fps=${MIN_FPS:-250}
run_timeout=${RUN_TIMEOUT_S:-420}
rate=500

# AXISCOMP_BIN: a binary built already (e.g. of another commit); otherwise the release build.
if [ -n "${AXISCOMP_BIN:-}" ]; then
  built=$AXISCOMP_BIN
else
  cargo build --release --locked -q
  built="${CARGO_TARGET_DIR:-target}/release/axiscomp"
fi
[ -x "$built" ] || { echo "soak.sh: no binary at $built" >&2; exit 1; }

source tests/interop/twin-configs.sh
harness soak.sh
twin_configs "$work"
# A copy: a build during the soak must not replace the binary under it.
bin="$work/axiscomp"
cp "$built" "$bin"
sock="$work/control.sock"
grep -q "^rate_hz = $rate.0" "$work/service.toml" || fail "the twin's service config is not at $rate Hz"
tmx=(tmux -L "axiscomp-soak-$$" -f /dev/null)
sub=""
soak_cleanup() {
  [ -n "$sub" ] && kill "$sub" 2>/dev/null
  "${tmx[@]}" kill-server 2>/dev/null || true
  harness_cleanup
}
trap soak_cleanup EXIT

"$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
sleep 1
RUST_LOG=${RUST_LOG:-info} "$bin" serve --config "$work/service.toml" >"$work/serve.log" 2>&1 & svc=$!

# status: "SEQ UNIX_US LATE IO_STATE IO_ERRORS IO_RECONNECTS HOMED READY" (empty when it does
# not answer; READY: the stitch referenced and at rest).
status() {
  "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
p = s.get("psd") or {}
io = s["links"]["io"]
t = s["tracking"]
print(p.get("seq", 0), s["unix_us"], p.get("late_frames", 0), io["state"], io["errors"],
      io["reconnects"], int(s["follower"]["homed"]), int(t["valid"] and t["at_rest"]))' 2>/dev/null || true
}
run_field() {
  "$bin" run status --json --socket "$sock" 2>/dev/null | python3 -c "
import json, sys
print(json.load(sys.stdin).get('$1', ''))" 2>/dev/null || true
}
rss() { awk '/^VmRSS:/ {print $2}' "/proc/$1/status"; }
hwm() { awk '/^VmHWM:/ {print $2}' "/proc/$1/status"; }
ticks() { awk '{print $14 + $15}' "/proc/$1/stat"; }
alive() {
  kill -0 "$svc" 2>/dev/null || fail "the service exited"
  kill -0 "$sim" 2>/dev/null || fail "the twin exited"
}

ready=""
for _ in $(seq 1 120); do
  read -r _ _ _ st _ _ homed rdy <<<"$(status)" || true
  [ "${st:-}" = up ] && [ "${homed:-0}" = 1 ] && [ "${rdy:-0}" = 1 ] && { ready=1; break; }
  alive
  sleep 0.5
done
[ -n "$ready" ] || fail "the service did not come up (the I/O link up, the follower homed, the stitch at rest)"

# The console in a real terminal, on its Live screen; the subscriber.
"${tmx[@]}" new-session -d -s console -x 80 -y 24 "$bin console --socket $sock"
"${tmx[@]}" set-option -t console remain-on-exit on >/dev/null
screen() { "${tmx[@]}" capture-pane -p -t console 2>/dev/null || true; }
console_pid=$("${tmx[@]}" display-message -p -t console '#{pane_pid}')
python3 tests/interop/soak_subscriber.py "$sock" 10 >"$work/subscriber.json" 2>"$work/subscriber.log" & sub=$!
for _ in $(seq 1 40); do
  grep -qF "Six errors" <<<"$(screen)" && break
  sleep 0.5
done
grep -qF "Six errors" <<<"$(screen)" || fail "the console does not show its Live screen"
sleep 5

tck=$(getconf CLK_TCK)
read -r seq0 us0 late0 _ err0 rec0 _ _ <<<"$(status)"
rss0=$(rss "$svc"); ct0=$(rss "$console_pid")
svc_t0=$(ticks "$svc"); sim_t0=$(ticks "$sim"); con_t0=$(ticks "$console_pid")
# The runs' travel (0-20 mm, 1 mm of overrun) aligned once: the pre-run check reads it for
# every run of the soak.
align_cli -1 21 >"$work/align.txt" 2>&1 || { cat "$work/align.txt" >&2; fail "the alignment check did not pass"; }
# The truth where the zero was just taken: every run's captures are judged against the truth
# relative to it (tests/interop/truth.py).
python3 tests/interop/truth.py zero "$twin_ctl" "$work/zero-truth.json" || fail "the twin did not give its truth"
load0=$(cut -d' ' -f1-3 /proc/loadavg)
start=$SECONDS
printf 't_s\trss_kib\tsvc_ticks\tseq\tlate\tio_errors\trun_state\n' >"$work/samples.tsv"
echo "soak.sh: $soak_s s at $rate Hz, a run every $run_every s; RSS at start $rss0 KiB; load $load0"

runs_started=0
runs_done=0
run_active=""
first_run_end=""
next_run=0
next_sample=0
# start_run: an ISO 230-2 run on the twin (0-20 mm, 5 targets, 2 runs: 20 captures).
start_run() {
  "$bin" run start --json --socket "$sock" --axis X --start-mm 0 --end-mm 20 --targets 5 --runs 2 \
    --dwell-s 1.5 --feed-mm-min 3000 --overrun-mm 1 --lead-mm 5 --dialect linuxcnc \
    >"$work/start-$runs_started.json" 2>&1 \
    || { cat "$work/start-$runs_started.json" >&2; fail "run $((runs_started + 1)) refused"; }
  run_expected=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["captures_expected"])' "$work/start-$runs_started.json")
  runs_started=$((runs_started + 1))
  run_active=$((SECONDS - start))
  echo "soak.sh: t=$run_active s: run $runs_started started ($run_expected captures)"
}
# check_run: when the active run has ended, check it finished with every capture.
check_run() {
  local state caps
  state=$(run_field state)
  case "$state" in
    finished)
      caps=$(run_field captures)
      [ "$caps" = "$run_expected" ] || fail "run $runs_started finished with $caps captures of $run_expected"
      runs_done=$((runs_done + 1))
      echo "soak.sh: t=$((SECONDS - start)) s: run $runs_started finished ($caps captures) in $((SECONDS - start - run_active)) s"
      # Every capture against the twin's truth: reported; SOAK_TRUTH=strict fails on one
      # outside its U (issue 24: the stored U is not yet the real one).
      local run_id strict=""
      [ "${SOAK_TRUTH:-report}" = strict ] && strict=--strict
      run_id=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["run_id"])' "$work/start-$((runs_started - 1)).json")
      python3 tests/interop/truth.py judge --db "$work/state/axiscomp.db" --run "$run_id" \
        --twin "$twin_ctl" --zero "$work/zero-truth.json" $strict --out "$work/truth-$run_id.json" \
        | sed 's/^/soak.sh: /' || fail "run $run_id: captures outside their U of the truth (above)"
      run_active=""
      [ -n "$first_run_end" ] || first_run_end=$((SECONDS - start))
      ;;
    failed | aborted) fail "run $runs_started ended $state" ;;
    *)
      [ $((SECONDS - start - run_active)) -le "$run_timeout" ] \
        || fail "run $runs_started did not finish within $run_timeout s (state ${state:-none})"
      ;;
  esac
}

while :; do
  t=$((SECONDS - start))
  alive
  [ -n "$run_active" ] && check_run
  if [ "$t" -ge "$soak_s" ] && [ -z "$run_active" ]; then break; fi
  if [ "$t" -ge "$next_run" ] && [ "$next_run" -lt "$soak_s" ]; then
    [ -z "$run_active" ] || fail "run $runs_started still going after $run_every s"
    start_run
    next_run=$((next_run + run_every))
  fi
  if [ "$t" -ge "$next_sample" ]; then
    read -r s_seq _ s_late _ s_err _ _ _ <<<"$(status)" || true
    printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$t" "$(rss "$svc")" "$(ticks "$svc")" "${s_seq:-}" \
      "${s_late:-}" "${s_err:-}" "$(run_field state)" >>"$work/samples.tsv"
    [ $((t % 300)) -lt "$sample_s" ] && echo "soak.sh: t=$t s: RSS $(rss "$svc") KiB, psd.seq ${s_seq:-?}"
    next_sample=$((next_sample + sample_s))
  fi
  sleep 1
done

read -r seq1 us1 late1 st1 err1 rec1 _ _ <<<"$(status)"
rss1=$(rss "$svc"); peak=$(hwm "$svc"); ct1=$(rss "$console_pid")
svc_t1=$(ticks "$svc"); sim_t1=$(ticks "$sim"); con_t1=$(ticks "$console_pid")
load1=$(cut -d' ' -f1-3 /proc/loadavg)
elapsed=$((SECONDS - start))
screen >"$work/console-end.txt"
grep -qF "Six errors" "$work/console-end.txt" || fail "the console no longer shows its Live screen"
kill "$sub"; wait "$sub" 2>/dev/null || true; sub=""
behind=$({ grep -o 'core fell behind the acquisition by [0-9]* frames' "$work/serve.log" || true; } \
  | awk '{s += $7} END {print s + 0}')

python3 - "$work/samples.tsv" "$work/subscriber.json" "${first_run_end:-0}" <<EOF || fail "figures out of bounds (above)"
import json, sys
rows = [l.split("\t") for l in open(sys.argv[1]).read().splitlines()[1:]]
sub = json.loads(open(sys.argv[2]).read().strip() or "{}")
first_end = int(sys.argv[3])
tck, rate = $tck, $rate
span_s = ($us1 - $us0) * 1e-6
scheduled = rate * span_s
acquired = $seq1 - $seq0
missed = max(0.0, scheduled - acquired)
lost = $behind + ($err1 - $err0)
lost_pct = 100 * lost / scheduled
fps = acquired / span_s
cpu = lambda a, b: 100 * (b - a) / tck / $elapsed
growth = $rss1 - $rss0
# Drift after the first run: least squares of RSS on time over the samples after it.
pts = [(float(r[0]), float(r[1])) for r in rows if r[1] and float(r[0]) >= first_end]
drift = None
if len(pts) >= 3:
    n = len(pts); mt = sum(p[0] for p in pts) / n; mr = sum(p[1] for p in pts) / n
    den = sum((p[0] - mt) ** 2 for p in pts)
    drift = sum((p[0] - mt) * (p[1] - mr) for p in pts) / den * 3600 if den else None
print(f"soak.sh: {$elapsed} s at {rate} Hz, runs {$runs_done} of {$runs_started} finished with every capture")
print(f"soak.sh: service RSS start {$rss0} KiB, end {$rss1} KiB (growth {growth:+d} KiB, bound {$max_growth}), "
      f"peak {$peak} KiB (bound {$max_rss})"
      + (f", drift after the first run {drift:+.0f} KiB/h" if drift is not None else ""))
print(f"soak.sh: frames acquired {acquired} of {scheduled:.0f} scheduled = {fps:.1f} frames/s "
      f"(bound {$min_fps}; ticks missed {missed:.0f} = {100 * missed / scheduled:.2f} %); "
      f"lost {lost} = {lost_pct:.4f} % (bound {$max_lost_pct} %: core behind {$behind}, "
      f"I/O link errors {$err1 - $err0}, reconnects {$rec1 - $rec0}, state $st1); "
      f"too late to decouple {$late1 - $late0}")
print(f"soak.sh: CPU (% of one core, over {$elapsed} s): service {cpu($svc_t0, $svc_t1):.2f}, "
      f"twin {cpu($sim_t0, $sim_t1):.2f}, console {cpu($con_t0, $con_t1):.2f}; console RSS {$ct0} -> {$ct1} KiB; "
      f"load average {'$load0'} -> {'$load1'} (a shared machine: CPU figures follow its load)")
print(f"soak.sh: subscriber: {sub.get('snapshots')} snapshots, longest gap {sub.get('max_gap_s')} s, "
      f"psd.seq backwards {sub.get('seq_backwards')}, closed by the service {sub.get('closed_by_service')}")
ok = True
def check(cond, what):
    global ok
    if not cond:
        print(f"soak.sh: out of bounds: {what}")
        ok = False
check(growth <= $max_growth, f"RSS grew {growth} KiB")
check($peak <= $max_rss, f"peak RSS {$peak} KiB")
check(lost_pct <= $max_lost_pct, f"{lost_pct:.4f} % of the frames lost")
check(fps >= $min_fps, f"{fps:.1f} frames/s acquired")
check($runs_done == $runs_started and $runs_started >= 1, "a run did not finish")
check(sub.get("snapshots", 0) >= 5 * $elapsed and sub.get("max_gap_s", 99) <= 5
      and not sub.get("closed_by_service") and sub.get("seq_backwards") == 0,
      "the subscriber's stream stalled, stopped or went backwards")
check("$st1" == "up", "the I/O link is $st1 at the end")
sys.exit(0 if ok else 1)
EOF
echo "soak.sh: PASS"
