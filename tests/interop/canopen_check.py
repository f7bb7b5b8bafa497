#!/usr/bin/env python3
"""Validate canopen_drive.py on its own with python-canopen's master side (RemoteNode,
BaseNode402), over the same udp_multicast bus, so that the drive script is known to be right
before axiscomp's master is pointed at it.

Run:

    python3 tests/interop/canopen_check.py [--port 43117] [--node-id 5]

It connects first, then starts canopen_drive.py as a subprocess (same port and node id,
default scaling), and checks, printing PASS/FAIL per step:
boot-up; SDO expedited and segmented (> 32 bytes) reads; reset communication (boot-up,
communication objects back to their defaults); heartbeat after writing 0x1017;
PDO mapping written by python-canopen's own `PdoMap.save()` (the standard disable / count 0 /
entries / count / enable sequence) for RPDO1 = 0x6040 + 0x607A and TPDO1 = 0x6041 + 0x6064,
synchronous; NMT start with SYNC; the CiA 402 power states up to operation enabled; homing;
profile-position moves with the set-point handshake; a fault injected through 0x2001 with its
EMCY, fault reset and re-enable; an SDO abort for a write to a read-only object; and a clean
exit of the drive on SIGTERM. The drive's own log is printed at the end. Exit status 0 when
every step passed.
"""

import argparse
import os
import signal
import subprocess
import threading
import sys
import time

import canopen
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import canopen_drive  # noqa: E402  (the same object dictionary)

FAILED = []


def check(name, ok, detail=""):
    print(f"{'PASS' if ok else 'FAIL'} {name}{': ' + detail if detail else ''}", flush=True)
    if not ok:
        FAILED.append(name)
    return ok


def wait(pred, timeout, step=0.01):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return pred()


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, default=43117)
    p.add_argument("--node-id", type=int, default=5)
    p.add_argument("--channel", default="239.74.163.2")
    args = p.parse_args()
    drive_args = argparse.Namespace(feed_mm=5.0, shaft_revs=1, increments=131072, motor_revs=1,
                                    heartbeat_ms=0)
    cpm = canopen_drive.counts_per_mm(drive_args)

    network = canopen.Network()
    network.connect(interface="udp_multicast", channel=args.channel, port=args.port,
                    receive_own_messages=False)
    node = BaseNode402(args.node_id, canopen_drive.build_od(args.node_id, drive_args))
    network.add_node(node)
    node.nmt.state  # noqa: B018  (the NMT master listens from here on)
    # Count boot-ups from the moment we listen, so one that arrives before we start waiting
    # for it is not lost (python-canopen's wait_for_bootup only sees later ones).
    global BOOTUPS
    BOOTUPS = Bootups(network, args.node_id)

    drive = subprocess.Popen(
        [sys.executable, os.path.join(HERE, "canopen_drive.py"), str(args.port),
         str(args.node_id), "--start-mm", "2.0", "--timeout", "120", "--channel", args.channel],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        run(node, network, cpm)
    except Exception as e:  # report, then still stop the drive
        check("scenario", False, f"{type(e).__name__}: {e}")
    finally:
        try:
            network.sync.stop()
            node.rpdo[1].stop()
        except Exception:
            pass
        drive.send_signal(signal.SIGTERM)
        try:
            out, _ = drive.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            drive.kill()
            out, _ = drive.communicate()
        check("drive exits cleanly on SIGTERM", drive.returncode == 0, f"status {drive.returncode}")
        print("--- drive log ---")
        print(out, end="")
        network.disconnect()
    print("ALL PASSED" if not FAILED else f"FAILED: {', '.join(FAILED)}")
    return 0 if not FAILED else 1


class Bootups:
    """Counts the node's boot-up messages (0x700 + id with byte 0 = 0)."""

    def __init__(self, network, node_id):
        self.cond = threading.Condition()
        self.count = 0
        network.subscribe(0x700 + node_id, self.on_message)

    def on_message(self, can_id, data, timestamp):
        if data and data[0] == 0:
            with self.cond:
                self.count += 1
                self.cond.notify_all()

    def wait_beyond(self, seen, timeout):
        """Wait until more than `seen` boot-ups have arrived; return the new count."""
        with self.cond:
            if not self.cond.wait_for(lambda: self.count > seen, timeout):
                raise TimeoutError(f"no boot-up within {timeout} s")
            return self.count


def run(node, network, cpm):
    seen = BOOTUPS.wait_beyond(0, 10)
    check("boot-up", True)
    check("device type 0x1000", node.sdo[0x1000].raw == 0x00020192)
    name = node.sdo[0x1008].raw
    check("segmented read of 0x1008", name == canopen_drive.DEVICE_NAME and len(name) > 32,
          f"{len(name)} bytes")

    # Reset communication, as axiscomp's configure does: boot-up again, 0x1017 at its default.
    node.sdo[0x1017].raw = 250
    node.nmt.state = "RESET COMMUNICATION"
    seen = BOOTUPS.wait_beyond(seen, 5)
    check("reset communication: boot-up, defaults back", node.sdo[0x1017].raw == 0)

    node.sdo[0x1017].raw = 100
    node.nmt.wait_for_heartbeat(2)
    check("heartbeat after 0x1017", node.nmt.state == "PRE-OPERATIONAL", node.nmt.state)

    # PDO mapping with python-canopen's own standard sequence.
    node.tpdo.read()
    node.rpdo.read()
    t = node.tpdo[1]
    t.clear()
    t.add_variable(0x6041)
    t.add_variable(0x6064)
    t.trans_type = 1
    t.enabled = True
    r = node.rpdo[1]
    r.clear()
    r.add_variable(0x6040)
    r.add_variable(0x607A)
    r.trans_type = 1
    r.enabled = True
    node.tpdo.save()
    node.rpdo.save()
    check("TPDO1 mapping", node.sdo[0x1A00][0].raw == 2 and node.sdo[0x1A00][1].raw == 0x60410010
          and node.sdo[0x1A00][2].raw == 0x60640020)
    check("RPDO1 mapping", node.sdo[0x1600][0].raw == 2 and node.sdo[0x1600][1].raw == 0x60400010
          and node.sdo[0x1600][2].raw == 0x607A0020)
    # The drive refuses mapping changes while the PDO is valid.
    try:
        node.sdo[0x1A00][0].raw = 0
        check("mapping locked while valid", False)
    except SdoAbortedError as e:
        check("mapping locked while valid", e.code == 0x08000022, f"0x{e.code:08X}")

    node.nmt.state = "OPERATIONAL"
    network.sync.start(0.01)
    r.start(0.01)
    node.setup_402_state_machine(read_pdos=False)
    node.nmt.wait_for_heartbeat(2)
    check("operational", node.nmt.state == "OPERATIONAL", node.nmt.state)
    node.check_statusword(1.0)
    check("TPDO on SYNC", node.state == "SWITCH ON DISABLED", f"{node.state} 0x{node.statusword:04X}")

    node.state = "OPERATION ENABLED"
    check("operation enabled", node.state == "OPERATION ENABLED", f"0x{node.statusword:04X}")

    ok = node.homing(timeout=20)
    node.check_statusword()
    check("homing", ok and node.tpdo_values[0x6064] == 0, f"position {node.tpdo_values[0x6064]}")
    # python-canopen's homing() leaves the start bit (4) set: drop it, so that the next
    # set-point is a rising edge.
    node.controlword = 0x0F
    node.check_statusword()
    node.check_statusword()

    node.op_mode = "PROFILED POSITION"
    check("profile position mode", node.op_mode == "PROFILED POSITION")
    for target_mm in (1.5, -1.0, 0.25):
        counts = int(round(target_mm * cpm))
        node.rpdo_pointers[0x607A].raw = counts
        node.controlword = 0x1F
        acked = wait(lambda: node.check_statusword() & 0x1000, 2)
        node.controlword = 0x0F
        reached = wait(lambda: (node.check_statusword() & 0x1400) == 0x0400, 10)
        pos = node.tpdo_values[0x6064]
        check(f"move to {target_mm} mm", acked and reached and abs(pos - counts) <= 1,
              f"ack {bool(acked)}, reached {bool(reached)}, position {pos} for {counts}")

    # Fault with EMCY, fault reset, enable again.
    node.emcy.reset()
    # The drive sends its EMCY before it confirms the write: look in the log.
    node.sdo[0x2001].raw = 0x8611
    wait(lambda: node.emcy.active, 2)
    emcy = node.emcy.active[0] if node.emcy.active else None
    check("EMCY following error", emcy is not None and emcy.code == 0x8611
          and emcy.register == 0x21 and emcy.data == b"\x01\x02\x03\x04\x05",
          str(emcy) if emcy is not None else "none")
    wait(lambda: node.check_statusword() is not None and node.state == "FAULT", 2)
    check("fault state", node.state == "FAULT", f"0x{node.statusword:04X}")
    node.controlword = 0x00
    node.check_statusword()
    node.controlword = 0x80
    wait(lambda: node.check_statusword() is not None and node.state == "SWITCH ON DISABLED", 2)
    node.controlword = 0x00
    check("fault reset", node.state == "SWITCH ON DISABLED" and not node.emcy.active,
          f"0x{node.statusword:04X}")
    node.state = "OPERATION ENABLED"
    check("enabled again", node.state == "OPERATION ENABLED")

    try:
        node.sdo[0x6041].raw = 1
        check("SDO abort on a read-only object", False)
    except SdoAbortedError as e:
        check("SDO abort on a read-only object", e.code == 0x06010002, f"0x{e.code:08X}")

    node.state = "SWITCH ON DISABLED"
    network.sync.stop()
    r.stop()
    node.nmt.state = "PRE-OPERATIONAL"


if __name__ == "__main__":
    sys.exit(main())
