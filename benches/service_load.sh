#!/usr/bin/env bash
# The whole service's CPU and memory while it polls the twin's I/O module at 500 Hz with the
# follower drive up (issue 3 figures: target ≤ 5 % of one core, ≤ 30 MB RSS).
#   bash benches/service_load.sh [seconds]      # from the repository root
# Builds the release binary, starts the twin and the service as separate processes, lets
# them settle, then samples /proc/<pid>/stat (utime+stime) and VmRSS over the window.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
secs=${1:-30}
cargo build --release --locked -q
bin=target/release/axiscomp
work=$(mktemp -d)
trap 'kill $sim $svc 2>/dev/null; wait 2>/dev/null; rm -rf "$work"' EXIT
sed "s#./run/#$work/#" configs/twin-service.toml > "$work/service.toml"
$bin sim --config configs/sim.toml >"$work/sim.log" 2>&1 & sim=$!
sleep 1
RUST_LOG=warn $bin serve --config "$work/service.toml" >"$work/serve.log" 2>&1 & svc=$!
sleep 8
tck=$(getconf CLK_TCK)
ticks() { awk '{print $14+$15}' "/proc/$1/stat"; }
split() { awk '{print $14, $15}' "/proc/$1/stat"; }
ctxt() { awk '/^voluntary_ctxt/ {v=$2} /^nonvoluntary_ctxt/ {n=$2} END {print v + n}' "/proc/$1/status"; }
t0=$(ticks $svc); u0=$(split $svc); c0=$(ctxt $svc); s0=$(date +%s.%N)
sleep "$secs"
t1=$(ticks $svc); u1=$(split $svc); c1=$(ctxt $svc); s1=$(date +%s.%N)
rss=$(awk '/VmRSS/ {print $2}' /proc/$svc/status)
hwm=$(awk '/VmHWM/ {print $2}' /proc/$svc/status)
rate=$($bin status --socket "$work/control.sock" --json | python3 -c 'import json,sys; print(round(json.load(sys.stdin)["psd"]["rate_hz"],1))')
read -r ut0 st0 <<<"$u0"; read -r ut1 st1 <<<"$u1"
awk -v ut="$((ut1 - ut0))" -v st="$((st1 - st0))" -v t0="$t0" -v t1="$t1" -v s0="$s0" -v s1="$s1" -v tck="$tck" -v rss="$rss" -v hwm="$hwm" -v rate="$rate" -v cs="$((c1 - c0))" 'BEGIN {
  cpu = (t1 - t0) / tck / (s1 - s0) * 100
  printf "service at %s frames/s over %.0f s: CPU %.2f %% of one core (user %.2f, system %.2f), RSS %.1f MB (peak %.1f MB), %.0f context switches/s\n", rate, s1 - s0, cpu, ut / tck / (s1 - s0) * 100, st / tck / (s1 - s0) * 100, rss / 1024, hwm / 1024, cs / (s1 - s0)
}'
