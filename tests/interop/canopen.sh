#!/usr/bin/env bash
# Interop with python-canopen (an independent CANopen implementation): our master configures,
# enables, homes and moves tests/interop/canopen_drive.py, a LocalNode scripted as a CiA 402
# drive, over python-can's udp_multicast bus. Also checks the drive script on its own with
# python-canopen's RemoteNode/BaseNode402 (tests/interop/canopen_check.py).
# Needs: pip install canopen python-can msgpack.
#
#   bash tests/interop/canopen.sh       # from the repository root
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
py=${PYTHON:-python3}
"$py" -c 'import canopen, can, msgpack' || {
  echo "canopen.sh: $py lacks canopen, python-can or msgpack (pip install canopen python-can msgpack)" >&2
  exit 2
}
"$py" tests/interop/canopen_check.py
exec cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored canopen::python_canopen --test-threads=1
