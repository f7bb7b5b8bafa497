"""Independent clients of the twin's hexapod controller (issue 17, must-show 1).

PI's pipython (its GCS socket interface: PISocket + GCSMessages + GCSCommands, no vendor DLL)
drives the GCS server, Newport's newportxps (its XPS class, the raw XPS socket calls) drives the
XPS server; both move the same platform. Every exchange is checked against the manuals'
strings, and the requests pipython sends are compared with the literal strings axiscomp's GCS
machine is tested against (src/hexapod/gcs.rs).

    python3 hexapod_peer.py HOST GCS_PORT XPS_PORT
"""

import sys
import time

from pipython.pidevice.gcscommands import GCSCommands
from pipython.pidevice.gcserror import GCSError
from pipython.pidevice.gcsmessages import GCSMessages
from pipython.pidevice.interfaces.pisocket import PISocket
from newportxps.XPS_C8_drivers import XPS

host, gcs_port, xps_port = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
AXES = ["X", "Y", "Z", "U", "V", "W"]
POSE = [0.1, -0.5, 0.0, 0.01, 0.0, -0.0125]
checks = 0


def check(cond, what):
    global checks
    if not cond:
        print(f"hexapod_peer: FAIL: {what}", file=sys.stderr)
        sys.exit(1)
    checks += 1


def wait_for(query, what, tries=200):
    for _ in range(tries):
        if all(query().values()):
            return
        time.sleep(0.02)
    check(False, what)


def close(a, b, tol):
    return all(abs(x - y) <= tol for x, y in zip(a, b))


# ---------- PI GCS 2.0 with pipython ----------
with PISocket(host=host, port=gcs_port) as gw:
    sent = []
    real_send = gw.send

    def spy(msg):
        sent.append(msg)
        return real_send(msg)

    gw.send = spy
    dev = GCSCommands(GCSMessages(gw))
    idn = dev.qIDN().strip()
    check("C-887" in idn, f"*IDN? answered {idn!r}")
    try:
        dev.MOV("X", 0.1)
        check(False, "MOV before referencing was accepted")
    except GCSError as e:
        check(e.val == 5, f"MOV before referencing: error {e.val}")
        check("Unallowable move attempted on unreferenced axis" in str(e), str(e))
    dev.SVO(AXES, [True] * 6)
    dev.FRF()
    wait_for(dev.qFRF, "referenced after FRF")
    check(all(dev.qFRF(AXES).values()), "FRF? X Y Z U V W")
    dev.SPI(["R", "S", "T"], [0.0, 0.0, 120.5])
    spi = dev.qSPI()
    check(close([spi["R"], spi["S"], spi["T"]], [0, 0, 120.5], 1e-9), f"SPI? {dict(spi)}")
    dev.KSD("AXISCOMP", AXES, [0, 0, 0, 0, 0, 90])
    dev.KEN("AXISCOMP")
    dev.MOV(AXES, POSE)
    wait_for(dev.qONT, "on target")
    pos = dev.qPOS()
    check(list(pos.keys()) == AXES, f"POS? axes {list(pos.keys())}")
    check(close(list(pos.values()), POSE, 1e-3), f"POS? {dict(pos)}")
    # pipython's requests are the strings axiscomp sends (src/hexapod/gcs.rs tests).
    for want in [
        "SVO X 1 Y 1 Z 1 U 1 V 1 W 1\n",
        "FRF\n",
        "SPI R 0 S 0 T 120.5\n",
        "KSD AXISCOMP X 0 Y 0 Z 0 U 0 V 0 W 90\n",
        "KEN AXISCOMP\n",
        "MOV X 0.1 Y -0.5 Z 0 U 0.01 V 0 W -0.0125\n",
        "POS?\n",
        "ONT?\n",
        "ERR?\n",
    ]:
        check(any(m.startswith(want) or m == want for m in sent), f"pipython did not send {want!r}: {sent[-12:]}")
    try:
        dev.MOV("X", 50.0)
        check(False, "MOV outside the workspace was accepted")
    except GCSError as e:
        check(e.val == 7, f"out of limits: error {e.val}")
        check("Position out of limits" in str(e), str(e))
    dev.STP(noraise=True)
    print(f"pipython: {idn}; moved to {list(pos.values())}; refusals 5 and 7 with the manual's texts")

# ---------- Newport XPS with newportxps ----------
x = XPS()
sid = x.TCP_ConnectToServer(host, xps_port, 5)
check(sid >= 0, "XPS connect")
err, ver = x.FirmwareVersionGet(sid)
check(err == 0 and "HXP" in ver, f"FirmwareVersionGet {err} {ver!r}")
for call in (x.GroupKill, x.GroupInitialize, x.GroupHomeSearch):
    err, _ = call(sid, "HEXAPOD")
    check(err == 0, f"{call.__name__}: {err}")
err, status = x.GroupStatusGet(sid, "HEXAPOD")
check((err, status) == (0, 11), f"GroupStatusGet after homing: {err}, {status}")
err, text = x.GroupStatusStringGet(sid, 11)
check(text == "Ready state from homing", f"GroupStatusStringGet: {text!r}")
err, _ = x.Send(sid, "HexapodCoordinateSystemSet(HEXAPOD,Tool,0,0,120.5,0,0,0)")
check(err == 0, f"Tool set: {err}")
err, _ = x.Send(sid, "HexapodMoveAbsolute(HEXAPOD,Work,%s)" % ",".join(str(v) for v in POSE))
check(err == 0, f"HexapodMoveAbsolute: {err}")
err, status = x.GroupStatusGet(sid, "HEXAPOD")
check((err, status) == (0, 12), f"GroupStatusGet after the move: {err}, {status}")
err, out = x.Send(
    sid,
    "HexapodPositionCurrentGet(HEXAPOD,Work,double *,double *,double *,double *,double *,double *)",
)
pose = [float(v) for v in out.split(",")]
check(err == 0 and close(pose, POSE, 1e-3), f"HexapodPositionCurrentGet: {err} {out!r}")
err, _ = x.Send(sid, "HexapodMoveAbsolute(HEXAPOD,Work,50,0,0,0,0,0)")
check(err == -17, f"outside the workspace: {err}")
err, text = x.ErrorStringGet(sid, -17)
check((err, text) == (0, "Parameter out of range"), f"ErrorStringGet(-17): {err} {text!r}")
err, text = x.ErrorStringGet(sid, -25)
check(text == "Following Error", f"ErrorStringGet(-25): {text!r}")
err, _ = x.Send(sid, "HexapodMoveAbsolute(HEXAPOD,Work,0,0,0,0,0,0)")
check(err == 0, f"home: {err}")
# Speed: the actuators' SGamma velocity, as newportxps' set_velocity writes it; the request
# is the literal string axiscomp's XPS machine sends (src/hexapod/xps.rs).
xps_sent = []
real_xps_send = x.Send


def xps_spy(s, cmd):
    xps_sent.append(cmd)
    return real_xps_send(s, cmd)


x.Send = xps_spy
orig_vel = None
for n in range(1, 7):
    err, vel, acc, tmin, tmax = x.PositionerSGammaParametersGet(sid, f"HEXAPOD.{n}")
    check(err == 0 and vel > 0 and acc > 0 and 0 < tmin <= tmax, f"SGamma get {n}: {err}")
    orig_vel = orig_vel or vel
    err, _ = x.PositionerSGammaParametersSet(sid, f"HEXAPOD.{n}", 4.0, acc, tmin, tmax)
    check(err == 0, f"SGamma set {n}: {err}")
check(
    xps_sent[0] == "PositionerSGammaParametersGet(HEXAPOD.1,double *,double *,double *,double *)",
    f"newportxps sent {xps_sent[0]!r}",
)
check(xps_sent[1].startswith("PositionerSGammaParametersSet(HEXAPOD.1,4.0,"), xps_sent[1])
err, vel, *_ = x.PositionerSGammaParametersGet(sid, "HEXAPOD.6")
check((err, vel) == (0, 4.0), f"SGamma velocity read back: {err} {vel}")
err, _ = x.PositionerSGammaParametersSet(sid, "HEXAPOD.1", 500.0, acc, tmin, tmax)
check(err == -17, f"an actuator velocity of 500 mm/s: {err}")
t0 = time.monotonic()
err, _ = x.Send(sid, "HexapodMoveAbsolute(HEXAPOD,Work,0,4,0,0,0,0)")
took = time.monotonic() - t0
check(err == 0 and 0.9 <= took <= 3.0, f"4 mm at 4 mm/s took {took:.2f} s ({err})")
err, _ = x.Send(sid, "HexapodMoveAbsolute(HEXAPOD,Work,0,0,0,0,0,0)")
for n in range(1, 7):
    x.PositionerSGammaParametersSet(sid, f"HEXAPOD.{n}", orig_vel, acc, tmin, tmax)
x.TCP_CloseSocket(sid)
print(f"newportxps: {ver}; moved to {pose}; -17 and -25 with the manual's texts; "
      f"actuator speed 4 mm/s: 4 mm in {took:.2f} s")
print(f"hexapod_peer: {checks} checks passed")
