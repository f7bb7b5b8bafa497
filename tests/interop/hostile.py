#!/usr/bin/env python3
"""Hostile peers against a running axiscomp service (issue 18), driven by tests/interop/hostile.sh.

    hostile.py control SOCKET PID   lines that are not JSON or not text, a 20 MB line, 2000
                                    connections held for 3 s; the service's peak RSS meanwhile
    hostile.py pull HOST:PORT UNIT PID
                                    1000 idle connections, a slow writer, an MBAP length that
                                    lies, an unknown unit id, a write outside the acknowledgement
                                    range, a peer not on the allow-list (from 127.0.0.2)

Each prints one JSON line of figures and exits non-zero (with the reason) when the service
misbehaves. Standard library only.
"""

import json
import socket
import struct
import sys
import time


def rss_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def fail(msg):
    print(f"hostile.py: FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def reply_line(s, timeout=5.0):
    s.settimeout(timeout)
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    return buf.decode(errors="replace")


def control(path, pid):
    out = {"rss_before_kib": rss_kib(pid)}

    def conn():
        s = socket.socket(socket.AF_UNIX)
        s.connect(path)
        return s

    # A line that is not JSON, then one that is not UTF-8 text: an error each, same connection.
    s = conn()
    s.sendall(b"hello\n")
    r = json.loads(reply_line(s))
    if r.get("ok") is not False or "JSON" not in r.get("error", ""):
        fail(f"non-JSON line: {r}")
    s.sendall(b"\xff\xfe\n")
    r = json.loads(reply_line(s))
    if r.get("ok") is not False or "not UTF-8" not in r.get("error", ""):
        fail(f"non-UTF-8 line: {r}")
    s.sendall(b'{"cmd":"status"}\n')
    if json.loads(reply_line(s)).get("ok") is not True:
        fail("status after the bad lines")
    s.close()
    out["bad_lines"] = "error replies"

    # A 20 MB line: refused after 64 KiB, the connection closed.
    s = conn()
    t0 = time.monotonic()
    sent = 0
    block = b"x" * 65536
    try:
        while sent < 20 * 1024 * 1024:
            s.sendall(block)
            sent += len(block)
    except (BrokenPipeError, ConnectionResetError):
        pass
    r = reply_line(s)
    if "longer than 65536 bytes" not in r:
        fail(f"20 MB line: {r!r}")
    out["long_line"] = {"sent_bytes_before_close": sent, "s": round(time.monotonic() - t0, 2)}
    s.close()

    # 2000 connections held for 3 s: beyond the limit each gets a refusal line and is closed.
    conns, refused = [], 0
    peak = rss_kib(pid)
    for _ in range(2000):
        try:
            conns.append(conn())
        except OSError:
            refused += 1
    time.sleep(0.5)
    for c in conns:
        c.setblocking(False)
        try:
            data = c.recv(4096)
            if b"control connections open" in data:
                refused += 1
        except BlockingIOError:
            pass
        except OSError:
            refused += 1
    t_end = time.monotonic() + 3
    while time.monotonic() < t_end:
        peak = max(peak, rss_kib(pid))
        time.sleep(0.1)
    for c in conns:
        c.close()
    time.sleep(1)
    out["connections"] = {"tried": 2000, "refused": refused, "admitted": 2000 - refused}
    out["rss_peak_kib"] = peak
    out["rss_after_kib"] = rss_kib(pid)
    if refused < 2000 - 64:
        fail(f"only {refused} of 2000 connections refused (limit 64)")
    # Serves normally afterwards.
    s = conn()
    s.sendall(b'{"cmd":"status"}\n')
    if json.loads(reply_line(s)).get("ok") is not True:
        fail("status after the attack")
    s.close()
    print(json.dumps(out), flush=True)


def mbap(tid, unit, pdu, length=None):
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1 if length is None else length, unit) + pdu


def request(addr, adu, timeout=2.0, src=None):
    s = socket.create_connection(addr, timeout=timeout, source_address=src)
    try:
        s.sendall(adu)
        hdr = b""
        while len(hdr) < 7:
            chunk = s.recv(7 - len(hdr))
            if not chunk:
                return None
            hdr += chunk
        n = struct.unpack(">H", hdr[4:6])[0] - 1
        body = b""
        while len(body) < n:
            chunk = s.recv(n - len(body))
            if not chunk:
                return None
            body += chunk
        return body
    finally:
        s.close()


def closed_soon(s, wait=0.5):
    s.settimeout(wait)
    try:
        return s.recv(1) == b""
    except socket.timeout:
        return False
    except OSError:
        return True


def pull(hostport, unit, pid):
    host, port = hostport.rsplit(":", 1)
    addr = (host, int(port))
    read0 = b"\x03\x00\x00\x00\x01"  # read holding register 0
    out = {"rss_before_kib": rss_kib(pid)}
    if request(addr, mbap(1, unit, read0)) is None:
        fail("the pull server does not answer before the attack")

    # 1000 idle connections: the server keeps a bounded number, closes the rest on accept.
    idle = []
    for _ in range(1000):
        try:
            idle.append(socket.create_connection(addr, timeout=2))
        except OSError:
            pass
    time.sleep(0.5)
    kept = sum(1 for s in idle if not closed_soon(s, 0.01))
    out["idle"] = {"tried": 1000, "kept_open": kept, "rss_kib": rss_kib(pid)}
    if kept > 64:
        fail(f"{kept} idle connections kept open")
    for s in idle:
        s.close()
    time.sleep(0.3)

    # An MBAP length that lies (65535, then 10 bytes): no reply, the server stays in step.
    s = socket.create_connection(addr, timeout=2)
    s.sendall(mbap(2, unit, read0, length=0xFFFF) + b"\x00" * 5)
    out["lying_length"] = "closed" if closed_soon(s, 1.0) else "held"
    s.close()

    # A slow writer: a request a byte per 50 ms still gets its reply; others are served meanwhile.
    s = socket.create_connection(addr, timeout=5)
    adu = mbap(3, unit, read0)
    for k, b in enumerate(adu):
        s.sendall(bytes([b]))
        if k == 3 and request(addr, mbap(4, unit, read0)) is None:
            fail("another client was not served during the slow writer")
        time.sleep(0.05)
    s.settimeout(2)
    r = s.recv(64)
    s.close()
    if len(r) < 9 or r[7] != 3:
        fail(f"the slow writer's reply: {r!r}")
    out["slow_writer"] = "answered"

    # An unknown unit id: exception 0x0B (gateway target device failed to respond).
    r = request(addr, mbap(5, 77, read0))
    if r is None or r[0] != 0x83 or r[1] != 0x0B:
        fail(f"unknown unit: {r!r}")
    # A write outside the acknowledgement range (register 16, the header's kind in the generic
    # map; the PLC's fields are 0..10): exception 0x02.
    r = request(addr, mbap(6, unit, b"\x06\x00\x10\x12\x34"))
    if r is None or r[0] != 0x86 or r[1] != 0x02:
        fail(f"write outside the acknowledgement range: {r!r}")
    out["unknown_unit"] = "exception 0x0B"
    out["write_outside_ack"] = "exception 0x02"

    # A peer not on the allow-list (127.0.0.2): closed on accept.
    try:
        s = socket.create_connection(addr, timeout=2, source_address=("127.0.0.2", 0))
        out["stranger"] = "closed" if closed_soon(s, 1.0) else "kept"
        s.close()
    except OSError as e:
        out["stranger"] = f"refused ({e})"
    if out["stranger"] == "kept":
        fail("a peer outside the allow-list was kept")

    if request(addr, mbap(7, unit, read0)) is None:
        fail("the pull server does not answer after the attack")
    out["rss_after_kib"] = rss_kib(pid)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    if sys.argv[1] == "control":
        control(sys.argv[2], int(sys.argv[3]))
    elif sys.argv[1] == "pull":
        pull(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
    else:
        fail(f"unknown attack {sys.argv[1]}")
