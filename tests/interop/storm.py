#!/usr/bin/env python3
"""The fault storm's driver (tests/interop/storm.sh sets up the processes and calls it).

During one whole run it injects randomly timed faults through the twin's control socket, one at
a time: each is held for a random while, removed, and the service is watched (its status, 10 Hz,
over the control socket) until it is healthy again; the time from removal to healthy is that
fault's recovery time. Besides the twin's faults it kills the service with SIGKILL (storm.sh's
`serve` is restarted by the driver), fills the state directory's file system, and steps the
service's wall clock (a libfaketime offset file). Every fault goes into EVENTS (TSV) with what the
service showed of it and its recovery time. Exits non-zero when a fault was not survived.

  storm.py --bin B --sock S --twin HOST:PORT --serve-cmd CMD --state DIR --events FILE ...
"""
import argparse
import json
import os
import random
import shlex
import signal
import socket
import sqlite3
import subprocess
import sys
import time

from iso230_2_check import evaluate
from truth import WITHIN_FLOOR, Twin, check_labels, far_from_truth, judge_by_truth

# Every fault the twin can inject during a run (src/sim/twin.rs), with how it is removed and the
# alarm codes the service is expected to show for it when held long enough.
TWIN_KINDS = {
    "io-stop": ({"cmd": "io", "action": "stop"}, {"cmd": "io", "action": "restart"},
                {"io-link-down"}),
    "io-exception": ({"cmd": "io", "exception": 6}, {"cmd": "io", "exception": 0},
                     {"io-exception"}),
    "io-hang": ({"cmd": "io", "delay_ms": 5000}, {"cmd": "io", "delay_ms": 0},
                {"io-link-down", "io-stale"}),
    "io-slow": ({"cmd": "io", "delay_ms": 25}, {"cmd": "io", "delay_ms": 0}, set()),
    "beam-blocked": (None, None, {"beam-blocked", "run-paused"}),
    "drive-fault": ({"cmd": "drive", "fault": 0x8611}, None, {"drive-fault"}),
    "heartbeat-lost": ({"cmd": "drive", "heartbeat": False}, {"cmd": "drive", "heartbeat": True},
                       {"heartbeat-lost"}),
    "knock": (None, None, set()),
}
SPECIAL = ["sigkill", "disk-full", "clock-step"]


def svc(sock, req, timeout=5.0):
    """One request to the service's control socket; None when it does not answer."""
    try:
        s = socket.socket(socket.AF_UNIX)
        s.settimeout(timeout)
        s.connect(sock)
        s.sendall(json.dumps(req).encode() + b"\n")
        line = s.makefile().readline()
        s.close()
        return json.loads(line) if line.strip() else None
    except (OSError, ValueError):
        return None


# Alarms that a run shows while it waits for the carriage to come back past the follower
# (PSD2 alone without its spot after the follower was stopped or left behind: by design the
# run waits for the carriage's next pass and makes up what it missed at the end).
WAITING_FOR_PASS = {"run-paused", "stitch-broken", "beam-blocked"}
# A capture flagged (a knock found late, the judge) stays alarmed while its run retakes it in
# the make-up pass: the run's own business, not a fault left unrecovered.
RUN_RETAKES = {"capture-flagged"}


def healthy(st):
    """Whether a status shows the service whole again: the I/O link up with a fresh frame, the
    follower enabled with its heartbeat and homed, and no active alarm — except, in a run, a
    flagged capture it retakes, and the three of a run waiting for the carriage's next pass
    (PSD1 and PSD3 seeing their spots, PSD2 not)."""
    if not st or "links" not in st:
        return False
    p = st.get("psd") or {}
    f = st["follower"]
    spots = p.get("spots_um", [None, None, None])
    run = st.get("run") is not None
    alarms = active_alarms(st) - (RUN_RETAKES if run else set())
    waiting = spots[0] is not None and spots[2] is not None and alarms <= WAITING_FOR_PASS
    return (st["links"]["io"]["state"] == "up" and p.get("age_ms", 1e9) < 100.0
            and f["heartbeat_ok"] and f["homed"] and f["state"] == "Operation enabled"
            and (not alarms or (waiting and run)))


def active_alarms(st):
    return {a["code"] for a in (st or {}).get("alarms", []) if a["active"]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", required=True)
    ap.add_argument("--sock", required=True)
    ap.add_argument("--twin", required=True)
    ap.add_argument("--serve-cmd", required=True, help="shell command that starts the service")
    ap.add_argument("--serve-log", required=True, help="log path prefix: PREFIX<n>.log")
    ap.add_argument("--pidfile", required=True, help="the service's pid (kept up to date)")
    ap.add_argument("--state", required=True, help="the state directory (its own file system)")
    ap.add_argument("--clock-file", required=True, help="libfaketime's offset file")
    ap.add_argument("--events", required=True)
    ap.add_argument("--faults", type=int, default=54)
    ap.add_argument("--seed", type=int, default=18)
    ap.add_argument("--hold-max", type=float, default=2.5)
    ap.add_argument("--gap-max", type=float, default=2.5)
    ap.add_argument("--recovery-timeout", type=float, default=60.0)
    ap.add_argument("--budget", type=float, default=900.0,
                    help="seconds from run start to finished, storm included")
    ap.add_argument("--run-args", required=True)
    ap.add_argument("--db", required=True)
    ap.add_argument("--disk", default="skip", help="what the state directory is on")
    ap.add_argument("--truth", default="report", choices=["report", "within", "strict"],
                    help="within: fail on any stored capture further from the truth than its U "
                         "or 1 µm / 0.4″; strict: on any outside its U, or a U not sharp")
    ap.add_argument("--truth-json", default="/dev/null",
                    help="where every capture's comparison with the truth is written")
    ap.add_argument("--verify-faults", type=int, default=0,
                    help="the verification run after publishing, under a storm of this many "
                         "faults, judged by the truth (0: no verification run)")
    ap.add_argument("--verify-e-um", type=float, default=1.0,
                    help="the compensated axis' positioning E by the truth must be within this")
    a = ap.parse_args()
    rng = random.Random(a.seed)
    twin = Twin(a.twin)
    # The zero was taken at 0 mm after the alignment and the carriage has not moved since: the
    # truth here is what every capture is measured from.
    zero_truth = twin.cmd({"cmd": "truth"})["truth"]
    t_start = time.monotonic()

    def log(msg):
        print(f"storm.py: t={time.monotonic() - t_start:6.1f} s: {msg}", flush=True)

    def status():
        return (svc(a.sock, {"cmd": "status"}, timeout=2.0) or {}).get("snapshot")

    def run_status():
        return (svc(a.sock, {"cmd": "run_status"}, timeout=2.0) or {}).get("result")

    def svc_pid():
        return int(open(a.pidfile).read().strip())

    def start_service(tag):
        log_f = open(f"{a.serve_log}{tag}.log", "w")
        p = subprocess.Popen(["bash", "-c", f"exec {a.serve_cmd}"], stdout=log_f,
                             stderr=subprocess.STDOUT)
        open(a.pidfile, "w").write(str(p.pid))
        return p

    def start_run():
        r = subprocess.run([a.bin, "run", "start", "--json", "--socket", a.sock] + shlex.split(a.run_args),
                           capture_output=True, text=True)
        if r.returncode != 0:
            sys.exit(f"storm.py: run start refused: {r.stdout}{r.stderr}")
        start = json.loads(r.stdout)
        log(f"run {start['run_id']} started: {start['captures_expected']} captures expected")
        if a.disk != "skip":
            # What the state directory holds (its file system is the disk-full fault's).
            files = []
            for root, _, names in os.walk(a.state):
                for n in names:
                    p = os.path.join(root, n)
                    try:
                        files.append(f"{os.path.relpath(p, a.state)} {os.path.getsize(p) // 1024} KiB")
                    except OSError:
                        pass
            st = os.statvfs(a.state)
            log(f"state directory: {st.f_bavail * st.f_frsize // 1024} KiB free; " + ", ".join(sorted(files)))
        return start["run_id"], start["captures_expected"]

    def draw(n):
        """n faults of every kind, shuffled, the special ones at random places in the second
        to the penultimate fifth."""
        kinds = list(TWIN_KINDS)
        plan = []
        while len(plan) < n - len(SPECIAL):
            batch = kinds[:]
            rng.shuffle(batch)
            plan += batch
        plan = plan[: n - len(SPECIAL)]
        for k in SPECIAL:
            plan.insert(rng.randint(len(plan) // 5, 4 * len(plan) // 5), k)
        return plan

    proc = None  # the service when the driver restarted it
    clock_offset = 0
    offsets = [0]  # every offset of the service's wall clock so far (s)
    worst = (0.0, "")

    def run_state():
        rs = run_status() or {}
        return rs.get("state"), rs.get("captures")

    def weather(plan, run_id, t_run, tag=""):
        """The faults of `plan` during run `run_id` (started at `t_run`), each held, removed and
        recovered from; then the rest of the run, within the budget. (events, state, captures)
        The service restarted after a SIGKILL logs to serve-<tag><n>.log."""
        nonlocal proc, clock_offset, worst
        events = []
        for i, kind in enumerate(plan):
            if time.monotonic() > t_run + a.budget:
                log(f"over the budget of {a.budget:.0f} s after {i} faults")
                break
            state, caps = run_state()
            if state in ("finished", "failed", "aborted"):
                log(f"the run ended ({state}) before fault {i + 1} of {len(plan)}")
                break
            hold = rng.uniform(0.3, a.hold_max)
            seen = set()
            before = status() or {}
            io0 = (before.get("links") or {}).get("io", {})
            detail = ""
            t_inject = time.monotonic()
            # Inject.
            if kind in TWIN_KINDS and kind not in ("beam-blocked", "knock"):
                on, off, _ = TWIN_KINDS[kind]
                twin.cmd(on)
            elif kind == "beam-blocked":
                psd = rng.randint(1, 3)
                detail = f"PSD{psd}"
                twin.cmd({"cmd": "block", "psd": psd, "on": True})
            elif kind == "knock":
                yaw = rng.choice([-1, 1]) * rng.uniform(2.0, 10.0)
                detail = f"yaw {yaw:+.1f} µrad"
                twin.cmd({"cmd": "knock", "yaw_urad": yaw})
                hold = 0.0
            elif kind == "sigkill":
                pid = svc_pid()
                os.kill(pid, signal.SIGKILL)
                if proc is not None:
                    proc.wait()
                detail = f"pid {pid} at {caps} captures"
            elif kind == "disk-full" and a.disk == "skip":
                detail = "not tested: the state directory has no file system of its own"
                hold = 0.0
            elif kind == "disk-full":
                ballast = os.path.join(a.state, "ballast")
                st = os.statvfs(a.state)
                free0 = st.f_bavail * st.f_frsize
                try:
                    # Opening can fail too: a file system the store has filled already.
                    with open(ballast, "wb") as f:
                        while True:
                            f.write(b"\0" * (1 << 20))
                            f.flush()
                except OSError:
                    pass
                st = os.statvfs(a.state)
                detail = f"{st.f_bavail * st.f_frsize} bytes left ({free0} before the ballast)"
                hold = max(hold, 4.0)
            elif kind == "clock-step":
                step = rng.choice([-1, 1]) * 3600 * rng.randint(1, 3)
                clock_offset += step
                offsets.append(clock_offset)
                with open(a.clock_file, "w") as f:
                    f.write(f"{clock_offset:+d}\n")
                detail = f"wall clock {step:+d} s (now {clock_offset:+d} s)"
                hold = 0.0
            # Hold, watching.
            t_end = time.monotonic() + hold
            while time.monotonic() < t_end:
                seen |= active_alarms(status())
                time.sleep(0.1)
            t_clear = time.monotonic()
            # Remove.
            if kind in TWIN_KINDS and kind not in ("beam-blocked", "knock"):
                off = TWIN_KINDS[kind][1]
                if off is not None:
                    twin.cmd(off)
            elif kind == "beam-blocked":
                twin.cmd({"cmd": "block", "psd": int(detail[3:]), "on": False})
            elif kind == "sigkill":
                time.sleep(hold)
                t_clear = time.monotonic()
                proc = start_service(f"{tag}{i + 1}")
            elif kind == "disk-full" and a.disk != "skip":
                try:
                    os.unlink(os.path.join(a.state, "ballast"))
                except FileNotFoundError:
                    pass
            # Recovered?
            deadline = t_clear + a.recovery_timeout
            st = status()
            operator = []
            last_op = 0.0
            while not healthy(st) and time.monotonic() < deadline:
                seen |= active_alarms(st)
                # What the alarms tell the operator to do: a faulted drive is reset, a drive the
                # service stopped (heartbeat lost) is enabled again, by command, never on its own.
                f = (st or {}).get("follower") or {}
                if f.get("heartbeat_ok") and time.monotonic() - last_op > 1.0:
                    action = ("fault_reset" if f.get("state") == "Fault"
                              else "enable" if f.get("state") in ("Switch on disabled",
                                                                   "Ready to switch on",
                                                                   "Switched on") else None)
                    if action:
                        svc(a.sock, {"cmd": "follower", "action": action})
                        operator.append(action)
                        last_op = time.monotonic()
                time.sleep(0.1)
                st = status()
            t_ok = time.monotonic()
            ok = healthy(st)
            io1 = (st or {}).get("links", {}).get("io", {})
            counters = ",".join(f"{k}+{io1.get(k, 0) - io0.get(k, 0)}"
                                for k in ("errors", "exceptions", "reconnects")
                                if io1.get(k, 0) != io0.get(k, 0)) if kind != "sigkill" else ""
            rec = t_ok - t_clear
            ev = {"run_id": run_id, "n": i + 1, "kind": kind, "detail": detail,
                  "injected_s": round(t_inject - t_run, 2), "held_s": round(t_clear - t_inject, 2),
                  "recovered": ok, "recovery_s": round(rec, 2),
                  "alarms_seen": sorted(seen), "io_counters": counters,
                  "captures": run_state()[1], "still_active": sorted(active_alarms(st)),
                  "operator": operator,
                  "waits_for_pass": bool(ok and active_alarms(st))}
            events.append(ev)
            log(f"fault {i + 1}/{len(plan)} {kind} {detail}: held {ev['held_s']} s, "
                f"{'recovered in ' + format(rec, '.2f') + ' s' if ok else 'NOT RECOVERED'}"
                f"{' (the run waits for the next pass)' if ev['waits_for_pass'] else ''}; "
                f"alarms {','.join(sorted(seen)) or '-'} {counters}"
                f"{'; operator: ' + ','.join(operator) if operator else ''}"
                f"{'' if ok else '; still ' + ','.join(sorted(active_alarms(st))) + ' ' + json.dumps(st.get('follower') if st else None)}")
            if ok and rec > worst[0]:
                worst = (rec, kind)
            if not ok:
                break
            time.sleep(rng.uniform(0.3, a.gap_max))

        # The rest of the run.
        deadline = t_run + a.budget
        while True:
            state, caps = run_state()
            if state in ("finished", "failed", "aborted"):
                break
            if time.monotonic() > deadline:
                break
            time.sleep(0.5)
        return events, state, caps

    run_id, expected = start_run()
    events, state, caps = weather(draw(a.faults), run_id, t_start)
    log(f"run {run_id} {state} with {caps} of {expected} captures")
    survived = sum(ev["recovered"] for ev in events)
    lost, dup = check_captures(a.db, run_id, log)
    truth = judge_by_truth(a.db, run_id, twin, zero_truth, log)
    wrong, unplaced = check_labels(a.db, run_id, twin, offsets, log)
    with open(a.truth_json, "w") as f:
        json.dump(truth, f, indent=1)
    tables_ok = publish_storm(a, twin, run_id, log) if state == "finished" else False
    truth_ok = truth_holds(a, truth, log)

    # The verification run on the compensated axis (the twin's PLC applies the tables it
    # accepted), under a storm of its own, judged by the truth; its positioning figures by the
    # service and by the truth, beside the first run's.
    verification, verified = None, a.verify_faults == 0
    if a.verify_faults > 0 and tables_ok:
        t_run = time.monotonic()
        vid, vexp = start_run()
        vevents, vstate, vcaps = weather(draw(a.verify_faults), vid, t_run, tag="v")
        log(f"verification run {vid} {vstate} with {vcaps} of {vexp} captures in "
            f"{time.monotonic() - t_run:.0f} s")
        events += vevents
        vlost, vdup = check_captures(a.db, vid, log)
        vtruth = judge_by_truth(a.db, vid, twin, zero_truth, log)
        vwrong, vunplaced = check_labels(a.db, vid, twin, offsets, log)
        if vlost or lost:
            log("no positioning figures: a run has captures missing")
            before = after = {w: {k: float("inf") for k in ("E", "A", "R", "B")}
                              for w in ("service", "truth")}
        else:
            before, after = positioning(truth), positioning(vtruth)
        for name, fig in ((f"before (run {run_id})", before), (f"after (run {vid})", after)):
            log(f"positioning {name}: "
                + ", ".join(f"{k} {fig['service'][k]:.2f} µm by the service, "
                            f"{fig['truth'][k]:.2f} µm by the truth" for k in ("E", "A", "R", "B")))
        e_ok = after["truth"]["E"] <= a.verify_e_um
        log(f"verification: E after by the truth {after['truth']['E']:.2f} µm "
            f"({'within' if e_ok else 'NOT within'} {a.verify_e_um:g} µm); by the service "
            f"{after['service']['E']:.2f} µm")
        verified = (vstate == "finished" and vlost == 0 and vdup == 0 and e_ok
                    and vwrong == 0 and vunplaced == 0
                    and all(ev["recovered"] for ev in vevents)
                    and len(vevents) >= a.verify_faults and truth_holds(a, vtruth, log))
        verification = {"run_id": vid, "state": vstate, "injected": len(vevents),
                        "survived": sum(ev["recovered"] for ev in vevents),
                        "captures_lost": vlost, "captures_duplicated": vdup,
                        "mislabelled": vwrong, "at_no_rest": vunplaced,
                        "positioning_before_um": before, "positioning_after_um": after,
                        "truth": {k: v for k, v in vtruth.items() if k != "captures"}}
    elif a.verify_faults > 0:
        log("no verification run: the tables were not published whole")

    with open(a.events, "w") as f:
        cols = ["run_id", "n", "kind", "detail", "injected_s", "held_s", "recovered", "recovery_s",
                "alarms_seen", "io_counters", "operator", "waits_for_pass", "captures", "still_active"]
        f.write("\t".join(cols) + "\n")
        for ev in events:
            f.write("\t".join(",".join(v) if isinstance(v, list) else str(v)
                              for v in (ev[c] for c in cols)) + "\n")
    by_kind = {}
    for ev in events:
        by_kind.setdefault(ev["kind"], []).append(ev["recovery_s"])
    for k, rs in sorted(by_kind.items()):
        log(f"  {k}: {len(rs)} injected, worst recovery {max(rs):.2f} s")
    print(json.dumps({"run_id": run_id, "expected": expected, "state": state,
                      "injected": len(events), "survived": survived,
                      "kinds": sorted(by_kind), "worst_recovery_s": round(worst[0], 2),
                      "worst_kind": worst[1],
                      "run_waited_for_a_pass": sum(ev["waits_for_pass"] for ev in events),
                      "captures_lost": lost, "captures_duplicated": dup,
                      "mislabelled": wrong, "at_no_rest": unplaced,
                      "tables_whole": tables_ok,
                      "truth": {k: v for k, v in truth.items() if k != "captures"},
                      "verification": verification}))
    if proc is not None:
        print(f"SERVICE_PID {proc.pid}", file=sys.stderr)
    first = [ev for ev in events if ev["run_id"] == run_id]
    checks = [
        (f"every fault recovered ({survived} of {len(first)})", survived == len(first)),
        (f"the run finished ({state})", state == "finished"),
        (f"no capture lost ({lost}) or duplicated ({dup})", lost == 0 and dup == 0),
        (f"none mislabelled ({wrong}) or at no rest ({unplaced})", wrong == 0 and unplaced == 0),
        ("the tables published whole", tables_ok),
        (f"every fault injected ({len(first)} of {a.faults})", len(first) >= a.faults),
        ("every capture within the truth's bound", truth_ok),
        ("the verification run", verified),
    ]
    failed = [name for name, ok in checks if not ok]
    log("storm: " + ("every check passed" if not failed else "FAILED: " + "; ".join(failed)))
    sys.exit(0 if not failed else 1)


def truth_holds(a, truth, log):
    """Whether a run's captures hold against the truth as --truth asks."""
    if a.truth == "within":
        return not far_from_truth(truth, WITHIN_FLOOR, log)
    return a.truth != "strict" or (truth["outside_u"] == 0 and truth["sharp"])


# The positioning error among the six: the head's frame has the beam along its y (dy).
POSITIONING = 1


def positioning(judged):
    """ISO 230-2 positioning figures (µm) of a judged run, from its stored captures and from the
    twin's truth at the same targets and directions (iso230_2_check.py, independent of the
    service's own evaluation)."""
    out = {}
    for what in ("service", "truth"):
        rows = [{"target_index": c["target"], "target_mm": c["mm"], "run": c["run"],
                 "direction": c["direction"],
                 "measured_mm": c["mm"]
                 + c["measured" if what == "service" else "truth"][POSITIONING] / 1e3}
                for c in judged["captures"]]
        out[what] = evaluate(rows)["axis"]
    return out


def check_captures(db, run_id, log):
    """Every (run, target, direction) of the plan stored exactly once: (missing, duplicated)."""
    c = sqlite3.connect(db)
    plan = json.loads(c.execute("SELECT plan_json FROM runs WHERE id = ?", (run_id,)).fetchone()[0])
    targets, runs = len(plan["targets"]), plan["spec"]["runs"]
    have = {}
    for r, t, d in c.execute("SELECT run, target_index, direction FROM captures WHERE run_id = ?",
                             (run_id,)):
        have[(r, t, d)] = have.get((r, t, d), 0) + 1
    want = {(r, t, d) for r in range(1, runs + 1) for t in range(targets) for d in "+-"}
    missing = sorted(want - have.keys())
    dup = sorted(k for k, n in have.items() if n > 1 or k not in want)
    log(f"captures: {sum(have.values())} stored of {len(want)} planned; missing {missing or 'none'}, "
        f"duplicated or not planned {dup or 'none'}")
    return len(missing), len(dup)


# The PLC's faults (src/sim/twin.rs `plc`), each with what undoes it, then a clean publish.
PLC_FAULTS = [
    ("refused", {"reject_next": 256}, None),
    ("corrupted", {"corrupt_next": 3}, None),
    ("commit-ignored", {"ignore_next": True}, None),
    ("silent-mid-publish", {"silent_after": 2, "down_ms": 1500}, None),
    ("not-ready", {"ready": False}, {"ready": True}),
    ("heartbeat-frozen", {"freeze_heartbeat": True}, {"freeze_heartbeat": False}),
    ("none", {}, None),
]


def publish_storm(a, twin, run_id, log):
    """Generate the run's tables and publish them with each PLC fault injected, then cleanly:
    after every attempt each of the PLC's active tables is the one it held before or the one
    just published, whole (sequence and payload CRC-32 as stored)."""
    g = svc(a.sock, {"cmd": "table_generate", "run_id": run_id}, timeout=60) or {}
    tables = (g.get("result") or {}).get("tables") or []
    if not tables:
        log(f"no tables generated from run {run_id}: {g}")
        return False
    ok = True
    crc_of = {t["id"]: t["crc"] for t in tables}
    for t in tables:
        for name, on, off in PLC_FAULTS:
            before = [(x or {}).get("sequence") and (x["sequence"], x["crc"])
                      for x in twin.cmd({"cmd": "plc"})["plc"]["active"]]
            twin.cmd(dict({"cmd": "plc"}, **on))
            r = svc(a.sock, {"cmd": "table_publish", "table_id": t["id"], "confirm": True},
                    timeout=90) or {}
            p = r.get("result") or {"result": r.get("error")}
            if off:
                twin.cmd(dict({"cmd": "plc"}, **off))
            if name == "silent-mid-publish":
                time.sleep(2.5)  # the PLC comes back
            after = [(x or {}).get("sequence") and (x["sequence"], x["crc"])
                     for x in twin.cmd({"cmd": "plc"})["plc"]["active"]]
            new = (p.get("sequence"), crc_of[t["id"]])
            whole = all(b == c or c == new for b, c in zip(before, after))
            applied = new in after
            committed = p.get("result") == "committed"
            good = whole and (applied == committed or (not committed and p.get("commit_sent")))
            if name == "none":
                good = good and committed and applied
            else:
                good = good and not committed
            ok &= good
            log(f"table {t['id']} ({t['name']}, {t['crc']}) with the PLC {name}: "
                f"{p.get('result')} (sequence {p.get('sequence')}, {p.get('message')}); "
                f"PLC active {after}: {'whole' if whole else 'PARTIAL'}"
                f"{'' if good else ' — WRONG'}")
    st = (svc(a.sock, {"cmd": "table_status"}, timeout=30) or {}).get("result") or {}
    log(f"table status: {st.get('verdict')}: {st.get('message')}")
    return ok and st.get("verdict") == "matches"


if __name__ == "__main__":
    main()
