#!/usr/bin/env python3
"""The loop with a real control: driftwatch orders cycles, LinuxCNC runs the measurement
program, the gateway posts the trips and writes the served sets into LinuxCNC's kinematics,
and the tool tip shows the gain.

    loop.py DRIFTWATCH_BINARY WORKDIR [--family bc ac] [--faults bc]

Per family (bc: xyzbc-trt-kins, ac: xyzac-trt-kins), as separate processes: `driftwatch serve`
(the nc_push link, the wall clock), LinuxCNC 2.9's headless simulation (tests/linuxcnc: its
INI, HAL and the truth component `dwtruth`, whose lines the test sets from named location
errors by docs/kinematics-conventions.md), and deploy/linuxcnc/dw_gateway.py. The truth
drifts between cycles. After each served set the test commands fixed poses in TCP mode and
reads the true tip (dwtruth) three times: with the pins as commissioned, as the gateway wrote
them, and as the truth's lines set them (the C line through its crossing of z = 0, the tilting
line through its point; its tilts no pin holds). Faults (on the
families given to --faults): a probe move without contact, E-stop mid-cycle, the gateway
killed mid-cycle, the service down mid-cycle, the pins reset behind the gateway. Every check prints a line; the figures go to
WORKDIR/report.json; exit status 1 when a check fails.

LinuxCNC refuses to run as root (rtapi_app), so as root LinuxCNC, the gateway and the pose
script run as the user `lcnc` (created when missing) through runuser, with a HOME of the
family's own, and the families run at once, each in namespaces of its own (apart). The truth
component must be installed (`halcompile --install tests/linuxcnc/dwtruth.comp`, as root); as
root this script does it when it is missing.
"""
import argparse
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(ROOT, "tests", "python"))
from served import stop, wait_served  # noqa: E402

USER = "lcnc"
TOKEN = "linuxcnc-gateway-token"
MACHINE_ID = "lcnc-1"
UM = 1e-3  # mm per um
URAD = 1e-6

FAMILIES = {
    "bc": {
        "ini": "xyzbc-trt.ini",
        "machine": "xyzbc-trt",
        "kins": "xyzbc-trt-kins",
        "tilt": "B",
        "held": ["x-rot-point", "y-rot-point", "x-offset", "z-offset"],
        # The truth at each cycle (um, urad): the B and C lines drift between cycles, the C
        # line's tilts (which no pin holds) stay. The B line's own tilts are 0: driftwatch
        # holds them at 0.
        "states": [
            {"EX0B": 12.0, "EZ0B": -20.0, "EX0C": 8.0, "EY0C": -6.0, "EA0C": 20.0, "EB0C": -15.0},
            {"EX0B": 18.0, "EZ0B": -45.0, "EX0C": 11.0, "EY0C": -9.0, "EA0C": 25.0, "EB0C": -12.0},
        ],
        "poses": [[60, 40, 30, 30, 0], [60, 40, 30, -30, 90], [-50, 60, 20, 45, -135],
                  [40, -70, 50, -60, 45], [0, 50, 80, 90, 180], [-70, -30, 10, -90, -60],
                  [30, 30, 100, 15, 270], [80, 0, 40, -45, 0]],
    },
    "ac": {
        "ini": "xyzac-trt.ini",
        "machine": "xyzac-trt",
        "kins": "xyzac-trt-kins",
        "tilt": "A",
        "held": ["x-rot-point", "y-rot-point", "y-offset", "z-offset"],
        "states": [
            {"EY0A": 10.0, "EZ0A": -25.0, "EX0C": 7.0, "EY0C": -5.0, "EA0C": 18.0, "EB0C": -14.0},
            {"EY0A": 16.0, "EZ0A": -48.0, "EX0C": 10.0, "EY0C": -8.0, "EA0C": 22.0, "EB0C": -10.0},
        ],
        "poses": [[60, 40, 30, -30, 0], [60, 40, 30, 30, 90], [-50, 60, 20, -45, -135],
                  [40, -70, 50, -60, 45], [0, 50, 80, -90, 180], [-70, -30, 10, -90, -60],
                  [30, 30, 100, -15, 270], [80, 0, 40, 20, 0]],
    },
}

results = {"checks": [], "families": {}}


def check(ok, what):
    results["checks"].append({"ok": bool(ok), "what": what})
    print(("ok   " if ok else "FAIL ") + what, flush=True)
    return ok


def log(*a):
    print("[loop %s]" % time.strftime("%H:%M:%S"), *a, flush=True)


# --- the truth, from docs/kinematics-conventions.md ---------------------------------------

def truth_lines(family, e):
    """The truth component's lines (mm, unit vectors) from named errors (um, urad)."""
    g = lambda n: e.get(n, 0.0)  # noqa: E731
    ea, eb = g("EA0C") * URAD, g("EB0C") * URAD
    # u_C = Ry(EB0C) * Rx(EA0C) * (0, 0, 1), as seen at tilt 0
    cu = (math.cos(ea) * math.sin(eb), -math.sin(ea), math.cos(ea) * math.cos(eb))
    if family == "bc":
        a, c = g("EA0B") * URAD, g("EC0B") * URAD
        tq = (g("EX0B") * UM, 0.0, g("EZ0B") * UM)
        tu = (-math.sin(c) * math.cos(a), math.cos(c) * math.cos(a), math.sin(a))
        cq = ((g("EX0B") + g("EX0C")) * UM, g("EY0C") * UM, 0.0)
    else:
        b, c = g("EB0A") * URAD, g("EC0A") * URAD
        tq = (0.0, g("EY0A") * UM, g("EZ0A") * UM)
        tu = (math.cos(c) * math.cos(b), math.sin(c) * math.cos(b), -math.sin(b))
        cq = (g("EX0C") * UM, (g("EY0A") + g("EY0C")) * UM, 0.0)
    pins = {}
    for name, v in (("tq", tq), ("tu", tu), ("cq", cq), ("cu", cu)):
        for axis, x in zip("xyz", v):
            pins[f"{name}-{axis}"] = x
    return pins


def ideal_pins(family, lines):
    """What LinuxCNC's trt kinematics can hold of the truth's lines: the C line vertical
    through rot-point (its crossing of z = 0), the tilting line through rot-point + offset
    (trtfuncs.c: joints = rp + D + R_tilt * (R_C * (p - rp) - D))."""
    out = {"x-rot-point": lines["cq-x"], "y-rot-point": lines["cq-y"], "z-offset": lines["tq-z"]}
    if family == "bc":
        out["x-offset"] = lines["tq-x"] - lines["cq-x"]
    else:
        out["y-offset"] = lines["tq-y"] - lines["cq-y"]
    return out


# --- processes -----------------------------------------------------------------------------

# The HOME of every process of this rig. LinuxCNC's clients find the tool table's shared file
# (and rtapi_app its socket) in $HOME, so a rig's processes share one and two rigs running at
# once must not: as root each family gets its own (rig_home), as another user it is the user's.
home = os.environ.get("HOME", "")


def rig_home(work):
    """A HOME for the rig working in `work` (as root; `prepare` hands `work` to LinuxCNC's user)."""
    global home
    home = os.path.join(work, "home")
    os.makedirs(home, exist_ok=True)


def as_user(cmd):
    """cmd as LinuxCNC's user, with the rig's HOME."""
    if os.getuid() != 0:
        return cmd
    return ["runuser", "-u", USER, "--", "env", "HOME=" + home] + cmd


def run(cmd, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, **kw)


def halcmd(*args):
    r = run(as_user(["halcmd", "-s", *args]))
    if r.returncode != 0:
        raise RuntimeError(f"halcmd {' '.join(args)}: {r.stderr.strip() or r.stdout.strip()}")
    return r.stdout.strip()


def getp(pin):
    return float(halcmd("getp", pin))


def setp(pin, value):
    halcmd("setp", pin, repr(float(value)))


def lcnc_py(code, timeout=60):
    """A few lines of the linuxcnc module as LinuxCNC's user (its NML memory is that user's)."""
    pre = "import linuxcnc, time\ns = linuxcnc.stat(); c = linuxcnc.command()\n"
    r = subprocess.run(as_user(["/usr/bin/python3", "-c", pre + code]), capture_output=True,
                       text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(f"linuxcnc: {r.stderr.strip()[-500:]}")
    return r.stdout


def free_port():
    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return so.getsockname()[1]


class Api:
    def __init__(self, base):
        self.base = base + "/api/v1/machines/" + MACHINE_ID

    def get(self, path, raw=False):
        req = urllib.request.Request(self.base + path, headers={"Authorization": "Bearer " + TOKEN})
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                body = r.read().decode()
                return r.status, (body if raw else json.loads(body or "null"))
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode()
        except (urllib.error.URLError, OSError) as e:
            return None, str(e)

    def post(self, path, body):
        req = urllib.request.Request(self.base + path, data=json.dumps(body).encode(), method="POST",
                                     headers={"Authorization": "Bearer " + TOKEN,
                                              "Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, r.read().decode()
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode()


class Journal:
    """The gateway's journal (its stdout, one JSON object a line), read as it grows."""

    def __init__(self, path):
        self.path = path
        self.entries = []
        self.offset = 0

    def read(self):
        if os.path.exists(self.path):
            with open(self.path) as f:
                f.seek(self.offset)
                for line in f:
                    if not line.endswith("\n"):
                        break
                    self.offset += len(line.encode())
                    try:
                        self.entries.append(json.loads(line))
                    except json.JSONDecodeError:
                        pass
        return self.entries

    def wait(self, pred, timeout, what):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for e in self.read():
                if pred(e):
                    return e
            time.sleep(0.2)
        raise TimeoutError(f"no {what} within {timeout} s (gateway journal {self.path})")


class Rig:
    """One family's service, LinuxCNC and gateway."""

    def __init__(self, binary, family, work):
        self.binary, self.family, self.work = binary, family, work
        self.f = FAMILIES[family]
        self.service = self.gateway = self.lcnc = None
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.api = Api(self.base)
        self.journal = Journal(os.path.join(work, "gateway.jsonl"))
        self.gateway_starts = 0

    def prepare(self):
        w = self.work
        os.makedirs(w, exist_ok=True)
        for name in (self.f["ini"], "sim.hal", "bc.hal", "ac.hal", "sim.tbl", "display.py", "poses.py"):
            shutil.copy(os.path.join(HERE, name), w)
        shutil.copy(os.path.join(ROOT, "deploy", "linuxcnc", "dw_gateway.py"), w)
        self.machine = os.path.join(ROOT, "deploy", "linuxcnc", "machines", self.f["machine"] + ".toml")
        self.program = os.path.join(w, "dw9100.ngc")
        r = run([self.binary, "nc", "program", "--machine", self.machine, "--dialect", "iso",
                 "--out", self.program])
        if r.returncode != 0:
            raise RuntimeError(f"nc program: {r.stderr}")
        with open(os.path.join(w, "driftwatch.toml"), "w") as f:
            f.write(f"""data_dir = "unused"
time_scale = 1.0
max_file_mib = 256
[http]
listen = "127.0.0.1:{self.port}"
anonymous_read = false
tokens = [{{ name = "gateway", token = "env:DW_TOKEN", role = "write" }}]
[[machines]]
id = "{MACHINE_ID}"
machine = "{self.machine}"
link = {{ kind = "nc_push" }}
alerts = []                    # the shipped rules watch table_bc's errors
[schedule]
max_retries = 0                # the test orders every cycle after the first itself
""")
        nominal = ", ".join(f'"{p}" = 0.0' for p in self.f["held"])
        with open(os.path.join(w, "gateway.toml"), "w") as f:
            f.write(f"""[service]
url = "{self.base}"
machine = "{MACHINE_ID}"
token = "env:DW_TOKEN"
poll_s = 0.5
[program]
path = "{self.program}"
before_mdi = ["M429"]
after_mdi = ["M428"]
timeout_s = 300
[kinematics]
component = "{self.f['kins']}"
nominal = {{ {nominal} }}
max_step_mm = 0.05
max_offset_mm = 0.2
""")
        if os.getuid() == 0:
            if run(["id", USER]).returncode != 0:
                run(["useradd", "-m", USER])
            rig_home(w)
            run(["chown", "-R", USER, w])
            if run(as_user(["test", "-r", os.path.join(w, self.f["ini"])])).returncode != 0:
                raise RuntimeError(f"the user {USER} cannot reach {w}: every directory above it "
                                   "must be searchable by others (chmod o+x; mktemp -d makes 700)")

    def start_service(self):
        log_path = os.path.join(self.work, "service.log")
        offset = os.path.getsize(log_path) if os.path.exists(log_path) else 0
        log = open(log_path, "ab")
        self.service = subprocess.Popen(
            [self.binary, "serve", "--config", os.path.join(self.work, "driftwatch.toml"),
             "--data-dir", os.path.join(self.work, "data")],
            env=dict(os.environ, RUST_LOG="warn", DW_TOKEN=TOKEN), stdout=log, stderr=subprocess.STDOUT)
        if wait_served(self.service, log_path, offset) is None:
            raise RuntimeError(f"the service did not start (see {log_path})")

    def start_lcnc(self):
        hold = os.path.join(self.work, "hold")
        open(hold, "w").close()
        self.hold = hold
        out = open(os.path.join(self.work, "linuxcnc.out"), "wb")
        env = {"PATH": "/usr/bin:/bin", "DW_HOLD": hold, "HOME": home}
        self.lcnc = subprocess.Popen(as_user(["env", "-i"] + [f"{k}={v}" for k, v in env.items()]
                                             + ["linuxcnc", "-r", os.path.join(self.work, self.f["ini"])]),
                                     cwd=self.work, stdout=out, stderr=subprocess.STDOUT)
        end = time.monotonic() + 90
        while time.monotonic() < end:
            if self.lcnc.poll() is not None:
                raise RuntimeError("LinuxCNC ended while starting (see linuxcnc.out)")
            try:
                if halcmd("getp", "motion.is-all-homed") == "TRUE":
                    return
            except RuntimeError:
                pass
            time.sleep(0.5)
        raise RuntimeError("LinuxCNC not homed within 90 s (see linuxcnc.out)")

    def start_gateway(self):
        self.gateway_starts += 1
        out = open(self.journal.path, "ab")
        self.gateway = subprocess.Popen(
            as_user(["env", f"DW_TOKEN={TOKEN}", "PATH=/usr/bin:/bin", "/usr/bin/python3",
                     os.path.join(self.work, "dw_gateway.py"), os.path.join(self.work, "gateway.toml")]),
            cwd=self.work, stdout=out, stderr=open(os.path.join(self.work, "gateway.err"), "ab"))
        n = self.gateway_starts
        self.journal.wait(lambda e: e["kind"] == "started" and self._count_started() >= n, 30, "gateway start")

    def _count_started(self):
        return sum(1 for e in self.journal.entries if e["kind"] == "started")

    def kill_gateway(self):
        # As root the gateway runs under runuser: kill the Python process itself.
        run(["pkill", "-9", "-f", os.path.join(self.work, "dw_gateway.py")])
        self.gateway.wait(timeout=10)

    def pause_gateway(self, paused):
        """Stop (SIGSTOP) or continue the gateway: while the test sets the pins itself to read
        the tip, the gateway must not put its set back."""
        sig = "-STOP" if paused else "-CONT"
        run(["pkill", sig, "-f", os.path.join(self.work, "dw_gateway.py")])

    def set_truth(self, errors):
        for pin, v in truth_lines(self.family, errors).items():
            setp(f"dwtruth.0.{pin}", v)

    def pins(self):
        return {p: getp(f"{self.f['kins']}.{p}") for p in self.f["held"]}

    def set_pins(self, values):
        for p, v in values.items():
            setp(f"{self.f['kins']}.{p}", v)

    def sweep(self):
        path = os.path.join(self.work, "poses.json")
        with open(path, "w") as f:
            json.dump({"tilt": self.f["tilt"], "poses": self.f["poses"]}, f)
        r = run(as_user(["/usr/bin/python3", os.path.join(self.work, "poses.py"), path]))
        if r.returncode != 0:
            raise RuntimeError(f"poses: {r.stderr.strip()[-800:]}")
        out = json.loads(r.stdout)
        errs = [[(t - c) / UM for t, c in zip(p["tip"], p["commanded"][:3])] for p in out["poses"]]
        norms = [math.sqrt(sum(v * v for v in e)) for e in errs]
        return {"rms_um": math.sqrt(sum(n * n for n in norms) / len(norms)), "max_um": max(norms),
                "per_pose_um": [[round(v, 3) for v in e] for e in errs]}

    def stop(self):
        if self.gateway and self.gateway.poll() is None:
            self.kill_gateway()
        if self.lcnc:
            if os.path.exists(self.hold):
                os.remove(self.hold)
            try:
                self.lcnc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.lcnc.kill()
            run(as_user(["halrun", "-U"]))
        if self.service:
            stop(self.service)


def served_form(rig):
    """The set as the service serves it to this gateway (?format=linuxcnc), as pin values."""
    q = "format=linuxcnc&linuxcnc_nominal=" + ",".join(f"{p}:0" for p in rig.f["held"])
    status, text = rig.api.get("/compensation?" + q, raw=True)
    if status != 200:
        return None
    pins = {}
    for line in text.splitlines():
        w = line.split()
        if len(w) == 3 and w[0] == "setp":
            pins[w[1].partition(".")[2]] = float(w[2])
    return pins


def wait_cycle_end(rig, after, timeout=300):
    return rig.journal.wait(lambda e: e["kind"] == "cycle_ended" and e["t"] > after, timeout, "cycle end")


def cycle_record(rig, n, timeout=60):
    """The service's record of cycle n (its row: status, reason) once it is closed."""
    end = time.monotonic() + timeout
    status, body = None, None
    while time.monotonic() < end:
        status, body = rig.api.get(f"/cycles/{n}")
        if status == 200 and body["cycle"]["status"] != "open":
            return body["cycle"]
        time.sleep(0.5)
    return {"cycle": n, "status": f"not closed within {timeout} s", "reason": f"last answer {status}: {str(body)[:200]}"}


def one_cycle(rig, k, state, report):
    """Cycle k of the family's drift: the truth moves, a cycle is ordered (the first by the
    scheduler), measured, validated, served and written; then the tip at the poses."""
    fam = rig.family
    t0 = time.time()
    if k > 0:
        rig.set_truth(state)
        status, body = rig.api.post("/cycles", {})
        check(status == 202, f"{fam} cycle {k + 1}: ordered by request ({status} {body[:200]})")
    ended = wait_cycle_end(rig, t0)
    check(ended["reason"] == "completed", f"{fam} cycle {ended['cycle']}: LinuxCNC ran it to the end "
          f"({ended['trips']} trips; {ended['reason']})")
    written = rig.journal.wait(lambda e: e["kind"] == "set_written" and e["t"] > t0, 60, "set written")
    wall = time.time() - t0
    status, comp = rig.api.get("/compensation")
    errs, sig = comp["errors"], comp["sigma"]
    z = {n: (errs[n] - state[n]) / sig[n] for n in errs}
    check(all(abs(v) < 4.0 for v in z.values()),
          f"{fam} cycle {ended['cycle']}: identified against the truth, z = "
          + ", ".join(f"{n} {v:+.2f}" for n, v in z.items()))
    deferred = [e for e in rig.journal.entries if e["kind"] == "set_deferred" and t0 < e["t"] <= written["t"]]
    check(written["t"] >= ended["t"],
          f"{fam} set {written['version']}: written after the program ended"
          + (f" (it arrived while the program ran and waited: {deferred[0]['reason']})" if deferred else ""))
    pins = rig.pins()
    form = served_form(rig)
    check(form is not None and written["version"] == comp["version"]
          and all(abs(pins[p] - form[p]) < 1e-9 for p in form)
          and all(abs(pins[p]) < 1e-12 for p in pins if p not in form),
          f"{fam} set {comp['version']}: the pins hold exactly the served set's values ({pins})")
    rig.pause_gateway(True)
    try:
        served = rig.sweep()
        rig.set_pins({p: 0.0 for p in rig.f["held"]})
        commissioned = rig.sweep()
        ideal_values = ideal_pins(fam, truth_lines(fam, state))
        rig.set_pins(ideal_values)
        ideal = rig.sweep()
        rig.set_pins(pins)
    finally:
        rig.pause_gateway(False)
    removable = commissioned["rms_um"] - ideal["rms_um"]
    share = (commissioned["rms_um"] - served["rms_um"]) / removable if removable > 0 else float("nan")
    check(served["rms_um"] < commissioned["rms_um"] and share > 0.8,
          f"{fam} set {comp['version']}: tip error RMS {commissioned['rms_um']:.2f} um as commissioned, "
          f"{served['rms_um']:.2f} um served, {ideal['rms_um']:.2f} um with the truth's lines in the pins "
          f"(max {commissioned['max_um']:.2f} / {served['max_um']:.2f} / {ideal['max_um']:.2f}): "
          f"the served set removes {100 * share:.1f} % of what the truth's lines remove")
    report["cycles"].append({
        "cycle": ended["cycle"], "version": comp["version"], "truth": state, "identified": errs,
        "sigma": sig, "z": z, "pins": pins, "ideal_pins": ideal_values,
        "set_deferred_while_running": len(deferred), "cycle_to_written_s": round(wall, 1),
        "tip": {"commissioned": commissioned, "served": served, "ideal": ideal, "share_removed": share}})


def mid_cycle(rig, after, n_trips=3):
    """Wait until the running cycle has posted n_trips detections."""
    return rig.journal.wait(lambda e: e["kind"] == "detection" and e["t"] > after and e["n"] >= n_trips,
                            120, f"trip {n_trips}")


def recover_machine():
    lcnc_py("c.state(linuxcnc.STATE_ESTOP_RESET); c.state(linuxcnc.STATE_ON); c.wait_complete()\n"
            "c.mode(linuxcnc.MODE_MANUAL); c.wait_complete(); c.home(-1)\n"
            "end = time.time() + 30\n"
            "while time.time() < end:\n"
            "    s.poll()\n"
            "    if s.task_state == linuxcnc.STATE_ON and all(s.homed[:5]): break\n"
            "    time.sleep(0.1)\n")


def faults(rig, report):
    fam = rig.family
    out = report["faults"] = []

    def case(name, provoke, expect_reason):
        before = rig.pins()
        version = rig.api.get("/compensation")[1]["version"]
        t0 = time.time()
        status, body = rig.api.post("/cycles", {})
        if status != 202:
            check(False, f"{fam} fault '{name}': cycle not ordered ({status} {body[:200]})")
            return
        provoke(t0)
        ended = wait_cycle_end(rig, t0, 120)
        started = [e for e in rig.journal.entries if e["kind"] == "cycle_started" and e["t"] > t0]
        record = cycle_record(rig, started[0]["cycle"], 90) if started else None
        time.sleep(2.0)  # a set, were one served, would be written within the gateway's poll
        after = rig.pins()
        v_after = rig.api.get("/compensation")[1]["version"]
        same = all(abs(after[p] - before[p]) < 1e-12 for p in before)
        reasons = record and f"cycle {record['cycle']} {record['status']}: {record['reason']}"
        out.append({"fault": name, "gateway_reason": ended["reason"], "service_record": record,
                    "pins_before": before, "pins_after": after, "served_before": version,
                    "served_after": v_after})
        check(same and v_after == version and expect_reason in ended["reason"],
              f"{fam} fault '{name}': nothing written (pins unchanged, served set {v_after} as before); "
              f"gateway: {ended['reason']}; service: {reasons}")

    # A probe move without contact: the beam is 30 mm off its place, the first approach misses.
    py = getp("dwtruth.0.beam-py")
    setp("dwtruth.0.beam-py", py - 30.0)
    try:
        case("probe move without contact", lambda t0: None, "no contact")
    finally:
        setp("dwtruth.0.beam-py", py)

    def estop(t0):
        mid_cycle(rig, t0)
        lcnc_py("c.state(linuxcnc.STATE_ESTOP)")

    case("E-stop mid-cycle", estop, "E-stop")
    recover_machine()

    def kill(t0):
        mid_cycle(rig, t0)
        rig.kill_gateway()
        rig.start_gateway()

    case("gateway killed mid-cycle", kill, "restarted mid-cycle")

    def service_down(t0):
        mid_cycle(rig, t0)
        stop(rig.service)
        time.sleep(3.0)
        rig.start_service()

    case("service down mid-cycle", service_down, "")

    # LinuxCNC's pins set back to their commissioned values behind the gateway (a restart of
    # LinuxCNC, a hand at halcmd): the gateway notices and writes the served set again.
    t0 = time.time()
    held = rig.pins()
    rig.set_pins({p: 0.0 for p in rig.f["held"]})
    changed = rig.journal.wait(lambda e: e["kind"] == "pins_changed" and e["t"] > t0, 30, "pins_changed")
    again = rig.journal.wait(lambda e: e["kind"] == "set_written" and e["t"] > t0, 30, "the set written again")
    after = rig.pins()
    out.append({"fault": "pins reset behind the gateway", "found": changed["found"],
                "rewritten_version": again["version"], "pins_after": after})
    check(all(abs(after[p] - held[p]) < 1e-9 for p in held),
          f"{fam} fault 'pins reset behind the gateway': noticed ({changed['found']}) and set {again['version']} "
          f"written again ({after})")


def family(binary, fam, work, with_faults):
    rig = Rig(binary, fam, work)
    report = results["families"][fam] = {"cycles": []}
    t_start = time.time()
    try:
        rig.prepare()
        rig.start_service()
        rig.start_lcnc()
        rig.set_truth(FAMILIES[fam]["states"][0])
        rig.start_gateway()
        for k, state in enumerate(FAMILIES[fam]["states"]):
            one_cycle(rig, k, state, report)
        if with_faults:
            faults(rig, report)
    except (RuntimeError, TimeoutError, KeyError, TypeError, ValueError) as e:
        check(False, f"{fam}: {type(e).__name__}: {e}")
    finally:
        rig.stop()
    report["wall_s"] = round(time.time() - t_start, 1)
    log(f"{fam}: {report['wall_s']} s")


def install_truth():
    """As root the component is built and installed every run (2 s), so it is this tree's."""
    if os.getuid() != 0 and os.path.exists("/usr/lib/linuxcnc/modules/dwtruth.so"):
        return
    if os.getuid() != 0:
        sys.exit("the truth component is not installed: halcompile --install tests/linuxcnc/dwtruth.comp (as root)")
    tmp = "/tmp/dwtruth-build"
    os.makedirs(tmp, exist_ok=True)
    shutil.copy(os.path.join(HERE, "dwtruth.comp"), tmp)
    r = run(["halcompile", "--install", "dwtruth.comp"], cwd=tmp)
    if r.returncode != 0:
        sys.exit(f"halcompile: {r.stdout}{r.stderr}")


def can_part():
    """Whether this process may make the namespaces `apart` needs (root in a container without
    the capability to may not): else the families run one after the other."""
    if os.getuid() != 0 or not (shutil.which("unshare") and shutil.which("ip")):
        return False
    probe = ["unshare", "--ipc", "--pid", "--net", "--mount", "--mount-proc", "--fork", "--",
             "ip", "link", "set", "lo", "up"]
    return subprocess.run(probe, capture_output=True, timeout=30).returncode == 0


def apart(binary, families, faults, work):
    """Each family in a process of its own, all at once, in namespaces of their own (as root):
    two LinuxCNCs on one host share HAL's and NML's System V memory (IPC), the `linuxcnc`
    script's clean-up kills another session's tasks by name (PID, with its own /proc), and
    the NML server binds TCP 5005 (network: each namespace brings its loopback up, and the
    family's service listens there). The shell stays the namespace's first process, so that
    it reaps what LinuxCNC's script leaves behind (a task the script waits to see gone must
    not linger as a zombie). Each family's output is printed, and its report merged, in order."""
    kids = []
    for fam in families:
        os.makedirs(os.path.join(work, fam), exist_ok=True)
        out = os.path.join(work, fam + ".out")
        cmd = ["unshare", "--ipc", "--pid", "--net", "--mount", "--mount-proc", "--fork",
               "--kill-child", "--", "sh", "-c", 'ip link set lo up && "$@"', "sh",
               sys.executable, os.path.abspath(__file__), binary, work, "--family", fam,
               "--faults", *[f for f in faults if f == fam],
               "--report", os.path.join(work, fam, "report.json"), "--installed"]
        with open(out, "wb") as log:
            kids.append((fam, out, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)))
    for fam, out, p in kids:
        p.wait()
        with open(out) as f:
            sys.stdout.write(f.read())
        try:
            with open(os.path.join(work, fam, "report.json")) as f:
                r = json.load(f)
        except (OSError, ValueError) as e:
            r = {"checks": [{"ok": False, "what": f"{fam}: no report ({e}; exit status {p.returncode})"}],
                 "families": {}}
            print("FAIL " + r["checks"][0]["what"], flush=True)
        results["checks"] += r["checks"]
        results["families"].update(r["families"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("work")
    ap.add_argument("--family", nargs="+", default=["bc", "ac"], choices=sorted(FAMILIES))
    ap.add_argument("--faults", nargs="*", default=["bc"], choices=sorted(FAMILIES))
    ap.add_argument("--report", help="where the report goes (default WORK/report.json)")
    ap.add_argument("--installed", action="store_true",
                    help="the truth component is installed already (a family run apart)")
    a = ap.parse_args()
    report = a.report or os.path.join(a.work, "report.json")
    if not a.installed:
        install_truth()
    t0 = time.time()
    if len(a.family) > 1 and can_part():
        apart(os.path.abspath(a.binary), a.family, a.faults, os.path.abspath(a.work))
    else:
        for fam in a.family:
            family(os.path.abspath(a.binary), fam, os.path.join(os.path.abspath(a.work), fam), fam in a.faults)
    results["wall_s"] = round(time.time() - t0, 1)
    with open(report, "w") as f:
        json.dump(results, f, indent=1)
    failed = [c for c in results["checks"] if not c["ok"]]
    print(f"linuxcnc loop: {len(results['checks']) - len(failed)} of {len(results['checks'])} checks "
          f"passed in {results['wall_s']} s (report {report})")
    sys.exit(1 if failed or not results["checks"] else 0)


if __name__ == "__main__":
    main()
