#!/usr/bin/env bash
# Hostile peers (issue 18) against the running service on loopback: `axiscomp sim` and
# `axiscomp serve` (release build, 500 Hz acquisition, the pull server on, allow-list
# 127.0.0.1). tests/interop/hostile.py attacks the control socket (lines that are not JSON or
# not text, a 20 MB line, 2000 connections) and the pull server (1000 idle connections, a slow
# writer, an MBAP length that lies, an unknown unit, a write outside the acknowledgement range,
# a peer not on the allow-list). Around each attack the frames acquired are counted from
# psd.seq (at least MIN_FPS, default 495 frames/s, over the attack), the service's RSS is read
# (at most MAX_RSS_KIB, default 30720 KiB, at the peak) and the service must serve normally
# afterwards. Prints the figures; exits non-zero with the logs on failure. On a loaded machine
# where the service misses MIN_FPS at rest already, 99 % of its rate at rest passes (STRICT=1:
# MIN_FPS only).
#   bash tests/interop/hostile.sh        KEEP=1 keeps the work directory
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
command -v python3 >/dev/null || { echo "hostile.sh: python3 not found" >&2; exit 1; }
min_fps=${MIN_FPS:-495}
max_rss=${MAX_RSS_KIB:-30720}

# AXISCOMP_BIN: a binary built already (.ci/run builds one for every script).
if [ -n "${AXISCOMP_BIN:-}" ]; then
  bin=$AXISCOMP_BIN
else
  cargo build --release --locked -q
  bin="${CARGO_TARGET_DIR:-target}/release/axiscomp"
fi

source tests/interop/twin-configs.sh
harness hostile.sh
twin_configs "$work"
sock="$work/control.sock"
pull_port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
sed -i "s#^\[plc\]#[plc]\npull = true\npull_bind = \"127.0.0.1:$pull_port\"\npull_allow = [\"127.0.0.1\"]#" "$work/service.toml"

"$bin" sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
sleep 1
RUST_LOG=${RUST_LOG:-info} "$bin" serve --config "$work/service.toml" >"$work/serve.log" 2>&1 & svc=$!

# psd: "SEQ UNIX_US STATE" of the I/O link and frames now (empty when it does not answer).
psd() {
  "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
p = s.get("psd") or {}
print(p.get("seq", 0), s["unix_us"], s["links"]["io"]["state"], 1 if p.get("valid") else 0)' 2>/dev/null || true
}
for _ in $(seq 1 60); do
  read -r _ _ st valid <<<"$(psd)" || true
  [ "${st:-}" = up ] && [ "${valid:-0}" = 1 ] && break
  kill -0 "$svc" 2>/dev/null || fail "the service exited"
  sleep 0.5
done
[ "${st:-}" = up ] || fail "the I/O link did not come up"
sleep 2

rss() { awk '/^VmRSS:/ {print $2}' "/proc/$svc/status"; }
read -r seq0 t0 _ _ <<<"$(psd)"
sleep 5
read -r seq1 t1 _ _ <<<"$(psd)"
rest_fps=$(python3 -c "print(f'{($seq1 - $seq0) / (($t1 - $t0) * 1e-6):.1f}')")
echo "hostile.sh: at rest: $rest_fps frames/s, RSS $(rss) KiB"

# attack NAME ARGS...: run hostile.py ARGS between two snapshots; check frames/s and RSS.
attack() {
  local name=$1; shift
  read -r seq0 t0 _ _ <<<"$(psd)"
  local figures
  figures=$(python3 tests/interop/hostile.py "$@") || fail "$name: the attack found a fault"
  read -r seq1 t1 st valid <<<"$(psd)"
  [ -n "${seq1:-}" ] || fail "$name: no status afterwards"
  local fps
  fps=$(python3 -c "print(f'{($seq1 - $seq0) / (($t1 - $t0) * 1e-6):.1f}')")
  echo "hostile.sh: $name: $figures"
  echo "hostile.sh: $name: $fps frames/s over the attack, I/O link $st, frame valid $valid, RSS now $(rss) KiB"
  python3 - "$figures" "$fps" "$min_fps" "$max_rss" "$rest_fps" <<'EOF' || fail "$name: figures out of bounds"
import json, sys
f, fps, min_fps, max_rss = json.loads(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
rest = float(sys.argv[5])
peak = max(v for k, v in f.items() if k.startswith("rss") and isinstance(v, int))
# The attack must cost no frames: MIN_FPS, or (on a machine where the service misses it at
# rest already) 99 % of the rate at rest. STRICT=1: MIN_FPS only.
strict = __import__("os").environ.get("STRICT") == "1"
fps_ok = fps >= min_fps or (not strict and fps >= 0.99 * rest)
print(f"  frames/s {fps:.1f} (>= {min_fps:.0f}, at rest {rest:.1f}), peak RSS {peak} KiB (<= {max_rss})")
sys.exit(0 if fps_ok and peak <= max_rss else 1)
EOF
  [ "$st" = up ] && [ "$valid" = 1 ] || fail "$name: not serving normally afterwards (I/O $st, valid $valid)"
}

attack "control socket" control "$sock" "$svc"
grep -q "control socket: refused a connection" "$work/serve.log" || fail "no log line for refused control connections"
attack "pull server" pull "127.0.0.1:$pull_port" 1 "$svc"
grep -q "modbus connection refused" "$work/serve.log" || fail "no log line for refused Modbus connections"
echo "hostile.sh: passed"
