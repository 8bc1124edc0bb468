"""Kill -9 harness: `driftwatch serve` killed with SIGKILL at random moments, on the simulated
link and on the nc_push link (a Python NC posting events and replaying a simulated cycle's
detections for each order), then started again on the same data directory.

usage: python3 kill_harness.py BINARY OUTDIR [--sim N] [--nc N] [--seed S] [--run-after-s S]

Each simulated trial runs a fresh data directory at 600x, is killed 0.3-2 s after it answers
(every other trial as soon as a cycle is seen running: a cycle takes 0.1 s of wall time),
restarted, checked, run `--run-after-s` more wall seconds (default 1, 10 min of the plant day)
and stopped; its cycles are counted, and any rejected because its set would lie before the
served one fails the series (the restarted plant must go on from the store's time). The
nc_push trials share one data directory on the wall clock: the NC runs operator-requested
cycles back to back, and the service is killed 0.3-2 s into each trial, mid-cycle included
(while the NC posts a cycle's detections), and started again. The nc_push series and the two
halves of the simulated one run at once, in processes of their own; --seed gives the same
kill moments as when the series ran in turn. After every restart:
- lost: a cycle seen `ok` before the kill that is not `ok` after it;
- versions back: the served compensation version below the highest seen before the kill;
- and at the end of each series (clean stop), unreadable: recording files the independent
  reader (check_daemon_files.py, the `mcap` package) refuses, and `.partial` files left.
Prints one line per series and a total; exits 1 if anything was lost, went back or is
unreadable.
"""
import argparse
import concurrent.futures
import json
import multiprocessing
import os
import random
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

from served import wait_served

HERE = os.path.dirname(os.path.abspath(__file__))
TOKEN = "harness-token"


def parse(text):
    try:
        return json.loads(text) if text else None
    except ValueError:
        return None


def call(base, method, path, body=None, token=None, timeout=2.0):
    """(status, JSON or None); (0, None) when the service does not answer."""
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(base + path, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", "Bearer " + token)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, parse(r.read())
    except urllib.error.HTTPError as e:
        return e.code, parse(e.read())
    except (urllib.error.URLError, OSError):
        return 0, None


class Service:
    def __init__(self, binary, data, log, config=None, scale=None):
        args = [binary, "serve", "--listen", "127.0.0.1:0", "--data-dir", data]
        if config:
            args += ["--config", config]
        if scale:
            args += ["--time-scale", str(scale), "--until", "100000"]
        env = dict(os.environ, RUST_LOG="warn", DRIFTWATCH_NC_TOKEN=TOKEN,
                   DRIFTWATCH_OPERATOR_TOKEN=TOKEN)
        offset = os.path.getsize(log) if os.path.exists(log) else 0
        self.log = open(log, "ab")
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=self.log, env=env)
        self.base = wait_served(self.proc, log, offset)
        if self.base is None:
            raise RuntimeError(f"serve did not say where it listens within 30 s; see {log}")
        deadline = time.time() + 30
        while time.time() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"serve exited with {self.proc.returncode}; see {log}")
            if call(self.base, "GET", "/healthz")[0] == 200:
                return
            time.sleep(0.05)
        raise RuntimeError(f"serve did not answer within 30 s; see {log}")

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)
        self.log.close()

    def stop(self):
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise RuntimeError("serve did not stop within 20 s of SIGTERM")
        finally:
            self.log.close()


class Watch:
    """What a reader saw before the kill: the highest version, the ok cycles."""

    def __init__(self):
        self.version = 0
        self.ok = set()
        self.mid_cycle = False

    def look(self, svc, machine):
        s, c = call(svc.base, "GET", f"/api/v1/machines/{machine}/compensation")
        if s == 200 and c:
            self.version = max(self.version, c["version"])
        s, cycles = call(svc.base, "GET", f"/api/v1/machines/{machine}/cycles?limit=1000")
        if s == 200:
            self.ok |= {c["cycle"] for c in cycles if c["status"] == "ok"}
        s, m = call(svc.base, "GET", f"/api/v1/machines/{machine}")
        self.mid_cycle = s == 200 and m.get("open_cycle") is not None

    def compare(self, svc, machine):
        """(lost, versions back) after a restart."""
        s, c = call(svc.base, "GET", f"/api/v1/machines/{machine}/compensation")
        back = int(self.version > 0 and (s != 200 or c["version"] < self.version))
        s, cycles = call(svc.base, "GET", f"/api/v1/machines/{machine}/cycles?limit=1000")
        now_ok = {c["cycle"] for c in cycles if c["status"] == "ok"} if s == 200 else set()
        return len(self.ok - now_ok), back


def unreadable(mcap_dir):
    """(files the independent reader refuses or problems it names, partial files left)."""
    partial = [f for f in os.listdir(mcap_dir) if f.endswith(".partial")]
    r = subprocess.run([sys.executable, os.path.join(HERE, "check_daemon_files.py"), "--short",
                        mcap_dir],
                       capture_output=True, text=True)
    bad = 0 if r.returncode == 0 else max(1, r.stdout.count("\n") - 1)
    if r.returncode != 0:
        print(r.stdout + r.stderr, file=sys.stderr)
    return bad, len(partial)


def cycles_by_status(data, machine):
    """(cycles, rejected, rejected because their set would lie before the served one)."""
    db = sqlite3.connect(os.path.join(data, "driftwatch.db"))
    try:
        rows = db.execute("SELECT status, COALESCE(reason, '') FROM cycles WHERE machine_id = ?",
                          (machine,)).fetchall()
    finally:
        db.close()
    rejected = [r for s, r in rows if s == "rejected"]
    return len(rows), len(rejected), sum("before the served set" in r for r in rejected)


def sim_series(binary, out, waits, run_after_s):
    """The simulated trials `waits` names (trial number: seconds before the kill)."""
    totals = dict(trials=0, mid=0, lost=0, back=0, unreadable=0, partial=0, cycles=0,
                  rejected=0, before_served=0)
    for i, wait in waits.items():
        data = os.path.join(out, f"sim-{i}")
        shutil.rmtree(data, ignore_errors=True)
        log = os.path.join(out, f"sim-{i}.log")
        svc = Service(binary, data, log, scale=600)
        w = Watch()
        end = time.time() + wait
        while time.time() < end:
            w.look(svc, "sim-1")
            time.sleep(0.02)
        # Every other trial waits for a cycle to be running (bounded) and kills inside it.
        end = time.time() + (10.0 if i % 2 else 0.0)
        w.look(svc, "sim-1")
        while not w.mid_cycle and time.time() < end:
            w.look(svc, "sim-1")
        svc.kill()
        svc = Service(binary, data, log, scale=600)
        lost, back = w.compare(svc, "sim-1")
        # The restarted plant goes on from where the store left it (not from its morning
        # again, when every cycle after a restart lay before the served set and was rejected).
        time.sleep(run_after_s)
        svc.stop()
        cycles, rejected, before_served = cycles_by_status(data, "sim-1")
        totals["cycles"] += cycles
        totals["rejected"] += rejected
        totals["before_served"] += before_served
        bad, partial = unreadable(os.path.join(data, "mcap", "sim-1"))
        totals["trials"] += 1
        totals["mid"] += int(w.mid_cycle)
        totals["lost"] += lost
        totals["back"] += back
        totals["unreadable"] += bad
        totals["partial"] += partial
    return totals


NC_CONFIG = """
data_dir = "unused"
time_scale = 1.0
max_file_mib = 256
[http]
listen = "127.0.0.1:0"
anonymous_read = true
tokens = [{{ name = "nc", token = "env:DRIFTWATCH_NC_TOKEN", role = "write" }}]
[[machines]]
id = "nc-1"
machine = "table_bc"
plan = "patent"
link = {{ kind = "nc_push" }}
[schedule]
min_spacing_min = 0.0
timeout_min = 1.0
"""


def template_detections(binary, out):
    """The 24 detections of the first cycle of a simulated recording (a real machine's
    trips, as the NC would post them)."""
    from mcap.reader import make_reader
    path = os.path.join(out, "template.mcap")
    subprocess.run([binary, "simulate", "--scenario", "patent", "--out", path], check=True,
                   capture_output=True)
    dets = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/probe/detection"]):
            d = json.loads(message.data)
            if d["cycle"] == 1:
                dets.append(d)
    return dets


class Nc(threading.Thread):
    """The NC: idle with the spindle on, events every 0.1 s, each order run at once by
    replaying the template's detections, a new cycle asked for after each."""

    def __init__(self, template):
        super().__init__(daemon=True)
        self.template = template
        self.base = None
        self.in_cycle = False
        self.stop = False
        self.errors_5xx = 0

    def post(self, events):
        s, _ = call(self.base, "POST", "/api/v1/machines/nc-1/nc/events", {"events": events},
                    TOKEN)
        if s >= 500 and s != 503:
            self.errors_5xx += 1
        return s

    def run(self):
        while not self.stop:
            if self.base is None:
                time.sleep(0.02)
                continue
            now = time.time_ns()
            self.post([
                {"topic": "/spindle", "t_ns": now, "msg": {"rpm": 20000.0}},
                {"topic": "/machine/state", "t_ns": now, "msg": {"state": "idle",
                                                                 "program": "harness"}},
                {"topic": "/temperature", "t_ns": now, "msg": {"sensor": "ambient",
                                                               "celsius": 20.0}},
            ])
            s, order = call(self.base, "GET", "/api/v1/machines/nc-1/nc/request", token=TOKEN)
            if s == 200 and order:
                self.in_cycle = True
                t = time.time_ns()
                self.post([{"topic": "/machine/state", "t_ns": t,
                            "msg": {"state": "measuring", "program": "cycle"}}])
                for d in self.template:
                    d = dict(d, cycle=order["cycle"])
                    self.post([{"topic": "/probe/detection", "t_ns": time.time_ns(), "msg": d}])
                    time.sleep(0.005)
                self.post([{"topic": "/machine/state", "t_ns": time.time_ns(),
                            "msg": {"state": "idle", "program": "harness"}}])
                self.in_cycle = False
            elif s == 204:
                call(self.base, "POST", "/api/v1/machines/nc-1/cycles", {}, TOKEN)
            time.sleep(0.1)


def nc_series(binary, out, trials, rng):
    totals = dict(trials=0, mid=0, lost=0, back=0, unreadable=0, partial=0, nc5xx=0)
    data = os.path.join(out, "nc")
    shutil.rmtree(data, ignore_errors=True)
    config = os.path.join(out, "nc.toml")
    with open(config, "w") as f:
        f.write(NC_CONFIG.format())
    nc = Nc(template_detections(binary, out))
    nc.start()
    log = os.path.join(out, "nc.log")
    svc = Service(binary, data, log, config=config)
    nc.base = svc.base
    w = Watch()
    for _ in range(trials):
        end = time.time() + rng.uniform(0.3, 2.0)
        while time.time() < end:
            w.look(svc, "nc-1")
            time.sleep(0.02)
        w.look(svc, "nc-1")
        mid = nc.in_cycle or w.mid_cycle
        svc.kill()
        svc = Service(binary, data, log, config=config)
        nc.base = svc.base
        lost, back = w.compare(svc, "nc-1")
        totals["trials"] += 1
        totals["mid"] += int(mid)
        totals["lost"] += lost
        totals["back"] += back
    nc.stop = True
    nc.join(timeout=5)
    w.look(svc, "nc-1")
    svc.stop()
    totals["ok_cycles"] = len(w.ok)
    totals["last_version"] = w.version
    totals["nc5xx"] = nc.errors_5xx
    bad, partial = unreadable(os.path.join(data, "mcap", "nc-1"))
    totals["unreadable"] += bad
    totals["partial"] += partial
    return totals


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binary")
    ap.add_argument("out")
    ap.add_argument("--sim", type=int, default=30)
    ap.add_argument("--nc", type=int, default=25)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--run-after-s", type=float, default=1.0,
                    help="wall seconds each restarted simulated plant runs (600x) before it stops")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    # The trials run three at a time: the nc_push series and each half of the simulated one
    # in processes of their own. They share nothing (each its own services and data
    # directories) and mostly wait on their kill moments (the simulated series kept about 40 %
    # of one core busy, the nc_push one 20 %), so one after the other they left the machine
    # idle most of the time. The kill moments are those one generator from --seed drew when
    # the series ran in turn: one a simulated trial, then the nc_push series' own. The halves
    # take trials in pairs (0-1, 4-5, ... and 2-3, 6-7, ...), so each has as many of the
    # odd trials, which wait for a cycle to be running.
    rng = random.Random(a.seed)
    waits = {i: rng.uniform(0.3, 2.0) for i in range(a.sim)}
    halves = [{i: w for i, w in waits.items() if (i // 2) % 2 == h} for h in (0, 1)]
    failed = False
    all_trials = 0
    results = {}
    with concurrent.futures.ProcessPoolExecutor(
            max_workers=2, mp_context=multiprocessing.get_context("fork")) as pool:
        nc = pool.submit(nc_series, a.binary, a.out, a.nc, rng) if a.nc else None
        other = (pool.submit(sim_series, a.binary, a.out, halves[1], a.run_after_s)
                 if halves[1] else None)
        if a.sim:
            sim = sim_series(a.binary, a.out, halves[0], a.run_after_s)
            if other is not None:
                sim = {k: v + other.result()[k] for k, v in sim.items()}
            results["simulated"] = sim
        if nc is not None:
            results["nc_push"] = nc.result()
    for name, t in results.items():
        all_trials += t["trials"]
        print(f"kill -9 harness, {name}: " + ", ".join(f"{k} {v}" for k, v in t.items()))
        failed |= any(t.get(k, 0) for k in ("lost", "back", "unreadable", "partial", "nc5xx",
                                             "before_served"))
    print(f"kill -9 harness: {all_trials} trials, {'FAILED' if failed else 'ok'}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
