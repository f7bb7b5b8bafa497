#!/usr/bin/env python3
"""A control-API subscriber for tests/interop/soak.sh: subscribes to the service's snapshots
(newline-delimited JSON on the Unix socket, {"cmd":"subscribe","hz":HZ}) and counts what it
gets until SIGTERM, then prints one JSON line: snapshots received, the longest gap between two
(s), whether psd.seq ever went backwards, the first and last psd.seq, and lines that were not
a snapshot.
    python3 soak_subscriber.py SOCKET [HZ]
"""
import json
import signal
import socket
import sys
import time

path = sys.argv[1]
hz = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
stop = False


def on_term(*_):
    global stop
    stop = True


signal.signal(signal.SIGTERM, on_term)
signal.signal(signal.SIGINT, on_term)

s = socket.socket(socket.AF_UNIX)
s.connect(path)
s.sendall(json.dumps({"cmd": "subscribe", "hz": hz}).encode() + b"\n")
s.settimeout(0.5)
buf = b""
n = 0
bad = 0
max_gap = 0.0
last = None
first_seq = None
last_seq = None
backwards = 0
closed = False
while not stop:
    try:
        chunk = s.recv(1 << 16)
    except socket.timeout:
        continue
    except InterruptedError:
        continue
    if not chunk:
        closed = True
        break
    buf += chunk
    while b"\n" in buf:
        line, buf = buf.split(b"\n", 1)
        try:
            snap = json.loads(line)["snapshot"]
        except (ValueError, KeyError, TypeError):
            bad += 1
            continue
        now = time.monotonic()
        if last is not None:
            max_gap = max(max_gap, now - last)
        last = now
        n += 1
        seq = (snap.get("psd") or {}).get("seq")
        if seq is not None:
            if last_seq is not None and seq < last_seq:
                backwards += 1
            if first_seq is None:
                first_seq = seq
            last_seq = seq
print(json.dumps({
    "snapshots": n,
    "max_gap_s": round(max_gap, 3),
    "seq_backwards": backwards,
    "first_seq": first_seq,
    "last_seq": last_seq,
    "bad_lines": bad,
    "closed_by_service": closed,
}), flush=True)
