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
      -e "s#^twin = \"127.0.0.1:5099\"#twin = \"127.0.0.1:$ctl\"#" \
      configs/twin-service.toml > "$dir/service.toml"
  grep -q "^twin = \"127.0.0.1:$ctl\"\$" "$dir/service.toml" \
    || { echo "twin_configs: configs/twin-service.toml has no [cnc] twin = \"127.0.0.1:5099\" to point at the twin" >&2; return 1; }
  twin_ctl="127.0.0.1:$ctl"
  # TWIN_HEXAPOD_PORTS=free: the twin's hexapod controllers on free ports too (two scripts
  # running at once would otherwise share 50000 and 5001, and one drive the other's platform).
  if [ "${TWIN_HEXAPOD_PORTS:-}" = free ]; then
    local gcs xps
    read -r gcs xps < <(python3 -c '
import socket
s = [socket.socket() for _ in range(2)]
for x in s:
    x.bind(("127.0.0.1", 0))
print(*(x.getsockname()[1] for x in s))')
    sed -i -e "s#^gcs_listen = \"127.0.0.1:50000\"#gcs_listen = \"127.0.0.1:$gcs\"#" \
        -e "s#^xps_listen = \"127.0.0.1:5001\"#xps_listen = \"127.0.0.1:$xps\"#" "$dir/sim.toml"
    sed -i -e "s#^address = \"127.0.0.1:50000\"#address = \"127.0.0.1:$gcs\"#" "$dir/service.toml"
  fi
}

# twin_cmd JSON: one request to the twin's control socket (after twin_configs); prints the
# reply, fails unless it is ok.
twin_cmd() {
  python3 - "$twin_ctl" "$1" <<'EOF'
import json, socket, sys
host, port = sys.argv[1].rsplit(":", 1)
with socket.create_connection((host, int(port)), timeout=120) as s:
    s.sendall(sys.argv[2].encode() + b"\n")
    r = s.makefile().readline()
print(r.strip())
if not json.loads(r).get("ok"):
    sys.exit(f"twin: {sys.argv[2]}: {r.strip()}")
EOF
}

# svc_cmd JSON: one request to the service's control socket at $sock (the console's and the
# CLI's protocol, for what the CLI has no command for); prints the reply, fails on an error.
svc_cmd() {
  python3 - "$sock" "$1" <<'EOF'
import json, socket, sys
s = socket.socket(socket.AF_UNIX)
s.settimeout(90)
s.connect(sys.argv[1])
s.sendall(sys.argv[2].encode() + b"\n")
r = s.makefile().readline()
print(r.strip())
if not r.strip() or "error" in json.loads(r):
    sys.exit(f"service: {sys.argv[2]}: {r.strip()}")
EOF
}

# align_cli FROM TO: one round of the beam alignment over FROM..TO mm with `axiscomp align`
# against the service at $sock ($bin the binary), the twin's carriage moved to each end, as a
# technician does before a run (the pre-run check wants the plan's travel aligned): where PSD2
# lost its spot on the way, the follower is brought to the carriage; back at 0 mm, the zero is
# taken again (at the nominal 0 mm). Fails unless the check passes.
align_cli() {
  local from=$1 to=$2 at
  "$bin" align clear --socket "$sock" >/dev/null || return 1
  for at in "$from" "$to"; do
    twin_cmd "{\"cmd\":\"move\",\"mm\":$at}" >/dev/null || return 1
    twin_cmd '{"cmd":"wait"}' >/dev/null || return 1
    if ! spots_at_rest 6; then
      svc_cmd "{\"cmd\":\"follower\",\"action\":\"move\",\"mm\":$at}" >/dev/null || return 1
      spots_at_rest 30 || return 1
    fi
    "$bin" align read --socket "$sock" --at-mm="$at" >/dev/null || return 1
  done
  "$bin" align advice --socket "$sock" --from-mm "$from" --to-mm "$to" --axis X || return 1
  twin_cmd '{"cmd":"move","mm":0}' >/dev/null || return 1
  twin_cmd '{"cmd":"wait"}' >/dev/null || return 1
  if ! spots_at_rest 6; then
    svc_cmd '{"cmd":"follower","action":"move","mm":0}' >/dev/null || return 1
    spots_at_rest 30 || return 1
  fi
  # The zero at a known nominal (0 mm), as the lab takes it: positioning then reads relative
  # to the carriage's true position here, the way every capture is judged by the truth.
  svc_cmd '{"cmd":"nominal","mm":0.0}' >/dev/null
  svc_cmd '{"cmd":"zero"}' >/dev/null
  svc_cmd '{"cmd":"nominal","mm":null}' >/dev/null
}

# spots_at_rest SECONDS: wait until the service sees a spot on every PSD with the carriage at
# rest, then a station's window more; fails (quietly) after SECONDS.
spots_at_rest() {
  local i
  for i in $(seq 1 $(( $1 * 2 ))); do
    if "$bin" status --socket "$sock" --json 2>/dev/null | python3 -c '
import json, sys
s = json.load(sys.stdin)
p, t = s.get("psd") or {}, s["tracking"]
sys.exit(0 if all(x is not None for x in p.get("spots_um", [None])) and t["at_rest"] else 1)' 2>/dev/null; then
      sleep 0.6
      return 0
    fi
    sleep 0.5
  done
  return 1
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
  # Never fails (it runs under set -e from an EXIT trap: a failing kill of a process that is
  # already gone would turn a passed script's exit status into 1).
  harness_cleanup() {
    if [ -n "$svc" ]; then kill "$svc" 2>/dev/null || true; fi
    if [ -n "$sim" ]; then kill "$sim" 2>/dev/null || true; fi
    wait 2>/dev/null || true
    # KEEP_LOGS=DIR: the logs of the twin and the service kept there (.ci/run: beside its own).
    if [ -n "${KEEP_LOGS:-}" ]; then
      mkdir -p "$KEEP_LOGS" && cp "$work"/*.log "$KEEP_LOGS"/ 2>/dev/null || true
    fi
    if [ -n "${KEEP:-}" ]; then echo "$harness_name: kept $work" >&2; else rm -rf "$work"; fi
  }
  fail() {
    echo "$harness_name: FAIL: $*" >&2
    for f in "$work"/*.log; do
      [ -f "$f" ] || continue
      echo "---- $(basename "$f") (tail) ----" >&2
      grep -v "control request" "$f" | tail -n 80 >&2
    done
    exit 1
  }
  trap harness_cleanup EXIT
}
