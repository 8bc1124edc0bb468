#!/usr/bin/python3
"""driftwatch's gateway for LinuxCNC: runs on the LinuxCNC computer, as the user LinuxCNC runs as.

It follows the nc_push handshake (docs/integrate-nc.md): it posts the machine's state, spindle
speed and temperatures; when the service orders a cycle and the machine is idle, on and homed,
it runs driftwatch's measurement program (`driftwatch nc program --dialect iso`) in AUTO and
posts every trip as it happens (the program's `(DEBUG,DW n x y z)` messages), `no_trip` where
LinuxCNC reports a probe move that ended without contact; and it writes each newly served set
into the kinematics' pins (`?format=linuxcnc`: a halcmd script of `setp` lines), only while
no program runs, only pins of its kinematics, never a step or an offset beyond its limits,
and reads each pin back. Everything it does and refuses goes to stdout as one JSON object a
line (its journal).

Needs Python 3.11 (tomllib) and LinuxCNC's `linuxcnc` module and `halcmd`; nothing else.
Usage: dw_gateway.py gateway.toml   (deploy/linuxcnc/gateway.example.toml documents the keys)
"""
import json
import math
import os
import re
import subprocess
import sys
import time
import tomllib
import urllib.error
import urllib.parse
import urllib.request

import linuxcnc

STEP_RE = re.compile(r"^\(STEP (\d+) (\S+)\)$")
PLAN_RE = re.compile(r"DRIFTWATCH PLAN (\S+) ON (\S+)")
TOOL_RE = re.compile(r"^\(TOOL (\S+) IN THE SPINDLE")
SPEED_RE = re.compile(r"^S(\d+(?:\.\d+)?) M3$")
TRIP_RE = re.compile(r"^DW (\d+) (-?\d+(?:\.\d+)?) (-?\d+(?:\.\d+)?) (-?\d+(?:\.\d+)?)$")
SET_RE = re.compile(r"set (\d+)")
PINS = ("x-rot-point", "y-rot-point", "z-rot-point", "x-offset", "y-offset", "z-offset")


def journal(kind, **fields):
    print(json.dumps({"t": round(time.time(), 3), "kind": kind, **fields}), flush=True)


def secret(value):
    """`env:VAR` reads the value from the environment."""
    if isinstance(value, str) and value.startswith("env:"):
        v = os.environ.get(value[4:])
        if v is None:
            sys.exit(f"dw_gateway: environment variable {value[4:]} is not set")
        return v
    return value


class Service:
    """The driftwatch service over HTTP: every call returns (status, headers, body) or None
    when the service cannot be reached; nothing here raises on the network."""

    def __init__(self, cfg):
        self.base = cfg["url"].rstrip("/") + "/api/v1/machines/" + urllib.parse.quote(cfg["machine"])
        self.token = secret(cfg["token"])
        self.timeout = float(cfg.get("timeout_s", 5.0))

    def call(self, method, path, body=None, headers=None):
        h = {"Authorization": "Bearer " + self.token}
        h.update(headers or {})
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            h["Content-Type"] = "application/json"
        req = urllib.request.Request(self.base + path, data=data, headers=h, method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                return r.status, dict(r.headers), r.read().decode()
        except urllib.error.HTTPError as e:
            return e.code, dict(e.headers), e.read().decode(errors="replace")
        except (urllib.error.URLError, OSError) as e:
            journal("service_unreachable", error=str(e))
            return None


class Outbox:
    """Events wait here until the service took them: one event a request, in order, so that a
    refused event (400, named by the service) is dropped alone and a retry is always safe."""

    def __init__(self, service):
        self.service = service
        self.events = []

    def add(self, topic, msg):
        self.events.append({"topic": topic, "t_ns": time.time_ns(), "msg": msg})

    def flush(self):
        while self.events:
            ev = self.events[0]
            r = self.service.call("POST", "/nc/events", {"events": [ev]})
            if r is None or r[0] == 503 or r[0] >= 500:
                return False
            if r[0] != 202:
                journal("event_refused", status=r[0], topic=ev["topic"], msg=ev["msg"], answer=r[2][:500])
            self.events.pop(0)
        return True


class Program:
    """driftwatch's ISO measurement program: its plan, machine, tool, speed and step labels."""

    def __init__(self, path):
        self.path = os.path.abspath(path)
        self.plan = self.machine = self.tool = None
        self.rpm = None
        self.labels = {}
        with open(self.path) as f:
            for line in f:
                t = line.strip()
                if m := PLAN_RE.search(t):
                    self.plan, self.machine = m.group(1), m.group(2)
                elif m := TOOL_RE.match(t):
                    self.tool = m.group(1)
                elif m := SPEED_RE.match(t):
                    self.rpm = float(m.group(1))
                elif m := STEP_RE.match(t):
                    self.labels[int(m.group(1))] = m.group(2)
        if not (self.plan and self.labels):
            raise ValueError(f"{self.path} is not a driftwatch ISO measurement program")

    def mismatch(self, order):
        """Why this program cannot run the order (None when it can)."""
        if order["plan"] != self.plan:
            return f"the order is for plan {order['plan']}, the program for {self.plan}"
        labels = [s["step"] for s in order["steps"]]
        mine = [self.labels[n] for n in sorted(self.labels)]
        if labels != mine:
            return f"the order's {len(labels)} steps are not the program's {len(mine)}"
        if self.rpm is not None and abs(order["spindle_rpm"] - self.rpm) > 0.5:
            return f"the order wants {order['spindle_rpm']} min^-1, the program turns {self.rpm}"
        return None


class Hal:
    """The kinematics' pins through halcmd (values persist when the gateway stops)."""

    def get(self, pin):
        out = subprocess.run(["halcmd", "-s", "getp", pin], capture_output=True, text=True, timeout=10)
        if out.returncode != 0:
            raise RuntimeError(f"halcmd getp {pin}: {out.stderr.strip() or out.stdout.strip()}")
        return float(out.stdout.strip())

    def set(self, pin, value):
        out = subprocess.run(["halcmd", "setp", pin, repr(value)], capture_output=True, text=True, timeout=10)
        if out.returncode != 0:
            raise RuntimeError(f"halcmd setp {pin}: {out.stderr.strip() or out.stdout.strip()}")


class Gateway:
    def __init__(self, cfg):
        self.cfg = cfg
        self.service = Service(cfg["service"])
        self.outbox = Outbox(self.service)
        self.program = Program(cfg["program"]["path"])
        self.before = list(cfg["program"].get("before_mdi", []))
        self.after = list(cfg["program"].get("after_mdi", []))
        self.timeout_s = float(cfg["program"].get("timeout_s", 600.0))
        k = cfg["kinematics"]
        self.kins = k["component"]
        self.nominal = {p: float(v) for p, v in k["nominal"].items()}
        bad = [p for p in self.nominal if p not in PINS]
        if bad:
            sys.exit(f"dw_gateway: kinematics.nominal names no pin of the trt kinematics: {bad}")
        self.max_step_mm = float(k.get("max_step_mm", 0.05))
        self.max_offset_mm = float(k.get("max_offset_mm", 0.2))
        self.temperatures = dict(cfg.get("temperatures", {}))
        self.poll_s = float(cfg["service"].get("poll_s", 1.0))
        self.s = linuxcnc.stat()
        self.c = linuxcnc.command()
        self.e = linuxcnc.error_channel()
        self.hal = Hal()
        self.state = None
        self.rpm = None
        self.rpm_sent = 0.0
        self.temp_sent = 0.0
        self.next_poll = 0.0
        self.etag = None
        self.written = None  # the version of the last set written
        self.written_text = self.written_pins = None  # that set as served, and its pin values
        self.next_verify = 0.0
        self.pending = None  # a set waiting for the machine to be idle
        self.refused_order = None
        self.ran = {}  # cycle number -> how its run ended: an order runs once
        self.deferred = None  # the ETag of a set last said to wait
        self.refusal = None  # the service's last refusal of a set, said once
        self.cycle = None

    # --- the machine ---------------------------------------------------------------------

    def machine_state(self):
        s = self.s
        if s.task_state == linuxcnc.STATE_ESTOP:
            return "alarm"
        if s.task_state != linuxcnc.STATE_ON or not all(s.homed[: s.joints]):
            return "off"
        if s.interp_state != linuxcnc.INTERP_IDLE or s.queue > 0 or not s.inpos:
            return "measuring" if self.cycle else "cutting"
        return "measuring" if self.cycle else "idle"

    def report(self, now):
        state = self.machine_state()
        if state != self.state:
            self.state = state
            program = os.path.basename(self.s.file) if self.s.file else None
            self.outbox.add("/machine/state", {"state": state, "program": program})
        rpm = abs(float(self.s.spindle[0]["speed"])) if self.s.spindle[0]["enabled"] else 0.0
        if rpm != self.rpm or (rpm > 0 and now - self.rpm_sent >= 10.0):
            self.rpm, self.rpm_sent = rpm, now
            self.outbox.add("/spindle", {"rpm": rpm})
        if self.temperatures and now - self.temp_sent >= 60.0:
            self.temp_sent = now
            for sensor, pin in self.temperatures.items():
                try:
                    self.outbox.add("/temperature", {"sensor": sensor, "celsius": self.hal.get(pin)})
                except (RuntimeError, ValueError, subprocess.SubprocessError) as e:
                    journal("temperature_unread", sensor=sensor, pin=pin, error=str(e))

    def messages(self):
        out = []
        while (m := self.e.poll()) is not None:
            out.append(m)
        return out

    def mdi(self, commands):
        if not commands:
            return
        self.c.mode(linuxcnc.MODE_MDI)
        self.c.wait_complete()
        for cmd in commands:
            self.c.mdi(cmd)
            self.c.wait_complete(30)

    # --- cycles ----------------------------------------------------------------------------

    def start_cycle(self, order):
        why = self.program.mismatch(order)
        if order["cycle"] in self.ran:
            # A cycle runs once: one that ended without all its trips is the service's to close
            # (it does when the state leaves measuring, or at its timeout) or to retry under a
            # new number, never the gateway's to repeat on its own.
            why = f"cycle {order['cycle']} already ran here ({self.ran[order['cycle']]})"
        if why:
            if self.refused_order != order["cycle"]:
                self.refused_order = order["cycle"]
                journal("order_refused", cycle=order["cycle"], reason=why)
            return
        self.messages()  # what was said before the cycle is not the cycle's
        self.ran[order["cycle"]] = "running"
        self.cycle = {"order": order, "posted": set(), "last": 0, "errors": [], "t0": time.time(),
                      "seen_running": False, "rpm": 0.0, "left_on": False}
        self.report(time.time())
        journal("cycle_started", cycle=order["cycle"], plan=order["plan"], steps=len(order["steps"]))
        try:
            self.mdi(self.before)
            self.c.mode(linuxcnc.MODE_AUTO)
            self.c.wait_complete()
            self.c.program_open(self.program.path)
            self.c.wait_complete()
            # Not waited on: the task holds a program run "executing" until the program ends
            # (wait_complete would block for its whole timeout), and the trips must be read
            # as they come.
            self.c.auto(linuxcnc.AUTO_RUN, 0)
        except linuxcnc.error as e:
            self.cycle["errors"].append(f"starting the program: {e}")

    def detection(self, step, xyz, status=None):
        cyc = self.cycle
        o = cyc["order"]["steps"][step - 1]
        msg = {"cycle": cyc["order"]["cycle"], "step": o["step"], "b_deg": o["b_deg"],
               "c_deg": o["c_deg"], "axis": o["axis"], "direction": o["direction"],
               "feed_mm_min": o["feed_mm_min"],
               # the speed while the approach ran (an aborted program has stopped the spindle
               # by the time its no_trip is posted)
               "spindle_rpm": cyc["rpm"],
               "tool_id": self.program.tool or "", "x_mm": xyz[0], "y_mm": xyz[1], "z_mm": xyz[2]}
        if status:
            msg["status"] = status
        self.outbox.add("/probe/detection", msg)
        cyc["posted"].add(step)
        cyc["last"] = step
        journal("detection", cycle=msg["cycle"], n=step, step=o["step"], status=status or "ok",
                xyz=[round(v, 6) for v in xyz])

    def follow_cycle(self):
        cyc = self.cycle
        n_steps = len(cyc["order"]["steps"])
        if self.s.spindle[0]["enabled"] and self.s.spindle[0]["speed"]:
            cyc["rpm"] = abs(float(self.s.spindle[0]["speed"]))
        cyc["left_on"] |= self.s.task_state != linuxcnc.STATE_ON
        for kind, text in self.messages():
            m = TRIP_RE.match(text.strip())
            if m and 1 <= int(m.group(1)) <= n_steps:
                self.detection(int(m.group(1)), [float(m.group(i)) for i in (2, 3, 4)])
            elif kind in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR):
                cyc["errors"].append(text.strip())
                journal("control_error", text=text.strip())
        running = self.s.interp_state != linuxcnc.INTERP_IDLE
        cyc["seen_running"] |= running
        if running and time.time() - cyc["t0"] > self.timeout_s:
            self.c.abort()
            cyc["errors"].append(f"the program ran over {self.timeout_s} s: aborted")
            return
        if running or (not cyc["seen_running"] and time.time() - cyc["t0"] < 5.0 and not cyc["errors"]):
            cyc["idle_polls"] = 0
            return
        # Idle on three polls in a row: an E-stop stops the interpreter a task cycle or so
        # before the state says E-stop, and the reason should say which it was.
        cyc["idle_polls"] = cyc.get("idle_polls", 0) + 1
        if cyc["idle_polls"] >= 3:
            self.end_cycle()

    def end_cycle(self):
        cyc = self.cycle
        n_steps = len(cyc["order"]["steps"])
        errors = cyc["errors"]
        # LinuxCNC 2.9: "G38.2 move finished without making contact." (not "Probe tripped
        # during non-probe move.", a trip where none was expected: an error like any other).
        no_contact = [e for e in errors if "without making contact" in e]
        if no_contact and cyc["last"] < n_steps:
            # G38.2 errors out at the end of a move without contact: the step after the last
            # one that tripped, ended where the move ended.
            self.detection(cyc["last"] + 1, list(self.s.position[:3]), status="no_trip")
        if self.s.task_state == linuxcnc.STATE_ESTOP or cyc["left_on"]:
            reason = f"E-stop (or machine off) after step {cyc['last']} of {n_steps}"
        elif no_contact:
            reason = f"no contact at step {cyc['last']} of {n_steps}: {no_contact[0]}"
        elif errors:
            reason = f"stopped after step {cyc['last']} of {n_steps}: {errors[0]}"
        elif len(cyc["posted"]) < n_steps:
            reason = f"the program ended with {len(cyc['posted'])} of {n_steps} trips"
        else:
            reason = "completed"
        journal("cycle_ended", cycle=cyc["order"]["cycle"], reason=reason, trips=len(cyc["posted"]),
                spindle_rpm=cyc["rpm"])
        self.ran[cyc["order"]["cycle"]] = reason
        self.cycle = None
        if self.s.task_state == linuxcnc.STATE_ON and not errors:
            try:
                self.mdi(self.after)
            except linuxcnc.error as e:
                journal("control_error", text=f"after the cycle: {e}")
        self.s.poll()
        self.report(time.time())  # leaving measuring closes the cycle on the service

    # --- compensation ----------------------------------------------------------------------

    def fetch_set(self):
        nominal = ",".join(f"{p}:{v}" for p, v in self.nominal.items())
        q = urllib.parse.urlencode({"format": "linuxcnc", "linuxcnc_nominal": nominal})
        h = {"If-None-Match": self.etag} if self.etag else {}
        r = self.service.call("GET", "/compensation?" + q, headers=h)
        if r is None or r[0] in (304, 404):
            return
        status, headers, body = r
        etag = headers.get("ETag") or headers.get("etag")
        if status != 200:
            if (status, body) != self.refusal:  # said once, not at every poll
                self.refusal = (status, body)
                journal("set_refused_by_service", status=status, answer=body[:500])
            return
        self.refusal = None
        self.etag = etag
        self.pending = body

    def parse_set(self, text):
        version = None
        pins = {}
        for line in text.splitlines():
            t = line.strip()
            if not t:
                continue
            if t.startswith("#"):
                if version is None and (m := SET_RE.search(t)):
                    version = int(m.group(1))
                continue
            words = t.split()
            if len(words) != 3 or words[0] != "setp":
                raise ValueError(f"not a setp line: {t!r}")
            prefix, _, short = words[1].partition(".")
            if prefix != self.kins or short not in PINS:
                raise ValueError(f"{words[1]} is not a pin of {self.kins}")
            value = float(words[2])
            if not math.isfinite(value):
                raise ValueError(f"{words[1]} = {words[2]}")
            pins[words[1]] = value
        if version is None or not pins:
            raise ValueError("no set version or no pin in the answer")
        return version, pins

    def write_set(self):
        """Write the pending set if the machine is idle; refuse it whole, with the reason, if
        any pin would step or stand beyond the limits."""
        text, self.pending = self.pending, None
        try:
            version, pins = self.parse_set(text)
        except ValueError as e:
            journal("set_refused", reason=f"the answer does not parse: {e}")
            return
        if self.written is not None and version <= self.written:
            return
        try:
            now = {p: self.hal.get(p) for p in pins}
        except (RuntimeError, ValueError, subprocess.SubprocessError) as e:
            journal("set_refused", version=version, reason=f"the pins cannot be read: {e}")
            return
        reasons = []
        for p, v in pins.items():
            short = p.partition(".")[2]
            if abs(v - now[p]) > self.max_step_mm:
                reasons.append(f"{p} steps {v - now[p]:+.6f} mm (limit {self.max_step_mm})")
            if short not in self.nominal:
                reasons.append(f"{p} has no commissioned value in the gateway's configuration")
            elif abs(v - self.nominal[short]) > self.max_offset_mm:
                reasons.append(f"{p} stands {v - self.nominal[short]:+.6f} mm from its commissioned value (limit {self.max_offset_mm})")
        if reasons:
            journal("set_refused", version=version, reason="; ".join(reasons))
            return
        try:
            for p, v in pins.items():
                self.hal.set(p, v)
            back = {p: self.hal.get(p) for p in pins}
            wrong = [p for p in pins if abs(back[p] - pins[p]) > 1e-9]
            if wrong:
                raise RuntimeError(f"read back differs: {wrong}")
        except (RuntimeError, ValueError, subprocess.SubprocessError) as e:
            for p, v in now.items():  # what was there before, rather than half a set
                try:
                    self.hal.set(p, v)
                except (RuntimeError, subprocess.SubprocessError):
                    pass
            journal("set_refused", version=version, reason=f"writing failed, previous values restored: {e}")
            return
        self.written = version
        self.written_text, self.written_pins = text, pins
        journal("set_written", version=version, pins=pins,
                steps={p: round(pins[p] - now[p], 6) for p in pins})

    def verify_pins(self):
        """The pins still hold the set last written. LinuxCNC restarted (its HAL file sets the
        commissioned values again) or a hand at halcmd changes them behind the gateway, which
        would otherwise go on believing the machine compensated: the set is written again,
        through the same checks, or refused with the reason."""
        try:
            now = {p: self.hal.get(p) for p in self.written_pins}
        except (RuntimeError, ValueError, subprocess.SubprocessError) as e:
            journal("pins_unread", error=str(e))
            return
        moved = {p: now[p] for p in now if abs(now[p] - self.written_pins[p]) > 1e-9}
        if moved:
            journal("pins_changed", version=self.written, expected=self.written_pins, found=moved)
            self.pending, self.written = self.written_text, None

    # --- the loop --------------------------------------------------------------------------

    def start(self):
        self.s.poll()
        if self.s.interp_state != linuxcnc.INTERP_IDLE and os.path.abspath(self.s.file or "") == self.program.path:
            # A cycle the gateway no longer follows (it was restarted mid-cycle): its trips can
            # no longer be posted, so it is stopped rather than left to run unobserved.
            self.c.abort()
            self.c.wait_complete()
            journal("cycle_ended", cycle=None, reason="the gateway restarted mid-cycle: program aborted", trips=0)
            time.sleep(0.5)
            self.s.poll()
        self.messages()
        journal("started", program=self.program.path, plan=self.program.plan, kinematics=self.kins)

    def run(self):
        self.start()
        while True:
            self.s.poll()
            now = time.time()
            if self.cycle:
                self.follow_cycle()
            else:
                for kind, text in self.messages():
                    if kind in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR):
                        journal("control_error", text=text.strip())
            self.report(now)
            self.outbox.flush()
            if now >= self.next_poll:
                self.next_poll = now + self.poll_s
                self.fetch_set()
                if self.state == "idle" and not self.cycle:
                    r = self.service.call("GET", "/nc/request")
                    if r is not None and r[0] == 200:
                        self.start_cycle(json.loads(r[2]))
            if (self.written_pins and self.pending is None and now >= self.next_verify
                    and self.machine_state() == "idle"):
                self.next_verify = now + 5.0
                self.verify_pins()
            if self.pending is not None:
                if self.machine_state() == "idle":
                    self.write_set()
                elif self.deferred != self.etag:
                    self.deferred = self.etag
                    journal("set_deferred", reason=f"the machine is {self.machine_state()}: "
                            "a set is written only while it is idle and no program runs")
            time.sleep(0.05 if self.cycle else 0.2)


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    with open(sys.argv[1], "rb") as f:
        cfg = tomllib.load(f)
    try:
        Gateway(cfg).run()
    except KeyboardInterrupt:
        journal("stopped")


if __name__ == "__main__":
    main()
