# Sourced by the interop scripts that run `axiscomp sim` + `axiscomp serve` as processes.
# twin_configs DIR: free loopback ports for the twin's I/O module, its CNC control socket, its
# PLC and the CAN gateway pair; writes DIR/sim.toml (configs/sim.toml on those ports) and
# DIR/service.toml (configs/twin-service.toml on those ports, state under DIR, the twin's CNC
# running the part programs). Append what else a script needs to DIR/service.toml.
twin_configs() {
  local dir=$1 io ctl plc can_svc can_twin
  read -r io ctl plc can_svc can_twin < <(python3 - <<'EOF'
import socket
tcp = [socket.socket() for _ in range(3)]
udp = [socket.socket(type=socket.SOCK_DGRAM) for _ in range(2)]
for s in tcp + udp:
    s.bind(("127.0.0.1", 0))
print(*(s.getsockname()[1] for s in tcp + udp))
EOF
)
  sed -e "s#127.0.0.1:5020#127.0.0.1:$io#" \
      -e "s#127.0.0.1:5099#127.0.0.1:$ctl#" \
      -e "s#127.0.0.1:5502#127.0.0.1:$plc#" \
      -e "s#^local = \"127.0.0.1:20001\"#local = \"127.0.0.1:$can_twin\"#" \
      -e "s#^remote = \"127.0.0.1:20000\"#remote = \"127.0.0.1:$can_svc\"#" \
      configs/sim.toml > "$dir/sim.toml"
  sed -e "s#\./run/#$dir/#" \
      -e "s#127.0.0.1:5020#127.0.0.1:$io#" \
      -e "s#127.0.0.1:5502#127.0.0.1:$plc#" \
      -e "s#^local = \"127.0.0.1:20000\"#local = \"127.0.0.1:$can_svc\"#" \
      -e "s#^remote = \"127.0.0.1:20001\"#remote = \"127.0.0.1:$can_twin\"#" \
      configs/twin-service.toml > "$dir/service.toml"
  cat >> "$dir/service.toml" <<EOF

[cnc]
mode = "twin"
twin = "127.0.0.1:$ctl"
EOF
}

# harness NAME: a work directory ($work) and the twin's and the service's pids ($sim, $svc,
# set by the caller), killed on exit; the directory removed unless KEEP is set. It defines
# fail MESSAGE: print NAME: FAIL: MESSAGE and the tail of every log in $work, exit 1 (only
# when called, so a script with a fail of its own keeps it).
harness() {
  harness_name=$1
  work=$(mktemp -d)
  sim=""
  svc=""
  harness_cleanup() {
    [ -n "$svc" ] && kill "$svc" 2>/dev/null
    [ -n "$sim" ] && kill "$sim" 2>/dev/null
    wait 2>/dev/null || true
    if [ -n "${KEEP:-}" ]; then echo "$harness_name: kept $work" >&2; else rm -rf "$work"; fi
  }
  fail() {
    echo "$harness_name: FAIL: $*" >&2
    for f in "$work"/*.log; do
      [ -f "$f" ] || continue
      echo "---- $(basename "$f") (tail) ----" >&2
      tail -n 40 "$f" >&2
    done
    exit 1
  }
  trap harness_cleanup EXIT
}
