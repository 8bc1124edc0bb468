#!/usr/bin/python3
"""Headless "display" for LinuxCNC: started by the linuxcnc script as
`display.py -ini <file>`; drives the machine through the linuxcnc Python module and exits,
which shuts LinuxCNC down.

Environment:
  DW_PROGRAM  G-code file to run in AUTO (optional)
  DW_REPEAT   number of repeated G38.2 trips on the beam for the latency estimate (default 20)
  DW_OUT      file for the JSON results (default results.json)
  DW_T0       wall-clock time (time.time()) the run script started LinuxCNC, for timings
  DW_HOLD     a file: after homing, skip the checks and the program and keep LinuxCNC up
              while the file exists, for another process (a gateway) to drive it
"""
import json
import os
import subprocess
import sys
import time

import linuxcnc

T0 = float(os.environ.get("DW_T0", time.time()))
OUT = os.environ.get("DW_OUT", "results.json")
res = {"errors": [], "messages": []}
s = linuxcnc.stat()
c = linuxcnc.command()
e = linuxcnc.error_channel()
INI = linuxcnc.ini(sys.argv[sys.argv.index("-ini") + 1])
KINS = INI.find("KINS", "KINEMATICS").split()[0]          # xyzbc-trt-kins / xyzac-trt-kins
TILT = INI.find("TRAJ", "COORDINATES").replace(" ", "")[3]  # B / A


def log(*a):
    print("[display %7.2fs]" % (time.time() - T0), *a, flush=True)


def drain_errors():
    while True:
        m = e.poll()
        if not m:
            return
        kind, text = m
        key = "errors" if kind in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR) else "messages"
        res[key].append(text)
        log(key[:-1] + ":", text)


def wait(pred, timeout, what):
    end = time.time() + timeout
    while time.time() < end:
        s.poll()
        drain_errors()
        if pred():
            return True
        time.sleep(0.01)
    raise SystemExit("timeout waiting for " + what)


def mdi(cmd, timeout=60):
    if s.task_mode != linuxcnc.MODE_MDI:
        c.mode(linuxcnc.MODE_MDI)
        c.wait_complete()
    n_err = len(res["errors"])
    c.mdi(cmd)
    c.wait_complete()
    time.sleep(0.02)
    wait(lambda: s.interp_state == linuxcnc.INTERP_IDLE and s.queue == 0
         and s.exec_state == linuxcnc.EXEC_DONE, timeout, cmd)
    return len(res["errors"]) == n_err


def halcmd(*args):
    return subprocess.run(["halcmd", *args], capture_output=True, text=True).stdout


def main():
    # 1. wait for task, reset estop, machine on, home
    wait(lambda: s.task_state == linuxcnc.STATE_ESTOP, 60, "task")
    res["t_task_up_s"] = time.time() - T0
    log("task up")
    c.state(linuxcnc.STATE_ESTOP_RESET)
    c.state(linuxcnc.STATE_ON)
    wait(lambda: s.task_state == linuxcnc.STATE_ON, 10, "machine on")
    c.mode(linuxcnc.MODE_MANUAL)
    c.wait_complete()
    t = time.time()
    c.home(-1)
    wait(lambda: all(s.homed[:5]), 30, "homing")
    res["t_home_s"] = time.time() - t
    res["t_ready_s"] = time.time() - T0
    log("homed in %.3f s" % res["t_home_s"])
    hold = os.environ.get("DW_HOLD")
    if hold:
        log("holding while", hold, "exists")
        # no drain_errors() here: the error channel is an NML queue, a message goes to
        # whichever reader takes it first; it belongs to the driving process now
        while os.path.exists(hold):
            time.sleep(0.2)
        c.state(linuxcnc.STATE_ESTOP)
        res["t_display_exit_s"] = time.time() - T0
        json.dump(res, open(OUT, "w"), indent=1)
        return

    # 2. kinematics pins, switchkins
    res["pins_kins"] = halcmd("show", "pin", KINS)
    res["pins_beam"] = halcmd("show", "pin", "dwtruth")
    res["pins_switch"] = halcmd("show", "pin", "motion.switchkins-type")
    res["params_kins"] = halcmd("show", "param", KINS)
    mdi("M428")
    res["switchkins_after_M428"] = halcmd("getp", "motion.switchkins-type").strip()
    halcmd("setp", KINS + ".x-rot-point", "12.5")
    res["x_rot_point_set_while_running"] = halcmd("getp", KINS + ".x-rot-point").strip()
    halcmd("setp", KINS + ".x-rot-point", "0")
    mdi("M429")
    res["switchkins_after_M429"] = halcmd("getp", "motion.switchkins-type").strip()
    log("switchkins M428 ->", res["switchkins_after_M428"], "M429 ->", res["switchkins_after_M429"])

    # 3. repeated G38.2 on the beam: Z down onto it (expected 70.000) and Y towards it
    # (expected -105.000, tool radius 5). Start i is shifted by i * 0.1 um so that the starts
    # sweep one servo period of travel (1.667 um at F100, 1 ms) and the trip phase varies.
    n = int(os.environ.get("DW_REPEAT", "20"))
    trips = {"z": [], "y": []}
    secs = []
    mdi("G21 G90 G54 G49")
    mdi("G0 Z250")
    mdi("G0 X0 Y-100 %s0 C0" % TILT)
    for i in range(n):
        mdi("G0 Z%.4f" % (71 + i * 0.0001))
        t = time.time()
        if mdi("G38.2 Z68.5 F100"):
            trips["z"].append(s.probed_position[2])
            secs.append(time.time() - t)
        mdi("G0 Z71")
    mdi("G0 Z72")
    mdi("G0 Y-106")
    mdi("G0 Z67")
    for i in range(n):
        mdi("G0 Y%.4f" % (-106 - i * 0.0001))
        if mdi("G38.2 Y-103.5 F100"):
            trips["y"].append(s.probed_position[1])
    mdi("G0 Y-106")
    mdi("G0 Z250")
    res["repeat"] = trips
    res["g38_wall_s"] = secs  # 1 mm at F100 is 0.6 s in real time
    for k, nominal in (("z", 70.0), ("y", -105.0)):
        v = trips[k]
        if v:
            # overshoot in the probing direction, um (z moves down, y moves up)
            err = [(nominal - x) * 1000 if k == "z" else (x - nominal) * 1000 for x in v]
            res["overshoot_um_" + k] = {"n": len(v), "min": min(err), "max": max(err),
                                        "mean": sum(err) / len(err),
                                        "all": [round(x, 3) for x in err]}
            log("G38.2 %s: %d trips, overshoot um min %.2f max %.2f mean %.2f" % (
                k, len(v), min(err), max(err), sum(err) / len(err)))
    log("G38.2 wall s (0.6 s in real time):", ["%.3f" % x for x in secs[:5]])

    # 3b. TCP kinematics: the same axis command with rotation point 0 and 5 mm
    tcp = {}
    mdi("M428")
    for xr in ("0", "5"):
        halcmd("setp", KINS + ".x-rot-point", xr)
        mdi("G0 X10 Y0 Z100 %s0 C0" % TILT)
        mdi("G0 C90")
        s.poll()
        p = s.actual_position  # x y z a b c u v w
        axes = [p[0], p[1], p[2], p[3] if TILT == "A" else p[4], p[5]]
        tcp["x-rot-point=" + xr] = {"axes": [round(v, 4) for v in axes],
                                    "joints": [round(v, 4) for v in s.joint_actual_position[:5]]}
        mdi("G0 C0")
    halcmd("setp", KINS + ".x-rot-point", "0")
    mdi("M429")
    res["tcp_demo"] = tcp
    log("TCP demo (M428, G0 X10 Z100 C90):", tcp)
    res["beam_trips"] = halcmd("getp", "dwtruth.0.trips").strip()

    # 4. the measurement program in AUTO
    prog = os.environ.get("DW_PROGRAM")
    if prog:
        n_err = len(res["errors"])
        c.mode(linuxcnc.MODE_AUTO)
        c.wait_complete()
        c.program_open(os.path.abspath(prog))
        c.wait_complete()
        t = time.time()
        c.auto(linuxcnc.AUTO_RUN, 0)
        c.wait_complete()
        wait(lambda: s.interp_state != linuxcnc.INTERP_IDLE, 10, "program start")
        seen = []
        last = tuple(s.probed_position)
        end = time.time() + 600
        while time.time() < end:
            s.poll()
            drain_errors()
            if tuple(s.probed_position) != last:
                last = tuple(s.probed_position)
                seen.append(last[:5])
            if s.interp_state == linuxcnc.INTERP_IDLE:
                break
            time.sleep(0.005)
        res["program_s"] = time.time() - t
        res["program_line_at_end"] = s.motion_line
        res["program_errors"] = res["errors"][n_err:]
        res["program_probed_positions"] = seen
        log("program finished in %.1f s, %d probe positions seen, errors: %s" % (
            res["program_s"], len(seen), res["program_errors"]))
        c.mode(linuxcnc.MODE_MANUAL)
        c.wait_complete()

    c.state(linuxcnc.STATE_ESTOP)
    res["t_display_exit_s"] = time.time() - T0
    json.dump(res, open(OUT, "w"), indent=1)
    log("results in", OUT)


if __name__ == "__main__":
    try:
        main()
    finally:
        if not os.path.exists(OUT):
            json.dump(res, open(OUT, "w"), indent=1)
