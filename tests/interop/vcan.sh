#!/usr/bin/env bash
# SocketCAN integration tests (tests/it/socketcan.rs) against a real kernel CAN stack: builds
# the `it` test binary on the host and runs only those tests inside the vcan VM
# (../shared/tools/vcan-vm, see its README), where vcan0 is up and can-utils are on PATH.
#
#   bash tests/interop/vcan.sh          # from the repository root
#
# Needs qemu-system-x86 and a prepared VM cache (run-in-vm.sh --prepare). Environment:
#   VCANVM_DIR           the vcan-vm tool (default ../shared/tools/vcan-vm)
#   VCANVM_RUNNER_OPTS   extra run-in-vm.sh options (default: -t 900 -m 1G)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
vm=${VCANVM_DIR:-../shared/tools/vcan-vm}
[ -x "$vm/cargo-runner.sh" ] || { echo "vcan.sh: no vcan-vm tool at $vm" >&2; exit 2; }
vm=$(cd "$vm" && pwd)
# The guest runs code about 14x slower than the host, and the test binary is large.
export VCANVM_RUNNER_OPTS=${VCANVM_RUNNER_OPTS:--t 900 -m 1G}
export CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_RUNNER="$vm/cargo-runner.sh"
# All tests share vcan0, so one at a time.
exec cargo test --locked --profile "${CARGO_PROFILE:-dev}" --test it -- --ignored socketcan:: --test-threads=1
