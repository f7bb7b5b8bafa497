#!/usr/bin/env bash
# LinuxCNC as a peer (Debian's linuxcnc-uspace, headless, no realtime kernel):
# - the generated LinuxCNC part program through LinuxCNC's own rs274 interpreter: every target of
#   every run and direction, from its direction's side after the overrun, with its dwell;
# - our comp files (types 0 and 1, mm and inch machines) loaded by a running LinuxCNC
#   (milltask + motmod, one trivkins joint, motor command looped back, a Python display that
#   homes and moves by MDI); the correction it applies, motor-pos-cmd − pos-cmd read from HAL
#   at table points and between them in both directions, must equal −e.
# As root, rtapi_app needs RTAPI_UID (it then runs as that uid; the tests put its FIFO in a
# directory that uid can write). The tests are #[ignore]d in plain `cargo test`.
set -euo pipefail
cd "$(dirname "$0")/../.."
for tool in rs274 linuxcnc halcmd; do
  command -v "$tool" >/dev/null || { echo "linuxcnc.sh: $tool missing: apt-get install linuxcnc-uspace" >&2; exit 1; }
done
# The display script imports LinuxCNC's Python modules from Debian's python3.
[ -x /usr/bin/python3 ] && /usr/bin/python3 -c 'import linuxcnc, hal' || {
  echo "linuxcnc.sh: /usr/bin/python3 cannot import linuxcnc and hal (linuxcnc-uspace)" >&2; exit 1; }
if [ "$(id -u)" = 0 ]; then
  export RTAPI_UID=${RTAPI_UID:-$(id -u nobody)}
fi
# LinuxCNC's lock: a running LinuxCNC keeps it, and then the tests must not start a second one.
# A lock that no LinuxCNC process holds is what a killed run left behind (a CI try stopped mid-step,
# say): it is removed, as LinuxCNC's own script does headless, and said so.
if [ -e /tmp/linuxcnc.lock ]; then
  running=$(pgrep -l -x 'rtapi_app|milltask|linuxcncsvr|io|linuxcnc' || true)
  if [ -n "$running" ]; then
    echo "linuxcnc.sh: /tmp/linuxcnc.lock is held by a running LinuxCNC ($(echo "$running" | tr '\n' ' ')): stop it (linuxcnc's own Ctrl-C, or kill those processes) and run again" >&2
    exit 1
  fi
  echo "linuxcnc.sh: /tmp/linuxcnc.lock left by a LinuxCNC that is no longer running: removed"
  rm -f /tmp/linuxcnc.lock
fi
cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it comp_export::linuxcnc -- --ignored --nocapture --test-threads=1
