#!/usr/bin/env bash
# Modbus interop with independent peers (DESIGN §10): pymodbus playing the I/O module for
# axiscomp's link and acquisition, and mbpoll reading the twin's I/O module.
# Needs python3 with pymodbus 3.x and /usr/bin/mbpoll (.ci/run installs them first).
set -euo pipefail
cd "$(dirname "$0")/../.."
command -v mbpoll >/dev/null || { echo "modbus.sh: mbpoll not found" >&2; exit 1; }
python3 -c 'import pymodbus, tomllib' || { echo "modbus.sh: python3 with pymodbus 3.x and tomllib (3.11+) needed" >&2; exit 1; }
cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored interop_pymodbus_io_frames interop_mbpoll_reads_the_twin
