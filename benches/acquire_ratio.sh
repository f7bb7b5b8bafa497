#!/usr/bin/env bash
# Acquisition at full speed against the best client there is (issue 18): the whole service
# (`axiscomp serve`, release build, [io] rate_hz = 0: unthrottled) reading the twin's I/O module
# (`axiscomp sim`, the generic map: 9 input registers of unit 1) against a C libmodbus client
# that reads the same block in a loop (modbus_read_input_registers, benches/acquire_ratio/
# libmodbus_read.c), interleaved on one twin: RUNS runs (default 3) of SLICES slices (default
# 5), each slice the service for WINDOW_S seconds (default 3; frames/s from psd.seq over the
# window, SETTLE_S = 1 s after it resumed) then, the service stopped (SIGSTOP), libmodbus for
# WINDOW_S seconds (blocks/s). Fine slices keep the two under the same load on a shared
# machine (a neighbour's compile moves both alike). Prints frames/s, blocks/s and their ratio
# per run, and the ratio of the totals.
# Like with like: libmodbus has one request in flight (its API waits for each reply), so the
# service reads with PIPELINE=1 by default (io.pipeline); PIPELINE=4 is the twin's setting
# (configs/twin-service.toml), a different client: the module answers the queued requests
# together, which libmodbus cannot ask for, so that ratio is not a comparison of decoders.
#
# libmodbus is never a build dependency: the bench fetches the Debian packages (libmodbus5,
# libmodbus-dev) with `apt-get download` into a temporary directory and unpacks them there
# with `dpkg -x`, or takes an unpacked or installed prefix from LIBMODBUS_PREFIX (its
# include/modbus/modbus.h and lib/.../libmodbus.so*).
#   bash benches/acquire_ratio.sh                 # from the repository root
#   RUNS=5 SLICES=10 bash benches/acquire_ratio.sh
#   PIPELINE=4 bash benches/acquire_ratio.sh      # the twin's setting: 4 reads in flight
#   AXISCOMP_BIN=/tmp/old/axiscomp bash benches/acquire_ratio.sh   # another build
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
runs=${RUNS:-3}
slices=${SLICES:-5}
window=${WINDOW_S:-3}
settle=${SETTLE_S:-1}
pipeline=${PIPELINE:-1}
command -v gcc >/dev/null || { echo "acquire_ratio.sh: gcc not found" >&2; exit 1; }
command -v python3 >/dev/null || { echo "acquire_ratio.sh: python3 not found" >&2; exit 1; }

# AXISCOMP_BIN: a binary built already (e.g. of another commit, for a before/after);
# otherwise the release build. It is copied, so a build meanwhile cannot replace it.
if [ -n "${AXISCOMP_BIN:-}" ]; then
  built=$AXISCOMP_BIN
else
  cargo build --release --locked -q
  built="${CARGO_TARGET_DIR:-target}/release/axiscomp"
fi

source tests/interop/twin-configs.sh
harness acquire_ratio.sh
twin_configs "$work"
bin="$work/axiscomp"
cp "$built" "$bin"
sed -i 's/^rate_hz = .*/rate_hz = 0.0/' "$work/service.toml"
sed -i "s/^pipeline = .*/pipeline = $pipeline/" "$work/service.toml"
grep -q "^pipeline = $pipeline\$" "$work/service.toml" || fail "no io.pipeline in the twin's service config"
# A binary from before io.pipeline (the "before" of a before/after) refuses the key: drop it.
checked=$("$bin" check --config "$work/service.toml" 2>&1 || true)
if grep -q 'unknown field `pipeline`' <<<"$checked"; then
  sed -i '/^pipeline = /d' "$work/service.toml"
  echo "acquire_ratio.sh: $built does not know io.pipeline: reading without it"
fi
sock="$work/control.sock"

# libmodbus, unpacked into the work directory (or LIBMODBUS_PREFIX).
prefix=${LIBMODBUS_PREFIX:-}
if [ -z "$prefix" ]; then
  command -v apt-get >/dev/null && command -v dpkg >/dev/null \
    || fail "no apt-get/dpkg to fetch libmodbus: set LIBMODBUS_PREFIX to an unpacked libmodbus"
  mkdir -p "$work/deb"
  (cd "$work/deb" && apt-get download -q libmodbus5 libmodbus-dev >"$work/apt.log" 2>&1) \
    || fail "apt-get download libmodbus5 libmodbus-dev failed (apt.log)"
  for d in "$work"/deb/*.deb; do dpkg -x "$d" "$work/libmodbus"; done
  prefix="$work/libmodbus/usr"
fi
header=$(find "$prefix" -name modbus.h -path '*modbus/modbus.h' | head -1)
lib=$(find "$prefix" -name 'libmodbus.so*' | sort | head -1)
[ -n "$header" ] && [ -n "$lib" ] || fail "no modbus.h or libmodbus.so under $prefix"
libdir=$(dirname "$lib")
gcc -O2 -I "$(dirname "$header")" -o "$work/libmodbus_read" benches/acquire_ratio/libmodbus_read.c \
  -L "$libdir" -l:"$(basename "$(find "$libdir" -name 'libmodbus.so.*' | sort | head -1)")" \
  -Wl,-rpath,"$libdir" || fail "cannot build the libmodbus client"
lm_version=$(find "$libdir" -name 'libmodbus.so.*.*' -printf '%f\n' | head -1)

io=$(sed -n 's/^listen = "127.0.0.1:\([0-9]*\)"/\1/p' "$work/sim.toml" | head -1)
read -r unit start count < <(python3 - <<'EOF'
import tomllib
m = tomllib.load(open("plc-maps/io/generic.toml", "rb"))
assert m["register"] == "input"
print(m["unit_id"], m["block_start"], m["block_length"])
EOF
)

"$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
sleep 1

# psd: "SEQ UNIX_US IO_STATE" (empty when the service does not answer).
psd() {
  "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
print((s.get("psd") or {}).get("seq", 0), s["unix_us"], s["links"]["io"]["state"])' 2>/dev/null || true
}

echo "acquire_ratio.sh: twin I/O module 127.0.0.1:$io, block: input registers $start..$((start + count - 1)) of unit $unit; $lm_version"
echo "acquire_ratio.sh: the service unthrottled (io.rate_hz = 0) with io.pipeline = $pipeline, libmodbus one request in flight"
echo "acquire_ratio.sh: $runs runs of $slices slices, each slice $window s of the service then $window s of libmodbus"
RUST_LOG=warn "$bin" serve --config "$work/service.toml" >"$work/serve.log" 2>&1 & svc=$!
st=""
for _ in $(seq 1 60); do
  read -r _ _ st <<<"$(psd)" || true
  [ "${st:-}" = up ] && break
  kill -0 "$svc" 2>/dev/null || fail "the service exited"
  sleep 0.5
done
[ "${st:-}" = up ] || fail "the I/O link did not come up"
trap 'kill -CONT "$svc" 2>/dev/null; harness_cleanup' EXIT
# Totals per run: frames, service seconds, blocks, libmodbus seconds.
results=()
for r in $(seq 1 "$runs"); do
  frames=0; fsecs=0; blocks=0; bsecs=0
  for _ in $(seq 1 "$slices"); do
    kill -CONT "$svc"
    sleep "$settle"
    read -r seq0 us0 _ <<<"$(psd)"
    sleep "$window"
    read -r seq1 us1 st <<<"$(psd)"
    # Stopped, the service leaves the machine (and the twin) to libmodbus.
    kill -STOP "$svc"
    [ "$st" = up ] || fail "the I/O link was $st at the end of a slice (run $r)"
    read -r b secs errors < <("$work/libmodbus_read" 127.0.0.1 "$io" "$unit" "$start" "$count" "$window") \
      || fail "the libmodbus client failed (run $r)"
    [ "$errors" = 0 ] || fail "the libmodbus client had $errors errors (run $r)"
    frames=$((frames + seq1 - seq0))
    fsecs=$(python3 -c "print($fsecs + ($us1 - $us0) * 1e-6)")
    blocks=$((blocks + b))
    bsecs=$(python3 -c "print($bsecs + $secs)")
  done
  line=$(python3 -c "
f = $frames / $fsecs; b = $blocks / $bsecs
print(f'$frames $fsecs $blocks $bsecs {f:.0f} {b:.0f} {f / b:.3f}')")
  results+=("$line")
  read -r _ _ _ _ fps bps ratio <<<"$line"
  echo "acquire_ratio.sh: run $r: service $fps frames/s, libmodbus $bps blocks/s, ratio $ratio"
done
kill -CONT "$svc"
printf '%s\n' "${results[@]}" | python3 -c '
import sys
rows = [l.split() for l in sys.stdin.read().splitlines()]
ratios = [float(r[6]) for r in rows]
f = sum(float(r[0]) for r in rows) / sum(float(r[1]) for r in rows)
b = sum(float(r[2]) for r in rows) / sum(float(r[3]) for r in rows)
print(f"acquire_ratio.sh: over {len(rows)} runs: service {f:.0f} frames/s, libmodbus {b:.0f} blocks/s, "
      f"ratio {f / b:.3f} (per run {min(ratios):.3f}..{max(ratios):.3f})")'
