#!/usr/bin/env python3
"""An independent PSD I/O module that misbehaves on command, for axiscomp's field-link tests
(issue 18): a pymodbus (>= 3.12) server holding the generic I/O map's block with all three
beams on (spots near the PSD centres), driven by one command per line on stdin:

    ok               serve normally (restarts the pymodbus server if it was stopped)
    once CODE        answer the next read with Modbus exception CODE, then normally
    exception CODE   answer every read with exception CODE until the next command
    hang             stop pymodbus; accept TCP connections on the same port, never answer
    outage           stop everything: connections closed, nothing listening

Each command is acknowledged with one line "ok <command>" on stdout once in effect. The first
line on stdout is JSON: {"port": P, "registers": [...], "block_start": S, "unit_id": U}.

Usage: pymodbus_faults.py --port PORT [--map plc-maps/io/generic.toml]
Run by the Rust test `interop_field_links_tell_the_truth` (tests/it/links.rs) via
tests/interop/links.sh.
"""

import asyncio
import json
import sys

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus_io import encode, port_and_map

# X, Y, SUM volts per PSD: every beam on, spots within 0.1 mm of the centres.
VOLTS = [(0.01, -0.02, 5.0), (0.0, 0.01, 4.5), (-0.01, 0.0, 4.0)]


class Module:
    def __init__(self, port, map_, regs):
        self.port = port
        self.map = map_
        self.regs = regs
        self.mode = ("ok", 0)
        self.server = None
        self.hung = None
        self.hung_conns = []

    async def action(self, function_code, start_address, address, count, registers, values):
        mode, code = self.mode
        if mode == "once":
            self.mode = ("ok", 0)
            return ExcCodes(code)
        if mode == "exception":
            return ExcCodes(code)
        return None

    async def start_modbus(self):
        if self.server is not None:
            return
        block = SimData(address=self.map["block_start"], values=self.regs, datatype=DataType.REGISTERS)
        device = SimDevice(id=self.map["unit_id"], simdata=[block], action=self.action)
        self.server = ModbusTcpServer(context=device, address=("127.0.0.1", self.port))
        await self.server.serve_forever(background=True)

    async def stop_modbus(self):
        if self.server is not None:
            await self.server.shutdown()
            self.server = None
            await asyncio.sleep(0.05)

    async def start_hung(self):
        async def swallow(reader, writer):
            self.hung_conns.append(writer)
            while await reader.read(4096):
                pass

        self.hung = await asyncio.start_server(swallow, "127.0.0.1", self.port, reuse_address=True)

    async def stop_hung(self):
        if self.hung is not None:
            self.hung.close()
            for w in self.hung_conns:
                w.close()
            self.hung_conns = []
            await self.hung.wait_closed()
            self.hung = None

    async def command(self, line):
        words = line.split()
        if not words:
            return
        cmd = words[0]
        if cmd in ("once", "exception"):
            self.mode = (cmd, int(words[1], 0))
        elif cmd == "ok":
            self.mode = ("ok", 0)
            await self.stop_hung()
            await self.start_modbus()
        elif cmd == "hang":
            await self.stop_modbus()
            await self.start_hung()
        elif cmd == "outage":
            await self.stop_modbus()
            await self.stop_hung()
        else:
            sys.exit(f"pymodbus_faults.py: unknown command {line!r}")
        print(f"ok {line}", flush=True)


async def main():
    port, map_ = port_and_map()
    if map_["register"] != "input":
        sys.exit("pymodbus_faults.py: maps on input registers only")
    regs, _, _ = encode(map_, VOLTS)
    module = Module(port, map_, regs)
    await module.start_modbus()
    print(
        json.dumps(
            {
                "port": port,
                "registers": regs,
                "block_start": map_["block_start"],
                "unit_id": map_["unit_id"],
            }
        ),
        flush=True,
    )
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    while line := await reader.readline():
        await module.command(line.decode().strip())


if __name__ == "__main__":
    asyncio.run(main())
