"""Soak of the NC door: stray and clock-skewed events against `driftwatch serve` on an
nc_push machine, with the process's resident memory and the data directory's size measured
before and after.

usage: python3 soak_nc.py BINARY OUTDIR [--strays N] [--batch B]

Starts the service (the kill harness's nc_push configuration, wall clock), has the NC report
idle, then posts detections of a cycle nobody ordered (a real detection of a simulated cycle,
numbered 999999) in batches of B. After every tenth batch it posts one event stamped an hour
ahead (refused: clock_skew) and an `idle` stamped a second in the past (taken, but older than
the state it follows). The first 20 000 strays warm the process up; RSS (VmRSS from
/proc/PID/status) and the data directory's size are read then and after N more (default
300 000). /metrics must count every stray and every skewed event. Prints
  soak: N strays, K skewed refused; RSS before X MiB, after Y MiB (+D MiB); data +S KiB
and exits 1 if RSS grew more than 8 MiB, the data directory more than 1 MiB, a count is
wrong or any answer was a 5xx.
"""
import argparse
import os
import shutil
import sys
import time
import urllib.request

from kill_harness import NC_CONFIG, TOKEN, Service, call, template_detections

WARMUP = 20_000
HOUR_NS = 3_600_000_000_000
MACHINE = "/api/v1/machines/nc-1"


def rss_kib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def dir_bytes(path):
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                total += os.path.getsize(os.path.join(root, name))
            except OSError:
                pass  # a file the service renamed meanwhile
    return total


def metric(base, name):
    r = urllib.request.Request(base + "/metrics")
    r.add_header("Authorization", "Bearer " + TOKEN)
    with urllib.request.urlopen(r, timeout=10) as resp:
        for line in resp.read().decode().splitlines():
            if line.startswith(name + " ") or line.startswith(name + "{"):
                return int(float(line.split()[-1]))
    raise RuntimeError(f"/metrics has no {name}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--strays", type=int, default=300_000)
    ap.add_argument("--batch", type=int, default=1000)
    a = ap.parse_args()
    out = os.path.abspath(a.outdir)
    os.makedirs(out, exist_ok=True)
    data = os.path.join(out, "soak")
    shutil.rmtree(data, ignore_errors=True)
    config = os.path.join(out, "soak.toml")
    with open(config, "w") as f:
        f.write(NC_CONFIG.format())
    det = dict(template_detections(os.path.abspath(a.binary), out)[0], cycle=999_999)
    svc = Service(os.path.abspath(a.binary), data, os.path.join(out, "soak.log"), config=config)
    problems = []
    counts = {"posted": 0, "skewed": 0, "5xx": 0}

    def post(events, expect):
        s, body = call(svc.base, "POST", MACHINE + "/nc/events", {"events": events}, TOKEN,
                       timeout=30)
        if s >= 500:
            counts["5xx"] += 1
        elif s != expect and len(problems) < 10:
            problems.append(f"expected {expect}, got {s}: {body}")
        return s

    def state(t_ns):
        return {"topic": "/machine/state", "t_ns": t_ns,
                "msg": {"state": "idle", "program": "soak"}}

    def strays(n):
        sent = 0
        while sent < n:
            k = min(a.batch, n - sent)
            now = time.time_ns()
            post([{"topic": "/probe/detection", "t_ns": now, "msg": det}] * k, 202)
            sent += k
            counts["posted"] += k
            if (sent // a.batch) % 10 == 0:
                if post([state(now + HOUR_NS)], 400) == 400:
                    counts["skewed"] += 1
                post([state(now - 1_000_000_000)], 202)

    try:
        post([state(time.time_ns())], 202)
        strays(WARMUP)
        rss0, disk0 = rss_kib(svc.proc.pid), dir_bytes(data)
        strays(a.strays)
        time.sleep(1.0)  # let the loop drain the queue
        rss1, disk1 = rss_kib(svc.proc.pid), dir_bytes(data)
        counted = metric(svc.base, "driftwatch_nc_stray_detections_total")
        refused = metric(svc.base, "driftwatch_nc_events_refused_clock_skew_total")
    finally:
        svc.stop()
    if counted != counts["posted"]:
        problems.append(f"/metrics counts {counted} strays, {counts['posted']} were posted")
    if refused != counts["skewed"]:
        problems.append(f"/metrics counts {refused} skewed events, {counts['skewed']} refused")
    grew = (rss1 - rss0) / 1024
    if grew > 8:
        problems.append(f"RSS grew {grew:.1f} MiB")
    if disk1 - disk0 > 1 << 20:
        problems.append(f"the data directory grew {(disk1 - disk0) >> 10} KiB")
    if counts["5xx"]:
        problems.append(f"{counts['5xx']} answers were 5xx")
    for p in problems:
        print("soak problem:", p)
    print(f"soak: {a.strays} strays, {counts['skewed']} skewed refused; RSS before "
          f"{rss0 / 1024:.1f} MiB, after {rss1 / 1024:.1f} MiB ({grew:+.1f} MiB); "
          f"data {(disk1 - disk0) / 1024:+.0f} KiB")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
