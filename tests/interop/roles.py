#!/usr/bin/env python3
"""The control API's roles, seen by a real user (issue 18): an independent client of the
socket (newline-delimited JSON, DESIGN §8), run by tests/interop/package.sh as an unprivileged
user of each kind through setpriv.

    roles.py none|viewer|operator SOCKET OPERATOR_GROUP

none:     the kernel refuses the connection (the socket admits the two role groups only).
viewer:   every viewing command answered; every changing command refused, naming the user,
          the command, the operator role and its group; none of them in the audit log.
operator: every changing command passes the role check (it may still fail on its own terms,
          e.g. no such run) and is in the audit log under this user.
Prints one line per check; exits 1 on the first failure.
"""
import json
import os
import pwd
import socket
import sys

# Every request that changes something (control.rs: `Request::needs` is Operator), with
# arguments the service parses; the follower's actions each count.
CHANGING = [
    {"cmd": "follower", "action": a, **({"mm": 0.0} if a in ("jog", "move") else {})}
    for a in ("home", "enable", "disable", "jog", "move", "stop", "fault_reset")
] + [
    {"cmd": "zero"},
    {"cmd": "clear_zero"},
    {"cmd": "nominal", "mm": None},
    {"cmd": "strategy", "strategy": "overlap"},
    # A plan the service refuses (one target): the role check comes first.
    {
        "cmd": "run_start",
        "plan": {"axis": "X", "start_mm": 0.0, "end_mm": 10.0, "targets": 1, "runs": 1,
                 "overrun_mm": 1.0, "dwell_s": 1.0, "feed_mm_min": 1000.0, "lead_mm": 0.0},
    },
    {"cmd": "run_abort"},
    {"cmd": "calibration_fit", "poses": "/nonexistent/poses.csv"},
    {"cmd": "calibration_accept"},
    {"cmd": "calibration_reject"},
    {"cmd": "table_generate", "run_id": 999999},
    {"cmd": "table_publish", "table_id": 999999, "confirm": False},
    {"cmd": "align_read"},
    {"cmd": "align_target", "psd": 1, "x": 0.0, "y": 0.0},
    {"cmd": "align_advice", "from_mm": 0.0, "to_mm": 10.0},
    {"cmd": "align_clear"},
]
# What an operator sends (the follower only told to stop: the others move the twin).
OPERATOR_SENDS = [r for r in CHANGING if r["cmd"] != "follower" or r["action"] == "stop"]
VIEWING = [
    {"cmd": "status"},
    {"cmd": "run_status"},
    {"cmd": "runs", "limit": 5},
    {"cmd": "run_result"},
    {"cmd": "audit", "limit": 5},
    {"cmd": "calibration"},
    {"cmd": "table_list", "limit": 5},
    {"cmd": "table_status"},
    {"cmd": "align_stored", "axis": "X"},
]


def fail(msg):
    print(f"roles.py ({ME}): FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


class Conn:
    def __init__(self, path):
        self.s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.s.settimeout(70)
        self.s.connect(path)
        self.f = self.s.makefile("rw", encoding="utf-8", newline="\n")

    def ask(self, req):
        self.f.write(json.dumps(req) + "\n")
        self.f.flush()
        line = self.f.readline()
        if not line:
            fail(f"{req['cmd']}: the service closed the connection")
        return json.loads(line)


def is_role_refusal(reply):
    return not reply.get("ok") and "may not" in reply.get("error", "")


def main():
    role, path, op_group = sys.argv[1], sys.argv[2], sys.argv[3]
    uid = os.getuid()
    if role == "none":
        try:
            Conn(path)
        except PermissionError as e:
            print(f"none: connect refused by the kernel ({e.strerror})")
            return
        fail("a user in neither group could connect to the socket")

    c = Conn(path)
    st = c.ask({"cmd": "status"})
    if not st.get("ok") or st.get("user") != ME or st.get("role") != role:
        fail(f"status says user {st.get('user')} role {st.get('role')}, not {ME} {role}: {st}")
    print(f"{role}: status names user {ME} with role {role}")
    for req in VIEWING:
        r = c.ask(req)
        if is_role_refusal(r):
            fail(f"{req['cmd']} refused: {r['error']}")
    # A subscription streams snapshots.
    sub = Conn(path)
    sub.f.write(json.dumps({"cmd": "subscribe", "hz": 20}) + "\n")
    sub.f.flush()
    if "snapshot" not in json.loads(sub.f.readline()):
        fail("subscribe gave no snapshot")
    print(f"{role}: all {len(VIEWING) + 1} viewing commands answered")

    if role == "viewer":
        for req in CHANGING:
            r = c.ask(req)
            want = (f"user {ME} (uid {uid}) may not {req['cmd']}: it needs the operator role, "
                    f"membership of group {op_group} (service.operator_group)")
            if r.get("ok") or not r.get("error", "").startswith(want):
                fail(f"{json.dumps(req)}: wanted a refusal starting {want!r}, got {r}")
        print(f"viewer: all {len(CHANGING)} changing requests refused, e.g. "
              f"\"{r['error']}\"")
        audit = c.ask({"cmd": "audit", "limit": 1000})["result"]["entries"]
        mine = [e for e in audit if e.get("user") == ME]
        if mine:
            fail(f"refused requests reached the audit log: {mine[:3]}")
        print("viewer: none of them in the audit log")
    else:
        for req in OPERATOR_SENDS:
            r = c.ask(req)
            if is_role_refusal(r):
                fail(f"{json.dumps(req)} refused to an operator: {r['error']}")
        audit = c.ask({"cmd": "audit", "limit": 1000})["result"]["entries"]
        done = {e["action"] for e in audit if e.get("user") == ME and e.get("uid") == uid}
        missing = {r["cmd"] for r in OPERATOR_SENDS} - done
        if missing:
            fail(f"not in the audit log under {ME}: {sorted(missing)}")
        print(f"operator: all {len({r['cmd'] for r in OPERATOR_SENDS})} changing commands "
              f"passed the role check and are in the audit log under {ME}")


ME = pwd.getpwuid(os.getuid()).pw_name
if __name__ == "__main__":
    main()
