#!/usr/bin/env bash
# The fault storm (issue 18, must-show 4) with real processes, release build: `axiscomp sim` (its
# CNC runs the part programs, machine speed raised so that a whole run takes minutes) and
# `axiscomp serve`; after a beam alignment over the travel, a whole 1000 mm run (11 targets, 5
# bidirectional runs, 110 captures) with STORM_FAULTS (default 54) randomly timed faults drawn from
# every kind the twin injects during a run (the I/O module stopped, answering exceptions, hung,
# slow; a beam blocked; a drive fault; the drive's heartbeat lost; the head knocked), plus a
# SIGKILL of the service (restarted: the run resumes), a full disk on the state directory (its own
# tmpfs, filled to the last byte for a few seconds) and steps of the service's wall clock
# (libfaketime's offset file: the service alone sees the step, monotonic time untouched; the
# machine's clock is shared and is not stepped). tests/interop/storm.py drives the storm and
# writes every fault, what the service showed of it and its recovery time to storm-events.tsv.
# Then the run's tables are published to the twin's PLC with each of the PLC's faults injected
# (refusal, corrupted payload, commit ignored, link silent mid-publish, not ready, heartbeat
# frozen) and once cleanly; after each the PLC's active table is compared with the store's: the
# old table or the new one, whole, never a mix.
# Then the verification run on the compensated axis (the twin's PLC applies the tables it took)
# under a storm of its own (STORM_VERIFY_FAULTS, default 18; 0: none), judged by the truth, with
# its ISO 230-2 positioning figures by the service and by the truth (issue 24, must-show 3: E
# after by the truth within STORM_VERIFY_E_UM, default 1.0 µm).
# Passes when both runs finish with every capture exactly once, every fault recovered, no
# table partially applied, and the compensated axis' E within its bound. Every stored capture is compared with the twin's truth (truth.py) and
# the figures printed; STORM_TRUTH=within also fails on a capture further from it than its U or
# 1 µm / 0.4″, STORM_TRUTH=strict on one outside its U or a U not sharp. Needs root for the tmpfs (else STORM_DISK=skip says the disk was not
# tested), apt-get download + dpkg -x for libfaketime (or FAKETIME_LIB).
# STORM_TWIN_SEED (default 1) draws another machine and follower; STORM_MAP=1 maps the twin's
# follower first (`axiscomp follower map --twin`, in virtual time: the set-up the README
# recommends) and the run uses the map, with PSD2's stitch the map-corrected encoder
# (STORM_STRATEGY=overlap to compare). KEEP=1 keeps the work directory and the store.
#   bash tests/interop/storm.sh
#   STORM_FAULTS=80 STORM_SEED=7 KEEP=1 bash tests/interop/storm.sh
#   STORM_TWIN_SEED=3 STORM_MAP=1 STORM_TRUTH=strict bash tests/interop/storm.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
command -v python3 >/dev/null || { echo "storm.sh: python3 not found" >&2; exit 1; }
faults=${STORM_FAULTS:-54}
seed=${STORM_SEED:-18}
twin_seed=${STORM_TWIN_SEED:-1}
disk_mb=${STORM_DISK_MB:-16}
# Machine speed: the twin's carriage at up to 100 mm/s and 250 mm/s² (configs/sim.toml: 50 mm/s,
# 500 mm/s²: faster, or harder accelerations, and the follower is left behind at a reversal now and
# then, which costs a whole pass), the program's feed 6 m/min, dwell 1.5 s (the service
# refuses less than 1.45 s at 500 Hz: the follower's rest and settling at each stop come before
# the capture's frames): about 4.5 min of machine time for the 110 captures.
carriage_mm_s=${STORM_CARRIAGE_MM_S:-100}
feed=${STORM_FEED_MM_MIN:-6000}
dwell=${STORM_DWELL_S:-1.5}

if [ -n "${AXISCOMP_BIN:-}" ]; then
  built=$AXISCOMP_BIN
else
  cargo build --release --locked -q
  built="${CARGO_TARGET_DIR:-target}/release/axiscomp"
fi
[ -x "$built" ] || { echo "storm.sh: no binary at $built" >&2; exit 1; }

source tests/interop/twin-configs.sh
harness storm.sh
twin_configs "$work"
bin="$work/axiscomp"
cp "$built" "$bin"
sock="$work/control.sock"
state="$work/state"
pidfile="$work/serve.pid"
mkdir -p "$state"
# The service (its pid in $pidfile: storm.py restarts it) and the twin stopped before the state
# directory's file system is unmounted, whatever failed before.
storm_cleanup() {
  if [ -f "$pidfile" ]; then kill "$(cat "$pidfile")" 2>/dev/null || true; fi
  if [ -n "$sim" ]; then kill "$sim" 2>/dev/null || true; fi
  sleep 0.5
  # KEEP=1 keeps the store beside the logs: the state directory's tmpfs goes with the run.
  if [ -n "${KEEP:-}" ]; then cp "$state"/axiscomp.db* "$work/" 2>/dev/null || true; fi
  if mountpoint -q "$state" 2>/dev/null; then umount "$state" || umount -l "$state" || true; fi
  harness_cleanup
}
trap storm_cleanup EXIT

# The state directory on a file system of its own, small enough to fill.
disk="skip"
if [ "${STORM_DISK:-}" != skip ]; then
  if mount -t tmpfs -o size="${disk_mb}m",mode=0700 storm-state "$state" 2>"$work/mount.err"; then
    disk="tmpfs ${disk_mb} MiB"
  else
    fail "cannot mount a tmpfs on the state directory ($(cat "$work/mount.err")): run as root, or STORM_DISK=skip"
  fi
fi

# libfaketime for the service's wall clock (never the machine's).
ft=${FAKETIME_LIB:-}
if [ -z "$ft" ]; then
  mkdir -p "$work/deb"
  (cd "$work/deb" && apt-get download -q libfaketime >"$work/apt.log" 2>&1) \
    || fail "apt-get download libfaketime failed (apt.log): set FAKETIME_LIB"
  dpkg -x "$work"/deb/libfaketime_*.deb "$work/faketime"
  ft=$(find "$work/faketime" -name libfaketimeMT.so.1 | head -1)
fi
[ -f "$ft" ] || fail "no libfaketimeMT.so.1 ($ft)"
echo "+0" >"$work/clock-offset"

# Homing from the far end after the SIGKILL: the default switch speed (5 mm/s) and timeout (30 s)
# cover 150 mm of the follower's 1110 mm (the service retries, 30 s at a time, from where it got
# to: about 4 min from 1000 mm); here a stage that homes at 50 mm/s within 40 s.
# The run judges every capture before it counts ([capture] judge, on by default);
# STORM_JUDGE=0 runs it without, to compare.
if [ "${STORM_JUDGE:-1}" = 0 ]; then printf '\n[capture]\njudge = false\n' >>"$work/service.toml"; fi
sed -i '/^\[follower\]/a homing_switch_speed_mm_s = 50.0\nhoming_timeout_ms = 40000' "$work/service.toml"
sed -i "s/^feed_mm_s = .*/feed_mm_s = $carriage_mm_s.0/; s/^accel_mm_s2 = .*/accel_mm_s2 = ${STORM_ACCEL_MM_S2:-250}.0/" "$work/sim.toml"
sed -i "0,/^seed = .*/s//seed = $twin_seed/" "$work/sim.toml"
grep -q "^seed = $twin_seed\$" "$work/sim.toml" || fail "could not set the twin's seed $twin_seed in sim.toml"
# With the follower mapped, PSD2's stitch is the map-corrected encoder from the zero
# ([tracking] strategy = "encoder"): one bridge whose error the map bounds (seed 1, 1.5 s
# dwell: positioning RMS 0.24 µm, a target's passes within 0.37 µm, roll's within 0.41″).
# The optical overlap handovers random-walk over a run's two hundred stops once the follower
# keeps its spot (the same storm: RMS 1.26 µm, passes within 1.40 µm and 1.36″, E after
# 1.18 µm by the truth). STORM_STRATEGY overrides it.
strategy=${STORM_STRATEGY:-$(if [ "${STORM_MAP:-0}" = 1 ]; then echo encoder; else echo overlap; fi)}
printf '\n[tracking]\nstrategy = "%s"\n' "$strategy" >>"$work/service.toml"
map="none"
if [ "${STORM_MAP:-0}" = 1 ]; then
  t0=$SECONDS
  "$bin" follower map --twin --seed "$twin_seed" --length-mm 1000 --db "$state/axiscomp.db" \
    >"$work/follower-map.txt" 2>&1 || { cat "$work/follower-map.txt" >&2; fail "the follower map on the twin failed"; }
  map="the twin's follower mapped in $((SECONDS - t0)) s ($(grep -c . "$work/follower-map.txt") lines: follower-map.txt)"
fi
serve_cmd="env LD_PRELOAD=$ft FAKETIME_TIMESTAMP_FILE=$work/clock-offset FAKETIME_DONT_FAKE_MONOTONIC=1 \
FAKETIME_CACHE_DURATION=1 RUST_LOG=${RUST_LOG:-info,axiscomp::run=debug,axiscomp::align::revisit=debug} $bin serve --config $work/service.toml"

"$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
sleep 1
bash -c "exec $serve_cmd" >"$work/serve-0.log" 2>&1 & echo $! >"$pidfile"
for _ in $(seq 1 120); do
  spots_at_rest 1 && "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
sys.exit(0 if json.load(sys.stdin)["follower"]["homed"] else 1)' && break
  kill -0 "$(cat "$pidfile")" 2>/dev/null || fail "the service exited"
done

# A whole run needs the travel aligned (0–1000 mm and 2 mm of overrun).
t0=$SECONDS
align_cli -2 1002 >"$work/align.txt" 2>&1 || { cat "$work/align.txt" >&2; fail "the alignment check did not pass"; }
echo "storm.sh: twin seed $twin_seed; follower map: $map; PSD2's stitch: $strategy"
echo "storm.sh: aligned over -2..1002 mm in $((SECONDS - t0)) s; state directory on $disk; $(basename "$ft")"

run_args="--axis X --start-mm 0 --end-mm 1000 --targets 11 --runs 5 --dwell-s $dwell \
--feed-mm-min $feed --overrun-mm 2 --lead-mm 10 --dialect linuxcnc"
t0=$SECONDS
python3 tests/interop/storm.py --bin "$bin" --sock "$sock" --twin "$twin_ctl" \
  --serve-cmd "$serve_cmd" --serve-log "$work/serve-" --pidfile "$pidfile" \
  --state "$state" --clock-file "$work/clock-offset" --events "$work/storm-events.tsv" \
  --faults "$faults" --seed "$seed" --gap-max "${STORM_GAP_MAX_S:-4}" --run-args "$run_args" --db "$state/axiscomp.db" \
  --disk "$disk" --budget "${STORM_BUDGET_S:-900}" --truth "${STORM_TRUTH:-report}" \
  --truth-json "$work/storm-truth.json" --verify-faults "${STORM_VERIFY_FAULTS:-18}" \
  --verify-e-um "${STORM_VERIFY_E_UM:-1.0}" | tee "$work/storm.out" || fail "the storm was not survived (storm-events.tsv)"
echo "storm.sh: run and storm in $((SECONDS - t0)) s"
column -t -s $'\t' "$work/storm-events.tsv" | sed 's/^/storm.sh:   /'
echo "storm.sh: PASS"
