#!/usr/bin/env python3
"""An independent Modbus TCP peer for axiscomp's interop tests: a pymodbus (3.x) server that
plays the PSD I/O module with known registers laid out per an I/O map (generic.toml).

It reads the map itself (tomllib), picks known voltages, encodes them as the map says
(signed 16-bit counts, volts_per_count, volts_offset), computes what axiscomp must decode from
them (spots in mm, SUMs in V, no spot below the SUM threshold), prints that as one JSON line
on stdout and then serves the registers until killed:

    {"registers": [...], "spots": [[x, y] | null, ...], "sums": [...], "unit_id": 1, ...}

Usage: pymodbus_io.py --port PORT [--map plc-maps/io/generic.toml]

Run by the Rust test `interop_pymodbus_io_frames` (tests/it/acquire.rs) via
tests/interop/modbus.sh; only conditioned maps with 16-bit integer channels are supported here.
"""

import argparse
import asyncio
import json
import sys
import tomllib

# Known voltages per PSD: (X, Y, SUM). PSD3's SUM is below the threshold: beam blocked.
VOLTS = [(1.234, -2.5, 5.0), (-0.75, 3.125, 4.2), (0.1, 0.2, 0.05)]


def encode(map_, volts):
    """Registers of the block and the expected decoding, computed independently of axiscomp."""
    d = map_.get("defaults", {})
    length = map_["block_length"]
    regs = [0] * length
    spots, sums = [], []
    for psd, (vx, vy, vs) in zip(map_["psd"], volts):
        decoded = {}
        for key, v in (("x", vx), ("y", vy), ("sum", vs)):
            ch = psd[key]
            ty = ch.get("type", d.get("type"))
            order = ch.get("word_order", d.get("word_order", "ABCD"))
            if ty not in ("i16", "u16") or order not in ("ABCD", "CDAB"):
                sys.exit(f"pymodbus_io.py: only 16-bit big-endian channels, got {ty} {order}")
            vpc = ch.get("volts_per_count", d.get("volts_per_count"))
            voff = ch.get("volts_offset", d.get("volts_offset", 0.0))
            counts = int(round((v - voff) / vpc))
            regs[ch["register"]] = counts & 0xFFFF
            decoded[key] = counts * vpc + voff
        x = psd["gain_x_mm_per_v"] * decoded["x"] + psd.get("offset_x_mm", 0.0)
        y = psd["gain_y_mm_per_v"] * decoded["y"] + psd.get("offset_y_mm", 0.0)
        lit = decoded["sum"] >= map_["sum_threshold_v"]
        spots.append([x, y] if lit else None)
        sums.append(decoded["sum"])
    return regs, spots, sums


def context(unit, start, regs, holding):
    """A server context for whichever pymodbus 3.x is installed."""
    try:  # pymodbus >= 3.12: SimData/SimDevice, 0-based addresses as on the wire
        from pymodbus.simulator import DataType, SimData, SimDevice

        block = SimData(address=start, values=regs, datatype=DataType.REGISTERS)
        return SimDevice(id=unit, simdata=[block])
    except ImportError:
        pass
    from pymodbus.datastore import ModbusSequentialDataBlock, ModbusServerContext

    try:  # 3.10, 3.11
        from pymodbus.datastore import ModbusDeviceContext as Device

        kw = "devices"
    except ImportError:  # 3.0 .. 3.9
        from pymodbus.datastore import ModbusSlaveContext as Device

        kw = "slaves"
    # These versions add 1 to the request address before looking up a sequential block.
    block = ModbusSequentialDataBlock(start + 1, regs)
    other = ModbusSequentialDataBlock(0, [0] * 2)
    dev = Device(hr=block if holding else other, ir=other if holding else block)
    return ModbusServerContext(**{kw: {unit: dev}, "single": False})


def port_and_map():
    """The --port and the I/O map (--map, conditioned maps only) from the command line; also
    used by pymodbus_faults.py."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--map", default="plc-maps/io/generic.toml")
    args = ap.parse_args()
    with open(args.map, "rb") as f:
        map_ = tomllib.load(f)
    if map_["mode"] != "conditioned":
        sys.exit(f"{ap.prog}: conditioned maps only")
    return args.port, map_


async def main():
    port, map_ = port_and_map()
    regs, spots, sums = encode(map_, VOLTS)
    print(
        json.dumps(
            {
                "registers": regs,
                "spots": spots,
                "sums": sums,
                "unit_id": map_["unit_id"],
                "block_start": map_["block_start"],
            }
        ),
        flush=True,
    )
    from pymodbus.server import StartAsyncTcpServer

    ctx = context(map_["unit_id"], map_["block_start"], regs, map_["register"] == "holding")
    await StartAsyncTcpServer(context=ctx, address=("127.0.0.1", port))


if __name__ == "__main__":
    asyncio.run(main())
