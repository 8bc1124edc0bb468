#!/usr/bin/python3
"""Simulated laser tool setter: a userspace HAL component named "beam".

Geometry (table_bc): the beam is a straight line fixed to the C table, through
beam-px/py/pz along beam-dx/dy/dz in the table frame (all axes at zero). The tool is a
solid cylinder of radius tool-radius whose tip is at the machine position (x, y, z) and
whose axis is +Z, tool-length long. The beam is interrupted, and trip goes true, when
the beam line meets the cylinder.

Table axes turn the table in the ISO 841 sense: a positive C command turns the table
by -C about Z, a positive B (A) command by -B about Y (-A about X). C is carried by the
tilting axis, B by default, A with `--tilt a`. The C line goes through (c-x, c-y) in the
tilting axis' frame, the B line through (t-x, t-z), the A line through (t-y, t-z);
non-zero values inject location errors of the rotary axes (mm).

The inputs are joint positions (machine coordinates), so the model holds whether the
identity or the TCP kinematics is active. Polls every --period seconds (default 0.0005).
Usage: beam.py [--tilt a|b] [--period s]
Counts trips in trips, the poll period actually seen in period-us.
"""
import math
import sys
import time

import hal

period = 0.0005
if "--period" in sys.argv:
    period = float(sys.argv[sys.argv.index("--period") + 1])

TILT = "b"
if "--tilt" in sys.argv:
    TILT = sys.argv[sys.argv.index("--tilt") + 1]
assert TILT in ("a", "b")

h = hal.component("beam")
for name in ("x", "y", "z", TILT, "c"):
    h.newpin(name, hal.HAL_FLOAT, hal.HAL_IN)
defaults = {
    "beam-px": 0.0, "beam-py": -100.0, "beam-pz": 70.0,
    "beam-dx": 1.0, "beam-dy": 0.0, "beam-dz": 0.0,
    "tool-radius": 5.0, "tool-length": 60.0,
    "t-x": 0.0, "t-y": 0.0, "t-z": 0.0, "c-x": 0.0, "c-y": 0.0,
}
for name in defaults:
    h.newpin(name, hal.HAL_FLOAT, hal.HAL_IO)
h.newpin("trip", hal.HAL_BIT, hal.HAL_OUT)
h.newpin("trips", hal.HAL_S32, hal.HAL_OUT)
h.newpin("period-us", hal.HAL_FLOAT, hal.HAL_OUT)
h.newpin("enable", hal.HAL_BIT, hal.HAL_IO)
h.ready()
# Geometry pins are IO: set here once, changeable any time with halcmd setp.
for name, value in defaults.items():
    h[name] = value
h["enable"] = True


def rot_z(p, a):
    ca, sa = math.cos(a), math.sin(a)
    return (ca * p[0] - sa * p[1], sa * p[0] + ca * p[1], p[2])


def rot_y(p, a):
    ca, sa = math.cos(a), math.sin(a)
    return (ca * p[0] + sa * p[2], p[1], -sa * p[0] + ca * p[2])


def rot_x(p, a):
    ca, sa = math.cos(a), math.sin(a)
    return (p[0], ca * p[1] - sa * p[2], sa * p[1] + ca * p[2])


def to_machine(p, t_deg, c_deg, is_dir):
    """Table-frame point (or direction) to the machine frame at tilt (B or A) and C."""
    k = 0.0 if is_dir else 1.0
    cx, cy = k * h["c-x"], k * h["c-y"]
    t = (k * h["t-x"], k * h["t-y"], k * h["t-z"])
    q = rot_z((p[0] - cx, p[1] - cy, p[2]), -math.radians(c_deg))
    q = (q[0] + cx - t[0], q[1] + cy - t[1], q[2] - t[2])
    q = (rot_y if TILT == "b" else rot_x)(q, -math.radians(t_deg))
    return (q[0] + t[0], q[1] + t[1], q[2] + t[2])


def interrupted():
    tilt, c = h[TILT], h["c"]
    p = to_machine((h["beam-px"], h["beam-py"], h["beam-pz"]), tilt, c, False)
    d = to_machine((h["beam-dx"], h["beam-dy"], h["beam-dz"]), tilt, c, True)
    tx, ty, tz = h["x"], h["y"], h["z"]
    r, length = h["tool-radius"], h["tool-length"]
    # Range of the line parameter s where the beam is between tip and tip + length.
    lo, hi = -1e9, 1e9
    if abs(d[2]) > 1e-12:
        s1, s2 = (tz - p[2]) / d[2], (tz + length - p[2]) / d[2]
        lo, hi = min(s1, s2), max(s1, s2)
    elif not (tz <= p[2] <= tz + length):
        return False
    # Closest approach in XY of the line (over [lo, hi]) to the tool axis.
    dxy2 = d[0] * d[0] + d[1] * d[1]
    if dxy2 < 1e-18:
        s = 0.0 if lo <= 0.0 <= hi else lo
    else:
        s = ((tx - p[0]) * d[0] + (ty - p[1]) * d[1]) / dxy2
        s = min(max(s, lo), hi)
    qx, qy = p[0] + s * d[0] - tx, p[1] + s * d[1] - ty
    return qx * qx + qy * qy <= r * r


last = time.monotonic()
try:
    while True:
        t = interrupted() if h["enable"] else False
        if t and not h["trip"]:
            h["trips"] += 1
        h["trip"] = t
        now = time.monotonic()
        h["period-us"] = 0.99 * h["period-us"] + 0.01 * (now - last) * 1e6
        last = now
        time.sleep(period)
except KeyboardInterrupt:
    pass
