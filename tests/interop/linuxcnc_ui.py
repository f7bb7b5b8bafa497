#!/usr/bin/python3
"""A headless LinuxCNC display for tests/interop/linuxcnc.sh (started by `linuxcnc` as
[DISPLAY]DISPLAY): machine on, home in place, then for each move list in $MOVES go through the
positions by MDI and record joint 0's commanded position and motor command from HAL. The
correction the comp file applies is motor-pos-cmd - pos-cmd. Writes JSON to $RESULT_FILE."""
import json
import os
import sys
import time

import hal
import linuxcnc


def servo_period():
    """The servo thread's last period (CPU cycles): it changes as the thread runs."""
    return hal.get_value("motion.servo.last-period")


def main():
    # hal.get_value needs a component of this process.
    probe = hal.component("axiscomp_probe")
    probe.ready()
    s = linuxcnc.stat()
    c = linuxcnc.command()
    for _ in range(200):
        try:
            s.poll()
            break
        except linuxcnc.error:
            time.sleep(0.05)

    def wait(cond, what, timeout=30.0):
        end = time.time() + timeout
        while time.time() < end:
            s.poll()
            if cond():
                return
            time.sleep(0.02)
        raise RuntimeError(f"timeout waiting for {what}")

    c.state(linuxcnc.STATE_ESTOP_RESET)
    c.wait_complete()
    c.state(linuxcnc.STATE_ON)
    c.wait_complete()
    wait(lambda: s.task_state == linuxcnc.STATE_ON, "machine on")
    c.mode(linuxcnc.MODE_MANUAL)
    c.wait_complete()
    c.home(-1)
    c.wait_complete()
    wait(lambda: all(s.homed[i] for i in range(s.joints)), "homing")
    c.mode(linuxcnc.MODE_MDI)
    c.wait_complete()
    c.mdi(os.environ["UNITS_GCODE"])
    c.wait_complete()
    feed = os.environ.get("FEED", "600")
    out = []
    for moves in json.loads(os.environ["MOVES"]):
        for x in moves:
            c.mdi(f"G1 X{x:.8f} F{feed}")
            c.wait_complete(60)
            wait(lambda: s.inpos, "in position")
        # The comp is slewed in by motion: read once the correction has held still for
        # 0.3 s while the servo thread ran (a fixed wait read it mid-slew on a loaded
        # machine; on one loaded enough the servo thread itself can stall for 0.3 s, so the
        # still time counts only with motion.servo.last-period seen changing 20 times).
        last, still_since, deadline = None, time.time(), time.time() + 20.0
        periods = set()
        while time.time() < deadline:
            d = hal.get_value("joint.0.motor-pos-cmd") - hal.get_value("joint.0.pos-cmd")
            if last is None or abs(d - last) > 1e-9:
                still_since, periods = time.time(), set()
            elif time.time() - still_since >= 0.3 and len(periods) >= 20:
                break
            periods.add(servo_period())
            last = d
            time.sleep(0.02)
        out.append({
            "x": moves[-1],
            "from": moves[0],
            "pos_cmd": hal.get_value("joint.0.pos-cmd"),
            "motor_pos_cmd": hal.get_value("joint.0.motor-pos-cmd"),
        })
    with open(os.environ["RESULT_FILE"], "w") as f:
        json.dump(out, f)
    c.state(linuxcnc.STATE_OFF)
    c.wait_complete()


if __name__ == "__main__":
    try:
        main()
    except Exception as e:  # reported through the result file, then LinuxCNC shuts down
        with open(os.environ["RESULT_FILE"], "w") as f:
            json.dump({"error": str(e)}, f)
        sys.exit(1)
