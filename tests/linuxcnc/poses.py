#!/usr/bin/python3
"""Command poses in TCP mode (M428) on a running LinuxCNC and read where the true tool tip is.

Run as the user LinuxCNC runs as. Input (argv[1], JSON): {"tilt": "B" | "A", "poses": [[x, y,
z, tilt_deg, c_deg], ...]} with x, y, z the table-frame point commanded. For each pose it
moves there with G0 in TCP mode and reads the true tip in the table frame from the truth
component (dwtruth.0.tip-x/y/z). Prints one JSON object: {"poses": [{"commanded": [...],
"tip": [...], "joints": [...]}, ...], "errors": [...]}. The truth's beam is switched off
meanwhile (the moves do not avoid the setter) and on again after.
"""
import json
import subprocess
import sys
import time

import linuxcnc

s = linuxcnc.stat()
c = linuxcnc.command()
req = json.load(open(sys.argv[1]))
out = {"poses": [], "errors": []}


def halcmd(*args):
    return subprocess.run(["halcmd", "-s", *args], capture_output=True, text=True, check=True).stdout.strip()


def wait_idle(timeout=60):
    end = time.time() + timeout
    while time.time() < end:
        s.poll()
        if s.interp_state == linuxcnc.INTERP_IDLE and s.queue == 0 and s.inpos:
            return
        time.sleep(0.01)
    raise SystemExit("timeout waiting for the move to end")


def mdi(cmd):
    c.mdi(cmd)
    c.wait_complete(60)
    time.sleep(0.02)
    wait_idle()


s.poll()
if s.task_state != linuxcnc.STATE_ON or s.interp_state != linuxcnc.INTERP_IDLE:
    sys.exit("the machine is not on and idle")
halcmd("setp", "dwtruth.0.enable", "0")
try:
    c.mode(linuxcnc.MODE_MDI)
    c.wait_complete()
    mdi("G21 G90 G54")
    for x, y, z, t, cc in req["poses"]:
        # Retract and turn in machine coordinates (identity kinematics), then reach the table
        # point in TCP mode, where the kinematics' pins place it.
        mdi("M429")
        mdi("G0 Z250")
        mdi(f"G0 {req['tilt']}{t:.4f} C{cc:.4f}")
        mdi("M428")
        mdi(f"G0 X{x:.4f} Y{y:.4f} Z{z:.4f} {req['tilt']}{t:.4f} C{cc:.4f}")
        time.sleep(0.05)  # a few servo periods: the component has seen the final position
        s.poll()
        tip = [float(halcmd("getp", f"dwtruth.0.tip-{a}")) for a in "xyz"]
        out["poses"].append({"commanded": [x, y, z, t, cc], "tip": tip,
                             "joints": list(s.joint_actual_position[:5])})
    mdi("M429")
    mdi("G0 Z250")
    mdi(f"G0 {req['tilt']}0 C0")
finally:
    halcmd("setp", "dwtruth.0.enable", "1")
print(json.dumps(out))
