#!/usr/bin/env python3
"""A CiA 402 servo drive scripted on python-canopen's LocalNode, on python-can's udp_multicast
interface: an independent peer for axiscomp's CANopen master (src/canopen).

Run it (python-canopen 2.x, python-can 4.x with msgpack):

    python3 tests/interop/canopen_drive.py PORT NODE_ID [--feed-mm 5.0] [--shaft-revs 1]
        [--increments 131072] [--motor-revs 1] [--start-mm 2.0] [--timeout SECONDS]
        [--channel 239.74.163.2] [--heartbeat-ms 0]

- PORT, NODE_ID: the UDP port of the multicast group and the drive's node id (1..=127).
- --feed-mm/--shaft-revs (0x6092) and --increments/--motor-revs (0x608F): the scaling,
  increments per mm = increments / motor_revs * shaft_revs / feed_mm (gear 1:1). Use the same
  values as the master's `[canopen.scaling]`. 0x6092:01 holds the feed in µm.
- --start-mm: where the stage stands at power-on; the home switch is at 0 mm.
- --timeout: exit after this many seconds (0: run until SIGTERM/SIGINT).
- --heartbeat-ms: 0x1017 at power-on and after reset communication.

It prints one line per event to stdout ("<seconds> <event>": NMT state, CiA 402 power state,
mode, set-points, target reached, homing, PDO mapping, EMCY, SYNC count) and exits 0 on
SIGTERM, SIGINT or the timeout.

What it implements:
- NMT slave: boot-up at start and after reset node / reset communication (communication
  objects back to their defaults), heartbeat producer (0x1017);
- SDO server (python-canopen's) over this object dictionary: 0x1000, 0x1001, 0x1008 (a name
  longer than 32 bytes), 0x1017, 0x1018, 0x1400/0x1600 (RPDO1), 0x1800/0x1A00 (TPDO1),
  0x2001 (write an EMCY code here to inject a fault), 0x603F, 0x6040, 0x6041, 0x605A, 0x6060,
  0x6061, 0x6064, 0x6065, 0x6067, 0x606C, 0x607A, 0x607C, 0x607D, 0x6081, 0x6083, 0x6084,
  0x6085, 0x608F, 0x6092, 0x6098, 0x6099, 0x609A, 0x6502;
- PDO mapping written by SDO and honoured (mapping changes only while the PDO is disabled
  with COB-ID bit 31 and its count is 0; entries checked for direction and length; ≤ 64 bits);
- RPDO1 applied at the next SYNC (types 0..240) or at once (254/255); TPDO1 sent on SYNC
  (types 1..240, every n-th) or on change (254/255);
- the CiA 402 state machine driven by controlword writes (SDO or RPDO), fault reset on the
  rising edge of bit 7, quick stop (0x605A), halt;
- homing (mode 6): methods 1..34 drive to the home switch at 0x6099:01 then 0x6099:02 and set
  the position there to 0x607C; 35/37 home on the current position; others: homing error;
- profile position (mode 1): new set-point (bit 4) / acknowledge (bit 12), change immediately
  (bit 5), relative (bit 6), target reached (bit 10), software limits (0x607D), a trapezoidal
  motion profile simulated in real time (2 ms ticks).
"""

import argparse
import math
import os
import signal
import struct
import sys
import threading
import time

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary
import canopen.objectdictionary.datatypes as dt
from canopen.sdo import SdoAbortedError

DEVICE_NAME = "python-canopen CiA 402 drive (axiscomp interop peer, profile position, homing)"

MODE_PP = 1
MODE_HOMING = 6

# Statusword patterns of the power states (CiA 402), and names as python-canopen writes them.
STATE_BITS = {
    "NOT READY TO SWITCH ON": 0x00,
    "SWITCH ON DISABLED": 0x40,
    "READY TO SWITCH ON": 0x21,
    "SWITCHED ON": 0x23,
    "OPERATION ENABLED": 0x27,
    "QUICK STOP ACTIVE": 0x07,
    "FAULT REACTION ACTIVE": 0x0F,
    "FAULT": 0x08,
}

# Abort codes (CiA 301).
ABORT_DEVICE_STATE = 0x08000022
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_INVALID_VALUE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031

COMM_INDICES = (0x1017, 0x1400, 0x1600, 0x1800, 0x1A00)


def _var(name, index, sub, data_type, default, access="rw", pdo=False):
    v = ODVariable(name, index, sub)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    v.pdo_mappable = pdo
    return v


def build_od(node_id, args):
    """The drive's object dictionary (also used by the check script as the remote's)."""
    od = ObjectDictionary()
    od.node_id = node_id

    def add(index, name, data_type, default, access="rw", pdo=False):
        od.add_object(_var(name, index, 0, data_type, default, access, pdo))

    def record(index, name, subs):
        r = ODRecord(name, index)
        for sub, sname, data_type, default, access in subs:
            r.add_member(_var(sname, index, sub, data_type, default, access))
        od.add_object(r)

    cpm = counts_per_mm(args)

    def c(mm):
        return int(round(mm * cpm))

    add(0x1000, "Device type", dt.UNSIGNED32, 0x00020192, "ro")
    add(0x1001, "Error register", dt.UNSIGNED8, 0, "ro", True)
    add(0x1008, "Manufacturer device name", dt.VISIBLE_STRING, DEVICE_NAME, "const")
    add(0x1017, "Producer heartbeat time", dt.UNSIGNED16, args.heartbeat_ms)
    record(0x1018, "Identity", [
        (0, "Highest sub-index", dt.UNSIGNED8, 4, "const"),
        (1, "Vendor-ID", dt.UNSIGNED32, 0x0A5C, "ro"),
        (2, "Product code", dt.UNSIGNED32, 0x402F, "ro"),
        (3, "Revision", dt.UNSIGNED32, 0x00010000, "ro"),
        (4, "Serial", dt.UNSIGNED32, 2, "ro"),
    ])
    record(0x1400, "RPDO1 communication", [
        (0, "Highest sub-index", dt.UNSIGNED8, 2, "const"),
        (1, "COB-ID", dt.UNSIGNED32, 0x200 + node_id, "rw"),
        (2, "Transmission type", dt.UNSIGNED8, 255, "rw"),
    ])
    record(0x1600, "RPDO1 mapping", [(0, "Number of entries", dt.UNSIGNED8, 1, "rw")] + [
        (k, f"Entry {k}", dt.UNSIGNED32, 0x60400010 if k == 1 else 0, "rw") for k in range(1, 9)
    ])
    record(0x1800, "TPDO1 communication", [
        (0, "Highest sub-index", dt.UNSIGNED8, 5, "const"),
        (1, "COB-ID", dt.UNSIGNED32, 0x180 + node_id, "rw"),
        (2, "Transmission type", dt.UNSIGNED8, 255, "rw"),
        (3, "Inhibit time", dt.UNSIGNED16, 0, "rw"),
        (5, "Event timer", dt.UNSIGNED16, 0, "rw"),
    ])
    record(0x1A00, "TPDO1 mapping", [(0, "Number of entries", dt.UNSIGNED8, 1, "rw")] + [
        (k, f"Entry {k}", dt.UNSIGNED32, 0x60410010 if k == 1 else 0, "rw") for k in range(1, 9)
    ])
    add(0x2001, "Inject fault (EMCY code)", dt.UNSIGNED16, 0)
    add(0x603F, "Error code", dt.UNSIGNED16, 0, "ro", True)
    add(0x6040, "Controlword", dt.UNSIGNED16, 0, "rw", True)
    add(0x6041, "Statusword", dt.UNSIGNED16, 0, "ro", True)
    add(0x605A, "Quick stop option code", dt.INTEGER16, 2)
    add(0x6060, "Modes of operation", dt.INTEGER8, 0, "rw", True)
    add(0x6061, "Modes of operation display", dt.INTEGER8, 0, "ro", True)
    add(0x6064, "Position actual value", dt.INTEGER32, 0, "ro", True)
    add(0x6065, "Following error window", dt.UNSIGNED32, c(0.5))
    add(0x6067, "Position window", dt.UNSIGNED32, c(0.001))
    add(0x606C, "Velocity actual value", dt.INTEGER32, 0, "ro", True)
    add(0x607A, "Target position", dt.INTEGER32, 0, "rw", True)
    add(0x607C, "Home offset", dt.INTEGER32, 0)
    record(0x607D, "Software position limit", [
        (0, "Highest sub-index", dt.UNSIGNED8, 2, "const"),
        (1, "Min position limit", dt.INTEGER32, 0, "rw"),
        (2, "Max position limit", dt.INTEGER32, 0, "rw"),
    ])
    add(0x6081, "Profile velocity", dt.UNSIGNED32, c(10.0))
    add(0x6083, "Profile acceleration", dt.UNSIGNED32, c(100.0))
    add(0x6084, "Profile deceleration", dt.UNSIGNED32, c(100.0))
    add(0x6085, "Quick stop deceleration", dt.UNSIGNED32, c(500.0))
    record(0x608F, "Position encoder resolution", [
        (0, "Highest sub-index", dt.UNSIGNED8, 2, "const"),
        (1, "Encoder increments", dt.UNSIGNED32, args.increments, "ro"),
        (2, "Motor revolutions", dt.UNSIGNED32, args.motor_revs, "ro"),
    ])
    record(0x6092, "Feed constant", [
        (0, "Highest sub-index", dt.UNSIGNED8, 2, "const"),
        (1, "Feed (um)", dt.UNSIGNED32, int(round(args.feed_mm * 1000)), "ro"),
        (2, "Shaft revolutions", dt.UNSIGNED32, args.shaft_revs, "ro"),
    ])
    add(0x6098, "Homing method", dt.INTEGER8, 19)
    record(0x6099, "Homing speeds", [
        (0, "Highest sub-index", dt.UNSIGNED8, 2, "const"),
        (1, "Speed during search for switch", dt.UNSIGNED32, c(5.0), "rw"),
        (2, "Speed during search for zero", dt.UNSIGNED32, c(0.5), "rw"),
    ])
    add(0x609A, "Homing acceleration", dt.UNSIGNED32, c(50.0))
    add(0x6502, "Supported drive modes", dt.UNSIGNED32, 0x21, "ro")
    return od


def counts_per_mm(args):
    return args.increments / args.motor_revs * args.shaft_revs / args.feed_mm


def u32(b):
    return struct.unpack("<I", bytes(b[:4]).ljust(4, b"\0"))[0]


class Drive:
    """The drive's behaviour around a LocalNode. Every entry point takes `self.lock`."""

    def __init__(self, node, network, args):
        self.node = node
        self.network = network
        self.args = args
        self.cpm = counts_per_mm(args)
        self.lock = threading.RLock()
        self.t0 = time.monotonic()
        self.fsa = "SWITCH ON DISABLED"
        self.last_cw = 0
        self.pos = args.start_mm  # physical, home switch at 0
        self.vel = 0.0
        self.goal = None  # None | ("to", target, v, a, d) | ("stop", d)
        self.zero = args.start_mm
        self.last_update = time.monotonic()
        self.ack = False
        self.pending = None
        self.last_target = 0
        self.halted = False
        self.internal_limit = False
        self.homing = None  # None | "search" | "approach"
        self.homing_bits = 0x0400  # interrupted / not started
        self.homed = False
        self.following_error = False
        self.fault_code = 0
        self.rpdo_latched = None
        self.rpdo_cob = None
        self.tpdo_syncs = 0
        self.last_tpdo = None
        self.syncs = 0
        self.reported_state = None
        self.reported_nmt = None

    # --- helpers --------------------------------------------------------------------------

    def log(self, msg):
        try:
            print(f"{time.monotonic() - self.t0:8.3f} {msg}", flush=True)
        except OSError:
            pass  # nobody reads our output any more: keep driving

    def raw(self, index, sub=0):
        return self.node.get_data(index, sub)

    def uint(self, index, sub=0):
        return int.from_bytes(self.raw(index, sub), "little")

    def sint(self, index, sub=0):
        return int.from_bytes(self.raw(index, sub), "little", signed=True)

    def store(self, index, sub, data):
        self.node.data_store.setdefault(index, {})[sub] = bytes(data)

    def speed(self, index, sub=0):
        return self.uint(index, sub) / self.cpm

    def mode(self):
        return self.sint(0x6060)

    def mapping(self, map_index):
        n = min(self.uint(map_index, 0), 8)
        out = []
        for k in range(1, n + 1):
            v = self.uint(map_index, k)
            out.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
        return out

    def encoder(self):
        return int(round((self.pos - self.zero) * self.cpm))

    def moving(self):
        return self.goal is not None or self.vel != 0.0

    def statusword(self):
        sw = STATE_BITS[self.fsa] | 0x0200  # remote
        if self.fsa != "NOT READY TO SWITCH ON":
            sw |= 0x0010  # voltage enabled
        still = not self.moving()
        m = self.mode()
        if m == MODE_PP:
            if still and self.pending is None:
                sw |= 0x0400
            if self.ack:
                sw |= 0x1000
            if self.following_error:
                sw |= 0x2000
        elif m == MODE_HOMING:
            bits = self.homing_bits
            if bits == 0x0400 and not still:
                bits = 0
            if bits == 0x2400 and not still:
                bits = 0x2000
            sw |= bits
        elif still:
            sw |= 0x0400
        if self.internal_limit:
            sw |= 0x0800
        return sw

    def report(self):
        nmt = self.node.nmt.state
        if nmt != self.reported_nmt:
            self.log(f"nmt {nmt}")
            self.reported_nmt = nmt
        if self.fsa != self.reported_state:
            self.log(f"state {self.reported_state} -> {self.fsa}")
            self.reported_state = self.fsa

    # --- object dictionary hooks ----------------------------------------------------------

    def on_read(self, index, subindex, od):
        with self.lock:
            if index == 0x6041:
                return self.statusword()
            if index == 0x6064:
                return self.encoder()
            if index == 0x6061:
                return self.mode()
            if index == 0x606C:
                return int(round(self.vel * self.cpm))
            if index == 0x603F:
                return self.fault_code
            return None

    def on_write(self, index, subindex, od, data):
        """Validate (raise SdoAbortedError to refuse) and react; python-canopen stores after."""
        with self.lock:
            value = int.from_bytes(bytes(data), "little")
            if index in (0x1400, 0x1800) and subindex == 1:
                cur = self.uint(index, 1)
                if not cur & 0x80000000 and not value & 0x80000000 and value != cur:
                    raise SdoAbortedError(ABORT_INVALID_VALUE)
                if index == 0x1400:
                    self.subscribe_rpdo(None if value & 0x80000000 else value & 0x7FF)
            elif index in (0x1600, 0x1A00):
                if not self.uint(index - 0x200, 1) & 0x80000000:
                    raise SdoAbortedError(ABORT_DEVICE_STATE)
                if subindex == 0:
                    self.check_mapping(index, value)
                    self.log(f"mapping 0x{index:04X} count {value}")
                elif self.uint(index, 0) != 0:
                    raise SdoAbortedError(ABORT_DEVICE_STATE)
            elif index == 0x6060:
                m = int.from_bytes(bytes(data), "little", signed=True)
                if m not in (0, MODE_PP, MODE_HOMING):
                    raise SdoAbortedError(ABORT_INVALID_VALUE)
                self.store(0x6060, 0, data)
                self.on_mode()
            elif index == 0x6040:
                self.store(0x6040, 0, data)
                self.on_controlword(value)
            elif index == 0x2001 and value:
                self.inject_fault(value)

    def check_mapping(self, map_index, n):
        if n > 8:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        od = self.node.object_dictionary
        bits = 0
        for k in range(1, n + 1):
            v = self.uint(map_index, k)
            index, sub, length = v >> 16, (v >> 8) & 0xFF, v & 0xFF
            try:
                obj = od[index] if sub == 0 and isinstance(od[index], ODVariable) else od[index][sub]
            except (KeyError, TypeError):
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            if not obj.pdo_mappable or len(obj) != length:
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            # Direction: controlword/target/mode into the RPDO, the rest into the TPDO.
            rx = index in (0x6040, 0x607A, 0x6060)
            if rx != (map_index == 0x1600):
                raise SdoAbortedError(ABORT_NOT_MAPPABLE)
            bits += length
        if bits > 64:
            raise SdoAbortedError(ABORT_PDO_TOO_LONG)

    # --- NMT ------------------------------------------------------------------------------

    def on_nmt(self, can_id, data, timestamp):
        """Runs after python-canopen's own NMT handler (which only sets the state)."""
        if len(data) != 2 or data[1] not in (0, self.node.id):
            return
        with self.lock:
            cmd = data[0]
            if cmd in (0x81, 0x82):
                self.node.nmt.stop_heartbeat()
                if cmd == 0x81:
                    self.reset_application()
                for index in COMM_INDICES:
                    self.node.data_store.pop(index, None)
                self.rpdo_latched = None
                self.tpdo_syncs = 0
                self.last_tpdo = None
                self.subscribe_rpdo(self.uint(0x1400, 1) & 0x7FF)
                # Boot-up (state 0 sends it), then pre-operational with the default 0x1017.
                self.node.nmt.send_command(cmd)
                self.node.nmt.send_command(0x80)
                self.log("reset " + ("node" if cmd == 0x81 else "communication") + ", boot-up sent")
            if self.node.nmt.state != "OPERATIONAL":
                self.rpdo_latched = None
            self.report()

    def reset_application(self):
        self.vel = 0.0
        self.goal = None
        self.fsa = "SWITCH ON DISABLED"
        self.last_cw = 0
        self.ack = False
        self.pending = None
        self.halted = False
        self.homing = None
        self.homing_bits = 0x0400
        self.homed = False
        self.following_error = False
        self.fault_code = 0
        self.zero = self.pos
        self.last_target = 0
        for index in (0x6040, 0x6060, 0x607A, 0x1001):
            self.node.data_store.pop(index, None)

    # --- PDO and SYNC ---------------------------------------------------------------------

    def subscribe_rpdo(self, cob):
        if self.rpdo_cob is not None:
            self.network.unsubscribe(self.rpdo_cob, self.on_rpdo)
        self.rpdo_cob = cob
        if cob is not None:
            self.network.subscribe(cob, self.on_rpdo)

    def on_rpdo(self, can_id, data, timestamp):
        with self.lock:
            if self.node.nmt.state != "OPERATIONAL":
                return
            need = sum(length // 8 for _, _, length in self.mapping(0x1600))
            if len(data) < need:
                self.emcy(0x8210)
                return
            if self.uint(0x1400, 2) <= 240:
                self.rpdo_latched = bytes(data)
            else:
                self.apply_rpdo(bytes(data))

    def apply_rpdo(self, data):
        at = 0
        touched = set()
        for index, sub, length in self.mapping(0x1600):
            n = length // 8
            self.store(index, sub, data[at:at + n])
            touched.add(index)
            at += n
        if 0x6060 in touched:
            self.on_mode()
        if 0x6040 in touched:
            self.on_controlword(self.uint(0x6040))

    def tpdo_data(self):
        out = b""
        for index, sub, _ in self.mapping(0x1A00):
            out += self.node.get_data(index, sub)
        return out

    def send_tpdo(self):
        cob = self.uint(0x1800, 1)
        d = self.tpdo_data()
        self.network.send_message(cob & 0x7FF, d)
        self.last_tpdo = d

    def tpdo_valid(self):
        return not self.uint(0x1800, 1) & 0x80000000

    def on_sync(self, can_id, data, timestamp):
        with self.lock:
            if self.node.nmt.state != "OPERATIONAL":
                return
            self.syncs += 1
            if self.syncs % 1000 == 1:
                self.log(f"SYNC #{self.syncs}")
            if self.rpdo_latched is not None:
                d, self.rpdo_latched = self.rpdo_latched, None
                self.apply_rpdo(d)
            self.update()
            if self.tpdo_valid():
                ty = self.uint(0x1800, 2)
                if ty == 0:
                    self.send_tpdo()
                elif ty <= 240:
                    self.tpdo_syncs += 1
                    if self.tpdo_syncs >= ty:
                        self.tpdo_syncs = 0
                        self.send_tpdo()
            self.report()

    def event_tpdo(self):
        if self.node.nmt.state == "OPERATIONAL" and self.tpdo_valid() and self.uint(0x1800, 2) >= 254:
            if self.tpdo_data() != self.last_tpdo:
                self.send_tpdo()

    def emcy(self, code, manufacturer=b"\0\0\0\0\0"):
        if self.node.nmt.state == "STOPPED":
            return
        register = self.uint(0x1001)
        self.node.emcy.send(code, register, manufacturer)
        self.log(f"EMCY 0x{code:04X} register 0x{register:02X}")

    # --- CiA 402 --------------------------------------------------------------------------

    def on_mode(self):
        self.update()
        if self.homing is not None and self.mode() != MODE_HOMING:
            self.interrupt_homing()
        self.ack = False
        self.log(f"mode {self.mode()}")

    def brake(self, d):
        self.goal = None if self.vel == 0.0 else ("stop", d)

    def enter(self, to):
        frm = self.fsa
        self.fsa = to
        if to == "QUICK STOP ACTIVE":
            self.brake(max(self.speed(0x6085), 1e-6))
            self.pending = None
            if self.homing is not None:
                self.interrupt_homing()
        elif to != "OPERATION ENABLED" and frm in ("OPERATION ENABLED", "QUICK STOP ACTIVE"):
            self.vel = 0.0
            self.goal = None
            self.pending = None
            self.ack = False
            if self.homing is not None:
                self.interrupt_homing()
        if frm == "FAULT" and to == "SWITCH ON DISABLED":
            self.fault_code = 0
            self.following_error = False
            self.store(0x1001, 0, b"\0")
            self.emcy(0)

    def command(self, cw, prev):
        """The FSA command in a controlword (CiA 402 command coding)."""
        if cw & 0x80:
            return "fault reset" if not prev & 0x80 else None
        if not cw & 0x02:
            return "disable voltage"
        if not cw & 0x04:
            return "quick stop"
        if not cw & 0x01:
            return "shutdown"
        return "enable operation" if cw & 0x08 else "switch on"

    TRANSITIONS = {
        ("FAULT", "fault reset"): "SWITCH ON DISABLED",
        ("SWITCH ON DISABLED", "shutdown"): "READY TO SWITCH ON",
        ("READY TO SWITCH ON", "switch on"): "SWITCHED ON",
        ("READY TO SWITCH ON", "enable operation"): "OPERATION ENABLED",
        ("READY TO SWITCH ON", "disable voltage"): "SWITCH ON DISABLED",
        ("READY TO SWITCH ON", "quick stop"): "SWITCH ON DISABLED",
        ("SWITCHED ON", "enable operation"): "OPERATION ENABLED",
        ("SWITCHED ON", "shutdown"): "READY TO SWITCH ON",
        ("SWITCHED ON", "disable voltage"): "SWITCH ON DISABLED",
        ("SWITCHED ON", "quick stop"): "SWITCH ON DISABLED",
        ("OPERATION ENABLED", "switch on"): "SWITCHED ON",
        ("OPERATION ENABLED", "shutdown"): "READY TO SWITCH ON",
        ("OPERATION ENABLED", "disable voltage"): "SWITCH ON DISABLED",
        ("OPERATION ENABLED", "quick stop"): "QUICK STOP ACTIVE",
        ("QUICK STOP ACTIVE", "disable voltage"): "SWITCH ON DISABLED",
        ("QUICK STOP ACTIVE", "enable operation"): "OPERATION ENABLED",
    }

    def on_controlword(self, cw):
        self.update()
        prev, self.last_cw = self.last_cw, cw
        nxt = self.TRANSITIONS.get((self.fsa, self.command(cw, prev)))
        if nxt is not None:
            self.enter(nxt)
            if not self.moving():
                self.standstill()
        if self.fsa != "OPERATION ENABLED":
            self.refresh_ack(cw)
            self.report()
            return
        if cw & 0x0100:
            if not self.halted:
                self.halted = True
                self.brake(max(self.speed(0x6084), 1e-6))
                self.pending = None
                if self.homing is not None:
                    self.interrupt_homing()
                self.log("halt")
        else:
            self.halted = False
        rising = cw & 0x10 and not prev & 0x10
        falling = prev & 0x10 and not cw & 0x10
        m = self.mode()
        if m == MODE_PP and rising and not self.halted and not self.ack:
            self.accept_setpoint(cw)
        elif m == MODE_HOMING and rising and not self.halted:
            self.start_homing()
        elif m == MODE_HOMING and falling and self.homing is not None:
            self.interrupt_homing()
        self.refresh_ack(cw)
        self.report()

    def refresh_ack(self, cw):
        if not cw & 0x10 and self.pending is None:
            self.ack = False

    def accept_setpoint(self, cw):
        t = self.sint(0x607A)
        target = self.last_target + t if cw & 0x40 else t
        lo, hi = self.sint(0x607D, 1), self.sint(0x607D, 2)
        self.internal_limit = False
        if lo < hi and not lo <= target <= hi:
            target = min(max(target, lo), hi)
            self.internal_limit = True
        self.last_target = target
        self.ack = True
        phys = target / self.cpm + self.zero
        kind = "relative" if cw & 0x40 else "absolute"
        if self.moving() and not cw & 0x20:
            self.pending = phys
            self.log(f"set-point {target} ({kind}) buffered")
        else:
            self.move_to(phys)
            self.log(f"set-point {target} ({kind}){' immediately' if cw & 0x20 else ''}")

    def move_to(self, phys):
        self.goal = ("to", phys, self.speed(0x6081), max(self.speed(0x6083), 1e-6),
                     max(self.speed(0x6084), 1e-6))

    def start_homing(self):
        method = self.sint(0x6098)
        offset = self.sint(0x607C) / self.cpm
        if method in (35, 37):
            self.zero = self.pos - offset
            self.finish_homing()
            return
        fast, slow = self.speed(0x6099, 1), self.speed(0x6099, 2)
        if not 1 <= method <= 34 or fast <= 0 or slow <= 0:
            self.homing_bits = 0x2400
            self.log(f"homing error (method {method})")
            return
        self.homing_bits = 0
        a = max(self.speed(0x609A), 1e-6)
        approach = 0.5
        if abs(self.pos) > approach:
            self.homing = "search"
            self.goal = ("to", math.copysign(approach, self.pos), fast, a, a)
        else:
            self.homing = "approach"
            self.goal = ("to", 0.0, slow, a, a)
        self.log(f"homing started (method {method})")

    def finish_homing(self):
        self.homing = None
        self.homing_bits = 0x1400
        self.homed = True
        self.last_target = self.encoder()
        self.log(f"homing attained, position {self.encoder()}")

    def interrupt_homing(self):
        self.homing = None
        self.homing_bits = 0x0400
        if self.goal is not None:
            self.brake(max(self.speed(0x609A), 1e-6))
        self.log("homing interrupted")

    def arrived(self):
        if self.homing == "search":
            self.homing = "approach"
            a = max(self.speed(0x609A), 1e-6)
            self.goal = ("to", 0.0, self.speed(0x6099, 2), a, a)
            return
        if self.homing == "approach":
            self.zero = -self.sint(0x607C) / self.cpm
            self.finish_homing()
            return
        if self.pending is not None:
            p, self.pending = self.pending, None
            self.move_to(p)
            self.refresh_ack(self.last_cw)
            return
        self.log(f"target reached, position {self.encoder()}")

    def standstill(self):
        if self.fsa == "FAULT REACTION ACTIVE":
            self.fsa = "FAULT"
        elif self.fsa == "QUICK STOP ACTIVE" and 0 <= self.sint(0x605A) <= 4:
            self.fsa = "SWITCH ON DISABLED"

    def step(self, dt):
        """One motion step (the same discrete-time trapezoid as the Rust twin)."""
        g = self.goal
        if g is None:
            return False
        if g[0] == "stop":
            dv = g[1] * dt
            if abs(self.vel) <= dv:
                self.vel = 0.0
                self.goal = None
                return True
            self.vel -= math.copysign(dv, self.vel)
            self.pos += self.vel * dt
            return False
        _, target, v, a, d = g
        s = target - self.pos
        if abs(s) < 1e-12:
            self.pos, self.vel, self.goal = target, 0.0, None
            return True
        h = d * dt
        braking = h * (math.sqrt(0.25 + 2.0 * abs(s) / (h * dt)) - 0.5)
        want = math.copysign(min(v, braking), s)
        speeding_up = abs(want) > abs(self.vel) and want * self.vel >= 0
        limit = (a if speeding_up else d) * dt
        self.vel += max(-limit, min(limit, want - self.vel))
        nxt = self.pos + self.vel * dt
        if (target - nxt) * s <= 0:
            self.pos, self.vel, self.goal = target, 0.0, None
            return True
        self.pos = nxt
        return False

    def update(self):
        now = time.monotonic()
        t = self.last_update
        while t < now:
            dt = min(now - t, 0.001)
            t += dt
            if self.step(dt):
                self.arrived()
        self.last_update = max(self.last_update, now)
        if not self.moving():
            self.standstill()

    def tick(self):
        with self.lock:
            self.update()
            self.event_tpdo()
            self.report()

    def inject_fault(self, code):
        self.update()
        self.fault_code = code
        self.following_error = code == 0x8611
        hi = code >> 8
        if 0x21 <= hi <= 0x23:
            cls = 0x02
        elif 0x30 <= hi <= 0x33:
            cls = 0x04
        elif 0x40 <= hi <= 0x44:
            cls = 0x08
        elif hi == 0x81:
            cls = 0x10
        elif 0x50 <= hi <= 0x8F:
            cls = 0x20
        else:
            cls = 0x80
        self.store(0x1001, 0, bytes([0x01 | cls]))
        self.pending = None
        self.ack = False
        if self.homing is not None:
            self.homing = None
            self.homing_bits = 0x2400
        self.fsa = "FAULT REACTION ACTIVE"
        self.brake(max(self.speed(0x6085), 1e-6))
        self.emcy(code, b"\x01\x02\x03\x04\x05")
        self.update()
        self.report()


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("port", type=int)
    p.add_argument("node_id", type=int)
    p.add_argument("--feed-mm", type=float, default=5.0)
    p.add_argument("--shaft-revs", type=int, default=1)
    p.add_argument("--increments", type=int, default=131072)
    p.add_argument("--motor-revs", type=int, default=1)
    p.add_argument("--start-mm", type=float, default=2.0)
    p.add_argument("--timeout", type=float, default=0.0)
    p.add_argument("--channel", default="239.74.163.2")
    p.add_argument("--heartbeat-ms", type=int, default=0)
    args = p.parse_args()
    if not 1 <= args.node_id <= 127:
        p.error("node id must be 1..127")
    if args.feed_mm <= 0 or min(args.shaft_revs, args.increments, args.motor_revs) <= 0:
        p.error("feed, revolutions and increments must be > 0")

    stop = threading.Event()

    def on_signal(*_):
        if stop.is_set():
            os._exit(1)  # a second signal: leave at once
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    network = canopen.Network()
    network.connect(interface="udp_multicast", channel=args.channel, port=args.port,
                    receive_own_messages=False)
    node = canopen.LocalNode(args.node_id, build_od(args.node_id, args))
    network.add_node(node)
    drive = Drive(node, network, args)
    node.add_read_callback(drive.on_read)
    node.add_write_callback(drive.on_write)
    network.subscribe(0, drive.on_nmt)
    network.subscribe(0x80, drive.on_sync)
    with drive.lock:
        drive.subscribe_rpdo(0x200 + args.node_id)
        drive.log(f"drive node {args.node_id} on {args.channel}:{args.port}, "
                  f"{drive.cpm:.4f} increments/mm, stage at {args.start_mm} mm")
        # Power-on: boot-up, then pre-operational.
        node.nmt.send_command(0x82)
        node.nmt.send_command(0x80)
        drive.report()

    deadline = time.monotonic() + args.timeout if args.timeout > 0 else None
    try:
        while not stop.is_set():
            if deadline is not None and time.monotonic() >= deadline:
                drive.log("timeout")
                break
            drive.tick()
            stop.wait(0.002)
    finally:
        with drive.lock:
            node.nmt.stop_heartbeat()
            drive.log("exit")
        network.disconnect()
    return 0


if __name__ == "__main__":
    code = main()
    try:
        sys.stdout.flush()
    except OSError:
        pass
    # Leave without waiting for python-can's helper threads (periodic senders) to wind down.
    os._exit(code)
