#!/usr/bin/env bash
# Interop with python-can (an independent implementation of the udp_multicast format): runs
# the ignored `can::python_can_*` tests, which start tests/interop/pycan_peer.py on loopback.
# Installs nothing: python3 with python-can and msgpack must already be there
# (pip install python-can msgpack). PYTHON selects the interpreter (default python3).
#
#   bash tests/interop/can.sh           # from the repository root
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
py=${PYTHON:-python3}
"$py" -c 'import can, msgpack' || {
  echo "can.sh: $py lacks python-can or msgpack (pip install python-can msgpack)" >&2
  exit 2
}
exec cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored can::python_can --test-threads=1
