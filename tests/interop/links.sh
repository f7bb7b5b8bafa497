#!/usr/bin/env bash
# Field links that tell the truth (issue 18): the live service against a pymodbus I/O module
# that answers with one exception, then only exceptions, then hangs (accepts connections,
# never answers), then goes away; the link state, the alarms and the frames' validity are
# asserted each time (tests/it/links.rs, tests/interop/pymodbus_faults.py).
# Needs python3 with pymodbus >= 3.12 (.ci/run installs it first).
set -euo pipefail
cd "$(dirname "$0")/../.."
python3 -c 'import pymodbus.simulator, tomllib' || { echo "links.sh: python3 with pymodbus >= 3.12 and tomllib (3.11+) needed" >&2; exit 1; }
cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored --exact links::interop_field_links_tell_the_truth --nocapture
