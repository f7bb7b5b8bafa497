#!/usr/bin/env python3
"""Independent Modbus TCP peers (pymodbus 3.x, 3.12+ SimDevice API) for axiscomp's PLC table
protocol (plc-maps/README.md). Nothing here uses axiscomp's code: the script reads the CNC
map itself (tomllib) and computes every register from the table's values and the map.

  plc  --port P --map M --values-file F --start-mm S --interval-mm I --kind K --axis A
       --base-axis B --sequence Q [--word-order ORDER]
      Plays the PLC side of the push handshake: ready = 1, a heartbeat that counts up on every
      read of it, status idle. It computes the registers axiscomp must write (header and
      payload, per word order, resolution, sign and CRC byte order of the map; ORDER overrides
      every field's word order) and, when the commit word arrives, compares what it received
      register by register. All equal, the CRC it computes over the received payload equal to
      the received header CRC, and the commit equal to the sequence: it echoes "accepted" and
      makes the sequence active. Otherwise "rejected" with code 1 (CRC), 2 (sequence) or
      1000 + the offset (from the header's first register) of the first register that differs.
      Prints "listening" then serves until killed; a mismatch is described on stderr.

  pull --port P --map M
      Plays the PLC pulling from axiscomp's pull server: reads the published sequence, the
      header and the payload (at most 120 registers per read), checks the CRC, then tries
      three writes that must be refused (into the header, onto the published sequence, and
      into the acknowledgement range from this peer, which the test does not allow to write),
      and prints one JSON line: {"published", "points", "crc_ok", "values_um",
      "write_header", "write_published", "write_ack_not_writer"} (the writes' exception codes,
      or 0 if a write was accepted).

Run by the ignored Rust tests in tests/it/plc.rs via tests/interop/plc.sh.
"""

import argparse
import asyncio
import json
import math
import struct
import sys
import tomllib
import zlib

UNITS_MM = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "nm": 1e-6}
PLC_FIELDS = ["plc_ready", "plc_heartbeat", "status", "error_code", "status_sequence", "active_sequence"]
HEADER_FIELDS = ["kind", "axis", "base_axis", "direction", "points", "unit", "start", "interval", "sequence", "crc"]


def round_half_away(x):
    """Round to the nearest integer, halves away from zero (as Rust's f64::round)."""
    return int(math.floor(x + 0.5)) if x >= 0 else -int(math.floor(-x + 0.5))


def value_bytes(ty, value):
    """A value's big-endian bytes A B (C D)."""
    fmt = {"u16": ">H", "i16": ">h", "u32": ">I", "i32": ">i", "f32": ">f"}[ty]
    return struct.pack(fmt, value)


def to_regs(ty, order, value):
    """Registers of `value` as `ty` in word order `order` (ABCD, CDAB, BADC, DCBA)."""
    b = value_bytes(ty, value)
    if len(b) == 2:
        a, bb = b
        return [(bb << 8 | a) if order in ("BADC", "DCBA") else (a << 8 | bb)]
    a, bb, c, d = b
    return {
        "ABCD": [a << 8 | bb, c << 8 | d],
        "CDAB": [c << 8 | d, a << 8 | bb],
        "BADC": [bb << 8 | a, d << 8 | c],
        "DCBA": [d << 8 | c, bb << 8 | a],
    }[order]


def from_regs(ty, order, regs):
    """The value of `ty` held in `regs` in word order `order`."""
    if ty in ("u16", "i16"):
        r = regs[0]
        hi, lo = (r & 0xFF, r >> 8) if order in ("BADC", "DCBA") else (r >> 8, r & 0xFF)
        return struct.unpack(">H" if ty == "u16" else ">h", bytes([hi, lo]))[0]
    r0, r1 = regs[0], regs[1]
    w = {"ABCD": (r0, r1), "CDAB": (r1, r0), "BADC": (r0, r1), "DCBA": (r1, r0)}[order]
    swap = order in ("BADC", "DCBA")
    bs = []
    for x in w:
        bs += [x & 0xFF, x >> 8] if swap else [x >> 8, x & 0xFF]
    fmt = {"u32": ">I", "i32": ">i", "f32": ">f"}[ty]
    return struct.unpack(fmt, bytes(bs))[0]


class Map:
    """The parts of a CNC map this script needs, read with tomllib."""

    def __init__(self, path, order_override=None):
        with open(path, "rb") as f:
            m = tomllib.load(f)
        self.unit_id = m["unit_id"]
        default = m.get("defaults", {}).get("word_order", "ABCD")
        self.fields = {}
        for sect, names in (("handshake", PLC_FIELDS + ["commit"]), ("header", HEADER_FIELDS)):
            for n in names:
                f = dict(m[sect][n])
                f["order"] = order_override or f.get("word_order", default)
                f["register"] = f.get("register", "holding")
                f["words"] = 1 if f["type"] in ("u16", "i16") else 2
                f["mm"] = f.get("scale", 1.0) * UNITS_MM.get(f.get("unit", "mm"), 1.0)
                self.fields[n] = f
        p = m["payload"]
        self.payload = {
            "address": p["address"],
            "type": p["type"],
            "order": order_override or p.get("word_order", default),
            "words": 1 if p["type"] == "i16" else 2,
            "um": p["scale"] * UNITS_MM[p["unit"]] * 1e3,
            "sign": -1.0 if p["sign"] == "correction" else 1.0,
            "crc_fmt": ("<" if p["crc_bytes"] == "little-endian" else ">") + ("h" if p["type"] == "i16" else "i"),
        }
        self.max_points = m["limits"]["max_points"]

    def regs_of(self, name, value):
        f = self.fields[name]
        return to_regs(f["type"], f["order"], value)


def expected(m, a):
    """Every header and payload register axiscomp must write: {address: value}."""
    vals = [float(x) for x in open(a.values_file).read().split(",")]
    p = m.payload
    counts = [round_half_away(p["sign"] * v / p["um"]) for v in vals]
    crc = zlib.crc32(b"".join(struct.pack(p["crc_fmt"], c) for c in counts)) & 0xFFFFFFFF
    unit_nm = round(p["um"] * 1000)
    hv = {
        "kind": a.kind,
        "axis": a.axis,
        "base_axis": a.base_axis,
        "direction": 0,
        "points": len(vals),
        "unit": unit_nm,
        "start": round_half_away(a.start_mm / m.fields["start"]["mm"]),
        "interval": round_half_away(a.interval_mm / m.fields["interval"]["mm"]),
        "sequence": a.sequence,
        "crc": crc,
    }
    regs = {}
    for n in HEADER_FIELDS:
        for k, r in enumerate(m.regs_of(n, hv[n])):
            regs[m.fields[n]["address"] + k] = r
    for i, c in enumerate(counts):
        for k, r in enumerate(to_regs(p["type"], p["order"], c)):
            regs[p["address"] + i * p["words"] + k] = r
    return regs


async def run_plc(a):
    from pymodbus.constants import ExcCodes
    from pymodbus.server import StartAsyncTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    m = Map(a.map, a.word_order)
    want = expected(m, a)
    first_header = min(m.fields[n]["address"] for n in HEADER_FIELDS)
    state = {"plc_ready": 1, "plc_heartbeat": 0, "status": 0, "error_code": 0,
             "status_sequence": 0, "active_sequence": 0}
    holding_end = max([m.payload["address"] + 2 * m.max_points * m.payload["words"]] +
                      [f["address"] + f["words"] for f in m.fields.values() if f["register"] == "holding"])
    holding_start = min(f["address"] for f in m.fields.values() if f["register"] == "holding")
    input_end = max([1] + [f["address"] + f["words"] for f in m.fields.values() if f["register"] == "input"])

    def put_status(regs, start, kind):
        for n in PLC_FIELDS:
            f = m.fields[n]
            if f["register"] != kind:
                continue
            for k, r in enumerate(m.regs_of(n, state[n])):
                regs[f["address"] - start + k] = r

    def commit(regs, start, seq):
        get = lambda addr: regs[addr - start]
        problem = None
        for addr in sorted(want):
            if get(addr) != want[addr]:
                problem = (1000 + addr - first_header,
                           f"register {addr}: received 0x{get(addr):04X}, expected 0x{want[addr]:04X}")
                break
        if problem is None:
            p = m.payload
            hdr = lambda n: from_regs(m.fields[n]["type"], m.fields[n]["order"],
                                      [get(m.fields[n]["address"] + k) for k in range(m.fields[n]["words"])])
            n_pts = hdr("points")
            counts = [from_regs(p["type"], p["order"],
                                [get(p["address"] + i * p["words"] + k) for k in range(p["words"])])
                      for i in range(n_pts)]
            crc = zlib.crc32(b"".join(struct.pack(p["crc_fmt"], c) for c in counts)) & 0xFFFFFFFF
            if crc != hdr("crc"):
                problem = (1, f"CRC 0x{crc:08X} of the received payload != header 0x{hdr('crc'):08X}")
            elif seq != a.sequence or hdr("sequence") != seq:
                problem = (2, f"commit {seq}, header {hdr('sequence')}, expected {a.sequence}")
        state["status_sequence"] = seq
        if problem is None:
            state.update(status=2, error_code=0, active_sequence=seq)
        else:
            state.update(status=3, error_code=min(problem[0], 0xFFFF))
            print(f"plc_peer.py: rejected: {problem[1]}", file=sys.stderr, flush=True)

    async def action(fc, start, address, count, regs, values):
        kind = "input" if fc == 4 else "holding"
        if values is None:
            state["plc_heartbeat"] = (state["plc_heartbeat"] + 1) & 0xFFFF
            put_status(regs, start, kind)
            return None
        # Writes: only the header, the payload and the commit word.
        c = m.fields["commit"]
        plc_regs = {m.fields[n]["address"] + k for n in PLC_FIELDS if m.fields[n]["register"] == "holding"
                    for k in range(m.fields[n]["words"])}
        if any(address + k in plc_regs for k in range(count)):
            return ExcCodes.ILLEGAL_ADDRESS
        if address == c["address"] and count == c["words"]:
            seq = from_regs(c["type"], c["order"], list(values))
            commit(regs, start, seq)
            put_status(regs, start, "holding")
        return None

    hr = [SimData(holding_start, values=[0] * (holding_end - holding_start), datatype=DataType.REGISTERS)]
    ir = [SimData(0, values=[0] * input_end, datatype=DataType.REGISTERS)]
    bits = lambda: [SimData(0, values=[False] * 16, datatype=DataType.BITS)]
    device = SimDevice(id=m.unit_id, simdata=(bits(), bits(), hr, ir), action=action)
    print("listening", flush=True)
    await StartAsyncTcpServer(context=device, address=("127.0.0.1", a.port))


def run_pull(a):
    from pymodbus.client import ModbusTcpClient

    m = Map(a.map)
    cl = ModbusTcpClient("127.0.0.1", port=a.port)
    if not cl.connect():
        sys.exit("plc_peer.py: cannot connect to the pull server")
    unit = m.unit_id

    def read(addr, count):
        out = []
        while count > 0:
            n = min(count, 120)
            r = cl.read_holding_registers(addr, count=n, device_id=unit)
            if r.isError():
                sys.exit(f"plc_peer.py: read {addr}+{n} failed: {r}")
            out += r.registers
            addr += n
            count -= n
        return out

    def field(n):
        f = m.fields[n]
        return from_regs(f["type"], f["order"], read(f["address"], f["words"]))

    published = field("commit")
    points = field("points")
    p = m.payload
    raw = read(p["address"], points * p["words"])
    counts = [from_regs(p["type"], p["order"], raw[i * p["words"]:(i + 1) * p["words"]]) for i in range(points)]
    crc = zlib.crc32(b"".join(struct.pack(p["crc_fmt"], c) for c in counts)) & 0xFFFFFFFF

    def write_code(addr, values):
        r = cl.write_registers(addr, values, device_id=unit)
        return r.exception_code if r.isError() else 0

    report = {
        "published": published,
        "points": points,
        "crc_ok": crc == field("crc") and field("sequence") == published,
        "values_um": [p["sign"] * c * p["um"] for c in counts],
        "write_header": write_code(m.fields["kind"]["address"], [9]),
        "write_published": write_code(m.fields["commit"]["address"], [0, 1]),
        "write_ack_not_writer": write_code(m.fields["status"]["address"], [2]),
    }
    cl.close()
    print(json.dumps(report), flush=True)


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="mode", required=True)
    p = sub.add_parser("plc")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--map", required=True)
    p.add_argument("--values-file", required=True)
    p.add_argument("--start-mm", type=float, required=True)
    p.add_argument("--interval-mm", type=float, required=True)
    p.add_argument("--kind", type=int, required=True)
    p.add_argument("--axis", type=int, required=True)
    p.add_argument("--base-axis", type=int, required=True)
    p.add_argument("--sequence", type=int, required=True)
    p.add_argument("--word-order", choices=["ABCD", "CDAB", "BADC", "DCBA"])
    q = sub.add_parser("pull")
    q.add_argument("--port", type=int, required=True)
    q.add_argument("--map", required=True)
    a = ap.parse_args()
    if a.mode == "plc":
        asyncio.run(run_plc(a))
    else:
        run_pull(a)


if __name__ == "__main__":
    main()
