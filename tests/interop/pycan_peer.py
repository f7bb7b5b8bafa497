#!/usr/bin/env python3
"""An independent python-can peer on a udp_multicast bus, for axiscomp's interop tests.

    pycan_peer.py --port P [--group G] [--iface 127.0.0.1] echo N
        Print every frame heard (one "RX" line each), answer it with the same frame at
        identifier + 1, exit after N frames.
    pycan_peer.py --port P [--group G] [--iface 127.0.0.1] script
        Send the scripted sequence SCRIPT below, then exit.

Prints "READY" once the bus is open. Frame lines are `RX <frame>` in candump notation:
`123#0102`, `1ABCDEF0#FF`, `701#R1` (3 hex digits: standard id, 8: extended).

python-can's UdpMulticastBus picks the multicast interface by routing and joins the group on
INADDR_ANY; the rig here lives on loopback, so after opening the bus the peer also joins the
group on --iface and sends through it (IP_MULTICAST_IF). If the host has no multicast route
at all, joining on INADDR_ANY fails inside python-can; the peer then retries with the join
address pointed at --iface. python-can hears its own messages (multicast loopback); the peer
drops the ones it sent itself.
"""
import argparse
import socket
import struct
import sys
import time

import can

SCRIPT = [
    can.Message(arbitration_id=0x181, is_extended_id=False, data=[1, 2, 3, 4, 5, 6, 7, 8]),
    can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True, data=[0xFF]),
    can.Message(arbitration_id=0x701, is_extended_id=False, is_remote_frame=True, dlc=1),
    can.Message(arbitration_id=0x000, is_extended_id=False, data=[]),
    can.Message(arbitration_id=0x12345, is_extended_id=True, is_remote_frame=True, dlc=8),
    can.Message(arbitration_id=0x7FF, is_extended_id=False, data=[0xDE, 0xAD, 0xBE, 0xEF]),
]


def notation(m: can.Message) -> str:
    ident = f"{m.arbitration_id:08X}" if m.is_extended_id else f"{m.arbitration_id:03X}"
    if m.is_remote_frame:
        return f"{ident}#R{m.dlc}"
    return f"{ident}#{bytes(m.data).hex().upper()}"


def key(m: can.Message):
    return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.dlc, bytes(m.data))


def open_bus(group: str, port: int, iface: str) -> can.BusABC:
    try:
        bus = can.Bus(interface="udp_multicast", channel=group, port=port)
    except can.CanInitializationError:
        # No route for the group: make python-can's INADDR_ANY join use the loopback address.
        saved = socket.INADDR_ANY
        socket.INADDR_ANY = struct.unpack("@I", socket.inet_aton(iface))[0]
        try:
            bus = can.Bus(interface="udp_multicast", channel=group, port=port)
        finally:
            socket.INADDR_ANY = saved
    sock = bus._multicast._socket
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(iface))
    try:
        sock.setsockopt(
            socket.IPPROTO_IP,
            socket.IP_ADD_MEMBERSHIP,
            socket.inet_aton(group) + socket.inet_aton(iface),
        )
    except OSError:
        pass  # already a member there (the fallback above joined on iface)
    return bus


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--group", default="239.74.163.2")
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--iface", default="127.0.0.1")
    ap.add_argument("--idle", type=float, default=60.0, help="give up after this many idle seconds")
    sub = ap.add_subparsers(dest="mode", required=True)
    echo = sub.add_parser("echo")
    echo.add_argument("count", type=int)
    sub.add_parser("script")
    args = ap.parse_args()

    bus = open_bus(args.group, args.port, args.iface)
    own = []  # frames we sent and have not heard back yet
    try:
        print("READY", flush=True)
        if args.mode == "script":
            for m in SCRIPT:
                bus.send(m)
            return 0
        done = 0
        deadline = time.monotonic() + args.idle
        while done < args.count:
            m = bus.recv(timeout=0.5)
            if m is None:
                if time.monotonic() > deadline:
                    print(f"TIMEOUT after {done} frames", flush=True)
                    return 1
                continue
            if key(m) in own:
                own.remove(key(m))
                continue
            deadline = time.monotonic() + args.idle
            print(f"RX {notation(m)}", flush=True)
            reply = can.Message(
                arbitration_id=m.arbitration_id + 1,
                is_extended_id=m.is_extended_id,
                is_remote_frame=m.is_remote_frame,
                dlc=m.dlc,
                data=None if m.is_remote_frame else m.data,
            )
            own.append(key(reply))
            bus.send(reply)
            done += 1
        return 0
    finally:
        bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
