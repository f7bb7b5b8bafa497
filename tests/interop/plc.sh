#!/usr/bin/env bash
# PLC table protocol against independent peers (DESIGN §6, §10): a pymodbus server playing the
# PLC's side of the push handshake checks our pushed registers against its own encoding (every
# shipped map, and the generic map in all four word orders); mbpoll and a pymodbus client read
# the pull server, and writes outside the acknowledgement range or from a peer not allowed to
# write get exceptions and change nothing.
# Needs python3 (3.11+, tomllib) with pymodbus 3.12+ and /usr/bin/mbpoll.
set -euo pipefail
cd "$(dirname "$0")/../.."
command -v mbpoll >/dev/null || { echo "plc.sh: mbpoll not found" >&2; exit 1; }
python3 -c 'import pymodbus.simulator, tomllib' || { echo "plc.sh: python3 with pymodbus 3.12+ (SimDevice) and tomllib (3.11+) needed" >&2; exit 1; }
log=$(mktemp)
trap 'rm -f "$log"' EXIT
cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored plc:: 2>&1 | tee "$log"
# A filter that matched nothing would pass: the interop tests must have run.
grep -Eq '^test result: ok\. [1-9][0-9]* passed' "$log" || { echo "plc.sh: no PLC interop test ran" >&2; exit 1; }
