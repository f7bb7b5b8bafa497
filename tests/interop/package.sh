#!/usr/bin/env bash
# The Debian package installed as a plant installs it, and the control API's roles for real
# (issue 18). Builds the package with cargo-deb (revision 1, and revision 2 for the upgrade),
# then, as root:
#   - dpkg -i: the binary, the unit (installed, not enabled), the configuration as a conffile,
#     the system user axiscomp, the groups axiscomp (operators) and axiscomp-view (viewers),
#     /var/lib/axiscomp owned by axiscomp, mode 0750;
#   - the service started as its system user against the twin (by systemd when systemd runs
#     the machine, else with the unit's User, UMask, Environment and ExecStartPre/ExecStart
#     through setpriv), with an edited /etc/axiscomp/axiscomp.toml;
#   - real users made here, one in each role group and one in neither, run
#     tests/interop/roles.py (an independent client) and the CLI through setpriv; the state
#     directory's and the socket's modes (and the socket's ACL) are checked;
#   - an upgrade to revision 2 and a reinstall over itself keep the store and the edited
#     conffile, and the service serves the same audit log after each; dpkg -r keeps the store
#     and the configuration; dpkg --purge deletes them.
# Nothing it installs may outlive it: where it can (root with CAP_SYS_ADMIN) it runs in a
# throwaway copy of the system, an overlay of / on tmpfs in private mount and pid namespaces,
# whose every change (the package, users, groups, /etc, /var, processes) vanishes with it. In a
# container without that capability the container is the throwaway (PACKAGE_SANDBOX=no, chosen
# by itself when it finds itself in one).
#   bash tests/interop/package.sh                     # root; cargo-deb on PATH (or CARGO_DEB)
#   KEEP=1 bash tests/interop/package.sh              # print the logs' tails at the end
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
name=package.sh

# Inside the chroot (or directly in a throwaway container): the test proper.
installed() {
  local deb1=$1 deb2=$2
  source tests/interop/twin-configs.sh
  harness "$name"
  # Globals: the EXIT trap reads them after this function has returned.
  users=(ac-viewer ac-operator ac-stranger)
  sock=/run/axiscomp/control.sock db=/var/lib/axiscomp/axiscomp.db systemd=""
  [ -d /run/systemd/system ] && systemd=1
  stop_service() {
    if [ -n "$systemd" ]; then systemctl stop axiscomp || true; fi
    if [ -n "$svc" ]; then kill "$svc" 2>/dev/null || true; wait "$svc" 2>/dev/null || true; svc=""; fi
  }
  cleanup() {
    stop_service
    for u in "${users[@]}"; do userdel "$u" 2>/dev/null || true; done
    harness_cleanup
  }
  trap cleanup EXIT
  unit_key() { sed -n "s/^$1=//p" "$unit"; }

  # start_service N: as the unit would (log serve-N.log), then wait until it answers.
  start_service() {
    if [ -n "$systemd" ] && ! systemctl start axiscomp; then
      # A container's systemd may lack what the unit's sandboxing needs: say so, go on
      # without it.
      echo "$name: systemctl start axiscomp failed; starting it with setpriv instead" >&2
      journalctl -u axiscomp -n 20 --no-pager >&2 || true
      systemd=""
    fi
    if [ -z "$systemd" ]; then
      local user group umask env pre start
      user=$(unit_key User); group=$(unit_key Group); umask=$(unit_key UMask)
      mapfile -t env < <(unit_key Environment)
      pre=$(unit_key ExecStartPre); start=$(unit_key ExecStart)
      # RuntimeDirectory=axiscomp, RuntimeDirectoryMode=0755.
      install -d -o "$user" -g "$group" -m 0755 /run/axiscomp
      setpriv --reuid "$user" --regid "$group" --init-groups --no-new-privs \
        env -i PATH=/usr/bin:/bin "${env[@]}" sh -c "umask $umask && $pre && exec $start" \
        >"$work/serve-$1.log" 2>&1 &
      svc=$!
    fi
    for _ in $(seq 1 120); do
      axiscomp status --socket "$sock" --json >/dev/null 2>&1 && return 0
      [ -z "$svc" ] || kill -0 "$svc" 2>/dev/null || fail "the service (start $1) exited"
      sleep 0.5
    done
    fail "the service (start $1) did not answer on $sock"
  }
  # as USER CMD...: run CMD as USER with its groups, nothing else of root's.
  as() { local u=$1; shift; setpriv --reuid "$u" --regid "$u" --init-groups --no-new-privs "$@"; }
  # audit_rows: the operator's audit entries in the store, read with sqlite3 (not the service).
  audit_rows() {
    python3 - "$db" <<'EOF'
import sqlite3, sys
c = sqlite3.connect(f"file:{sys.argv[1]}?mode=ro", uri=True)
print(c.execute("SELECT count(*) FROM audit WHERE user = 'ac-operator'").fetchone()[0])
EOF
  }
  # same_conf: the edited configuration is still in place.
  same_conf() {
    cmp -s /etc/axiscomp/axiscomp.toml "$work/service.toml" || fail "$1: /etc/axiscomp/axiscomp.toml is not the edited one"
  }

  echo "$name: dpkg -i $(basename "$deb1")"
  dpkg -i "$deb1" >"$work/dpkg-install.log" 2>&1 || fail "dpkg -i $deb1"
  unit=$(dpkg -L axiscomp | grep '/systemd/system/axiscomp.service$') || fail "no unit in the package"
  [ -x /usr/bin/axiscomp ] || fail "no /usr/bin/axiscomp"
  dpkg-query -W -f='${Conffiles}\n' axiscomp | grep -q '^ /etc/axiscomp/axiscomp.toml ' \
    || fail "/etc/axiscomp/axiscomp.toml is not a conffile"
  [ ! -e /etc/systemd/system/multi-user.target.wants/axiscomp.service ] \
    || fail "the unit was enabled on install (it must wait for the configuration)"
  getent group axiscomp >/dev/null && getent group axiscomp-view >/dev/null || fail "role groups missing"
  uid=$(id -u axiscomp) || fail "no system user axiscomp"
  [ "$uid" -lt 1000 ] || fail "axiscomp is not a system user (uid $uid)"
  [ "$(stat -c '%a %U %G' /var/lib/axiscomp)" = "750 axiscomp axiscomp" ] \
    || fail "/var/lib/axiscomp is $(stat -c '%a %U %G' /var/lib/axiscomp), not 750 axiscomp axiscomp"
  echo "$name: installed: $unit (not enabled), conffile, user axiscomp (uid $uid), groups axiscomp and axiscomp-view, /var/lib/axiscomp 750"

  # The plant's configuration: the twin's links (the edited conffile the upgrades must keep).
  twin_configs "$work"
  cp "$work/service.toml" /etc/axiscomp/axiscomp.toml
  axiscomp sim --config "$work/sim.toml" >"$work/sim.log" 2>&1 & sim=$!
  sleep 1
  start_service 1
  echo "$name: the service answers on $sock as user axiscomp ($([ -n "$systemd" ] && echo systemd || echo "setpriv, the unit's settings"))"

  # Modes: the store is not world-readable; the socket admits its owner and the two groups.
  [ "$(stat -c '%a %U %G' /var/lib/axiscomp)" = "750 axiscomp axiscomp" ] || fail "state directory mode changed"
  others=$(find /var/lib/axiscomp -perm /o=rwx | head -3)
  [ -z "$others" ] || fail "readable by others in the store: $others"
  [ "$(stat -c '%a %U' "$sock")" = "660 axiscomp" ] || fail "socket is $(stat -c '%a %U %G' "$sock"), not 660 axiscomp"
  python3 - "$sock" <<'EOF' || fail "the socket's ACL"
import grp, os, struct, sys
v = os.getxattr(sys.argv[1], "system.posix_acl_access")
assert struct.unpack_from("<I", v)[0] == 2, "ACL version"
e = [struct.unpack_from("<HHI", v, 4 + 8 * i) for i in range((len(v) - 4) // 8)]
named = {grp.getgrgid(i).gr_name: p for t, p, i in e if t == 0x08}
objs = {t: p for t, p, i in e if t != 0x08}
assert named == {"axiscomp": 6, "axiscomp-view": 6}, named
assert objs == {0x01: 6, 0x04: 0, 0x10: 6, 0x20: 0}, objs
print("package.sh: socket ACL: user::rw- group::--- group:axiscomp:rw- group:axiscomp-view:rw- mask::rw- other::---")
EOF

  # Real users: a viewer, an operator, and one in neither group.
  useradd -M -s /usr/sbin/nologin -G axiscomp-view ac-viewer
  useradd -M -s /usr/sbin/nologin -G axiscomp ac-operator
  useradd -M -s /usr/sbin/nologin ac-stranger
  # A Python the users may run (root's own may be under /root).
  local py=/usr/bin/python3 bin
  [ -x "$py" ] || py=$(command -v python3)
  bin=$(mktemp -d); chmod 755 "$bin"
  cp tests/interop/roles.py "$bin/"; chmod 644 "$bin/roles.py"
  as ac-stranger "$py" "$bin/roles.py" none "$sock" axiscomp || fail "stranger"
  as ac-viewer "$py" "$bin/roles.py" viewer "$sock" axiscomp || fail "viewer"
  as ac-operator "$py" "$bin/roles.py" operator "$sock" axiscomp || fail "operator"
  # The CLI says the same to each.
  if out=$(as ac-stranger axiscomp status --socket "$sock" 2>&1); then fail "the stranger read the status"; fi
  grep -q "permission denied; only the service's viewer and operator groups may" <<<"$out" \
    || fail "the stranger's CLI error: $out"
  echo "$name: stranger, CLI: $out"
  if ls_out=$(as ac-stranger ls /var/lib/axiscomp 2>&1); then fail "the stranger listed the store"; fi
  if ls_out=$(as ac-viewer ls /var/lib/axiscomp 2>&1); then fail "a viewer listed the store"; fi
  as ac-viewer axiscomp status --socket "$sock" >/dev/null || fail "the viewer's axiscomp status"
  rc=0; out=$(as ac-viewer axiscomp run abort --socket "$sock" 2>&1) || rc=$?
  [ "$rc" != 0 ] && grep -q "may not run_abort: it needs the operator role" <<<"$out" \
    || fail "the viewer's axiscomp run abort (exit $rc): $out"
  echo "$name: viewer, CLI (exit $rc): $out"
  rc=0; out=$(as ac-operator axiscomp run abort --socket "$sock" 2>&1) || rc=$?
  ! grep -q "may not" <<<"$out" || fail "the operator's axiscomp run abort: $out"
  echo "$name: operator, CLI (exit $rc): $out"

  # The store across an upgrade, a reinstall, a removal.
  stop_service
  rows=$(audit_rows)
  [ "$rows" -ge 16 ] || fail "only $rows audit entries of ac-operator in the store"
  sum=$(sha256sum "$db" | cut -c1-16)
  for step in "upgrade to $(basename "$deb2")" "reinstall of $(basename "$deb2")"; do
    dpkg -i "$deb2" >"$work/dpkg-upgrade.log" 2>&1 || fail "dpkg -i $deb2 ($step)"
    [ "$(sha256sum "$db" | cut -c1-16)" = "$sum" ] || fail "$step changed the store"
    same_conf "$step"
    [ "$(stat -c '%a %U %G' /var/lib/axiscomp)" = "750 axiscomp axiscomp" ] || fail "$step: state directory mode"
    start_service "after $step"
    # The service serves the same log to the operator (id 1 is root's first request, if any).
    n=$(as ac-operator "$py" -c '
import json, socket, sys
s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1]); f = s.makefile("rw")
f.write(json.dumps({"cmd": "audit", "limit": 1000}) + "\n"); f.flush()
print(sum(e.get("user") == "ac-operator" for e in json.loads(f.readline())["result"]["entries"]))' "$sock")
    [ "$n" = "$rows" ] || fail "$step: the service shows $n of the operator's $rows audit entries"
    stop_service
    sum=$(sha256sum "$db" | cut -c1-16)
    echo "$name: $step: store kept ($rows operator audit entries served), edited conffile kept"
  done
  version=$(dpkg-query -W -f='${Version}' axiscomp)
  dpkg -r axiscomp >"$work/dpkg-remove.log" 2>&1 || fail "dpkg -r"
  [ ! -e /usr/bin/axiscomp ] && [ ! -e "$unit" ] || fail "dpkg -r left the binary or the unit"
  [ "$(sha256sum "$db" | cut -c1-16)" = "$sum" ] || fail "dpkg -r changed the store"
  [ "$(audit_rows)" = "$rows" ] || fail "dpkg -r: audit entries lost"
  same_conf "dpkg -r"
  echo "$name: dpkg -r ($version): binary and unit gone; store ($rows operator audit entries) and configuration kept"
  dpkg --purge axiscomp >"$work/dpkg-purge.log" 2>&1 || fail "dpkg --purge"
  [ ! -e /var/lib/axiscomp ] || fail "purge left /var/lib/axiscomp"
  [ ! -e /etc/axiscomp ] || fail "purge left /etc/axiscomp: $(ls -A /etc/axiscomp)"
  echo "$name: dpkg --purge: store and configuration deleted (user axiscomp and the groups kept, Debian's practice)"
  if [ -n "${KEEP:-}" ]; then tail -n 5 "$work"/*.log; fi
  echo "$name: PASS"
}

# Inside private mount and pid namespaces: an overlay of / on a tmpfs at $1, then the test in
# a chroot there. Every mount dies with the namespace.
sandbox() {
  local t=$1 deb1=$2 deb2=$3 r
  mount -t tmpfs -o mode=0755 tmpfs "$t"
  mkdir "$t/upper" "$t/work" "$t/root"
  mount -t overlay overlay -o "lowerdir=/,upperdir=$t/upper,workdir=$t/work" "$t/root"
  r=$t/root
  mount -t proc proc "$r/proc"
  mount --rbind /dev "$r/dev"
  mount --rbind /sys "$r/sys"
  mount -t tmpfs -o mode=0755 tmpfs "$r/run"
  mount -t tmpfs -o mode=1777 tmpfs "$r/tmp"
  # The checkout may be on a mount of its own, which the overlay of / does not show.
  mkdir -p "$r$PWD"
  mount --rbind "$PWD" "$r$PWD"
  mkdir "$r/tmp/debs"
  cp "$deb1" "$deb2" "$r/tmp/debs/"
  chroot "$r" /usr/bin/env -C "$PWD" bash tests/interop/package.sh --installed \
    "/tmp/debs/$(basename "$deb1")" "/tmp/debs/$(basename "$deb2")"
}

case "${1:-}" in
  --installed) shift; installed "$@"; exit ;;
  --sandbox) shift; sandbox "$@"; exit ;;
esac

[ "$(id -u)" = 0 ] || { echo "$name: needs root (dpkg -i, useradd): run it in CI or a root container" >&2; exit 1; }
cargo_deb=${CARGO_DEB:-cargo-deb}
[ -n "${PACKAGE_DEBS:-}" ] || command -v "$cargo_deb" >/dev/null \
  || { echo "$name: no cargo-deb (cargo install cargo-deb --version 3.8.0 --locked)" >&2; exit 1; }
for tool in dpkg setpriv useradd python3; do
  command -v "$tool" >/dev/null || { echo "$name: $tool not found" >&2; exit 1; }
done

# The packages: revision 1 (cargo-deb builds the release binary if needed) and revision 2;
# PACKAGE_DEBS="A.deb B.deb" tests those two instead.
if [ -n "${PACKAGE_DEBS:-}" ]; then
  read -r deb1 deb2 <<<"$PACKAGE_DEBS"
  deb1=$(realpath "$deb1"); deb2=$(realpath "$deb2")
else
out=${CARGO_TARGET_DIR:-target}/debian/package-test
rm -rf "$out" && mkdir -p "$out"
# The binary the rest of CI tested (AXISCOMP_BIN, put where cargo-deb looks for it) or the
# release build, so cargo-deb adds no build of its own; then the packaging alone, timed;
# --strip: the profiles keep line tables, the package not.
if [ -n "${AXISCOMP_BIN:-}" ]; then
  mkdir -p "${CARGO_TARGET_DIR:-target}/release"
  cp "$AXISCOMP_BIN" "${CARGO_TARGET_DIR:-target}/release/axiscomp"
else
  cargo build --release --locked
fi
start=$(date +%s.%N)
"$cargo_deb" --no-build --strip --deb-revision 1 -o "$out/" >/dev/null
mid=$(date +%s.%N)
"$cargo_deb" --no-build --strip --deb-revision 2 -o "$out/" >/dev/null
deb1=$(realpath "$out"/axiscomp_*-1_*.deb)
deb2=$(realpath "$out"/axiscomp_*-2_*.deb)
python3 -c 'import sys; print(f"package.sh: {sys.argv[1]}: {int(sys.argv[2]) / 2**20:.1f} MiB ({int(sys.argv[3]) / 2**20:.1f} MiB installed); cargo deb --no-build took {float(sys.argv[5]) - float(sys.argv[4]):.1f} s")' \
  "$(basename "$deb1")" "$(stat -c %s "$deb1")" "$(( $(dpkg-deb -f "$deb1" Installed-Size) * 1024 ))" "$start" "$mid"
dpkg-deb --contents "$deb1" | awk '{print "  " $1, $2, $6}'
fi

mode=${PACKAGE_SANDBOX:-auto}
if [ "$mode" = auto ]; then
  if unshare --mount --pid --fork true 2>/dev/null; then
    mode=yes
  elif [ -e /.dockerenv ] || [ -e /run/.containerenv ] || [ -n "${container:-}" ]; then
    mode=no
  else
    echo "$name: cannot make a throwaway root here (no mount namespaces) and this is not a container: refusing to install into this system (PACKAGE_SANDBOX=no overrides)" >&2
    exit 1
  fi
fi
if [ "$mode" = yes ]; then
  t=$(mktemp -d /tmp/axiscomp-package.XXXXXX)
  rc=0
  unshare --mount --pid --fork --propagation private bash "$0" --sandbox "$t" "$deb1" "$deb2" || rc=$?
  rmdir "$t"
  exit "$rc"
fi
installed "$deb1" "$deb2"
