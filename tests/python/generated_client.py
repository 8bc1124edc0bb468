"""The NC handshake driven by a client generated from the OpenAPI document a running driftwatch
serves (`openapi-python-client`), as an NC integrator would build one.

usage: python3 generated_client.py BINARY OUTDIR [--timeout-s S]

1. Starts `BINARY serve` with one machine `nc-1` on the nc_push link (table_bc, the patent
   plan, the wall clock, data in OUTDIR/data, a free loopback port, the NC's write token from
   DRIFTWATCH_NC_TOKEN), reads GET /api/v1/openapi.json and generates a Python client from it
   in OUTDIR/driftwatch_client with `python3 -m openapi_python_client generate`. Any operation
   the generator leaves out (it warns "Endpoint will not be generated", e.g. for a reference
   the document does not define) fails the check.
2. Plays the NC with the generated client's typed calls only (no hand-written HTTP for them):
   - `api.machines.healthz` until the service answers;
   - `api.nc.nc_events` (POST /api/v1/machines/{id}/nc/events, an `EventBatch` of
     `PostedEvent`s): `/spindle` at 20000 min^-1, `/machine/state` idle and an ambient
     `/temperature`, every second while it waits;
   - `api.nc.nc_request` (GET .../nc/request) until it answers a `CycleOrder`;
   - `api.nc.nc_events` again: `/machine/state` measuring, then one `/probe/detection` per step
     of the order, each posted (in a batch of its own, stamped with the clock) when the step
     trips in the cycle's own timing, then `/machine/state` idle: the cycle takes its machine
     time on the wall clock, about a minute for the patent plan. (The solve estimates the
     tool-tip drift rates from the detections' times: a cycle whose 24 detections were all
     stamped within a few milliseconds was once rejected as not converging.) The detections
     and their times in the cycle are those of the first cycle of `BINARY simulate --scenario
     patent` (the truth simulator's virtual machine, as kill_harness.py replays them), found
     for each order step by its label and posted under the order's cycle number;
   - `api.cycles.cycle` (GET .../cycles/{n}) until the cycle is no longer open; it must be
     `ok` (validated);
   - `api.machines.compensation` (GET .../compensation) as a typed `CompensationSet` of the
     cycle, with its ETag; then the same call with `if_none_match` = that ETag: 304.
   The document itself is read with urllib (it is not an operation of the API).
Closes with
  generated client: N operations, cycle C ok (S steps), compensation version V, 304 on its ETag
The exit status is 1 when any step fails, else 0. About 70 s; bounded: --timeout-s (default
120) for each wait, all on 127.0.0.1.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request

from served import stop, wait_served

TOKEN = "generated-client-token"
MACHINE = "nc-1"
RPM = 20000.0

CONFIG = """
data_dir = "unused"
time_scale = 1.0
max_file_mib = 256
[http]
listen = "127.0.0.1:0"
anonymous_read = true
tokens = [{ name = "nc", token = "env:DRIFTWATCH_NC_TOKEN", role = "write" }]
[[machines]]
id = "nc-1"
machine = "table_bc"
plan = "patent"
link = { kind = "nc_push" }
"""


class Failed(Exception):
    pass


def start(binary: str, outdir: str) -> tuple[subprocess.Popen, str]:
    config = os.path.join(outdir, "nc.toml")
    with open(config, "w") as f:
        f.write(CONFIG)
    log_path = os.path.join(outdir, "service.log")
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [binary, "serve", "--config", config, "--data-dir", os.path.join(outdir, "data"),
             "--listen", "127.0.0.1:0"],
            env=dict(os.environ, RUST_LOG="warn", DRIFTWATCH_NC_TOKEN=TOKEN),
            stdout=log, stderr=subprocess.STDOUT)
    base = wait_served(proc, log_path)
    if base is None:
        stop(proc)
        raise Failed(f"the service did not say where it listens (see {log_path})")
    return proc, base


def generate(base: str, outdir: str):
    """The client package generated from the served document, imported; and the number of
    operations it has."""
    doc_path = os.path.join(outdir, "openapi.json")
    with urllib.request.urlopen(base + "/api/v1/openapi.json", timeout=30) as r:
        doc = json.load(r)
    with open(doc_path, "w") as f:
        json.dump(doc, f, indent=2)
    pkg = os.path.join(outdir, "driftwatch_client")
    r = subprocess.run([sys.executable, "-m", "openapi_python_client", "generate",
                        "--path", doc_path, "--meta", "none", "--output-path", pkg,
                        "--overwrite"],
                       capture_output=True, text=True, cwd=outdir)
    out = r.stdout + r.stderr
    with open(os.path.join(outdir, "generate.log"), "w") as f:
        f.write(out)
    if r.returncode != 0 or "will not be generated" in out or "Warning" in out:
        print(out)
        raise Failed("openapi-python-client did not generate every operation cleanly "
                     "(see generate.log)")
    ops = {op["operationId"] for item in doc["paths"].values() for op in item.values()
           if isinstance(op, dict) and "operationId" in op}
    made = {f[:-3] for d, _, files in os.walk(os.path.join(pkg, "api")) for f in files
            if f.endswith(".py") and f != "__init__.py"}
    if ops - made:
        raise Failed(f"operations missing from the generated client: {sorted(ops - made)}")
    sys.path.insert(0, outdir)
    return importlib.import_module("driftwatch_client"), len(ops)


def template_detections(binary: str, outdir: str) -> dict[str, tuple[float, dict]]:
    """The detections of the first cycle of a simulated patent recording (the virtual
    machine's trips, as an NC would post them) by step label, each with its time in the
    cycle, s."""
    from mcap.reader import make_reader
    path = os.path.join(outdir, "template.mcap")
    subprocess.run([binary, "simulate", "--scenario", "patent", "--out", path], check=True,
                   capture_output=True)
    with open(path, "rb") as f:
        msgs = [(m.log_time, json.loads(m.data)) for _, _, m in
                make_reader(f).iter_messages(topics=["/probe/detection"])]
    first = [(t, d) for t, d in msgs if d["cycle"] == 1]
    if not first:
        raise Failed("the simulated recording has no detection of cycle 1")
    t0 = min(t for t, _ in first)
    return {d["step"]: ((t - t0) / 1e9, d) for t, d in first}


def handshake(dw, base: str, template: dict[str, tuple[float, dict]], timeout_s: float) -> str:
    """The NC's side, through the generated client's typed calls. Returns the closing words."""
    from driftwatch_client.api.cycles import cycle as get_cycle
    from driftwatch_client.api.machines import compensation, healthz
    from driftwatch_client.api.nc import nc_events, nc_request
    from driftwatch_client.models import CompensationSet, CycleOrder, EventBatch, PostedEvent
    from driftwatch_client.models import CycleStatus, PostedEventMsg

    client = dw.AuthenticatedClient(base_url=base, token=TOKEN, timeout=30.0)

    def post(*events: tuple[str, dict]) -> None:
        now = time.time_ns()
        batch = EventBatch(events=[PostedEvent(topic=t, t_ns=now, msg=PostedEventMsg.from_dict(m))
                                   for t, m in events])
        r = nc_events.sync_detailed(MACHINE, client=client, body=batch)
        if r.status_code != 202:
            raise Failed(f"nc_events answered {int(r.status_code)}: {r.parsed}")

    def until(what: str, probe):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            got = probe()
            if got is not None:
                return got
            time.sleep(0.2)
        raise Failed(f"no {what} within {timeout_s:.0f} s")

    until("answer of healthz",
          lambda: True if healthz.sync_detailed(client=client).status_code == 200 else None)

    idle = (("/spindle", {"rpm": RPM}),
            ("/machine/state", {"state": "idle", "program": "generated-client"}),
            ("/temperature", {"sensor": "ambient", "celsius": 20.0}))
    last_post = [0.0]

    def order_or_none():
        # The NC reports at least once a minute while the spindle turns; once a second here.
        if time.monotonic() - last_post[0] >= 1.0:
            post(*idle)
            last_post[0] = time.monotonic()
        r = nc_request.sync_detailed(MACHINE, client=client)
        if r.status_code == 200:
            if not isinstance(r.parsed, CycleOrder):
                raise Failed(f"nc_request 200 not parsed as a CycleOrder: {r.parsed!r}")
            return r.parsed
        if r.status_code != 204:
            raise Failed(f"nc_request answered {int(r.status_code)}: {r.parsed}")
        return None

    order = until("cycle order", order_or_none)
    print(f"order: cycle {order.cycle}, plan {order.plan}, {len(order.steps)} steps at "
          f"{order.spindle_rpm:.0f} min^-1")

    post(("/machine/state", {"state": "measuring", "program": "generated-client"}))
    start = time.monotonic()
    for st in order.steps:
        found = template.get(st.step)
        if found is None:
            raise Failed(f"order step {st.step!r} is not a step of the simulated cycle")
        at_s, det = found
        if (det["axis"], det["direction"], det["feed_mm_min"]) != (st.axis, st.direction,
                                                                  st.feed_mm_min):
            raise Failed(f"order step {st.step!r} differs from the simulated one: {st} / {det}")
        # The trip happens this far into the cycle (the machine moves there first).
        time.sleep(max(0.0, start + at_s - time.monotonic()))
        post(("/probe/detection", dict(det, cycle=order.cycle)))
    post(("/machine/state", {"state": "idle", "program": "generated-client"}))
    print(f"detections: {len(order.steps)} posted over {time.monotonic() - start:.1f} s")

    def closed():
        r = get_cycle.sync_detailed(MACHINE, order.cycle, client=client)
        if r.status_code != 200:
            return None
        row = r.parsed.cycle
        return None if row.status == CycleStatus.OPEN else row

    row = until(f"end of cycle {order.cycle}", closed)
    print(f"cycle {row.cycle}: {row.status.value}" + (f" ({row.reason})" if row.reason else ""))
    if row.status != CycleStatus.OK:
        raise Failed(f"cycle {row.cycle} was {row.status.value}: {row.reason}")

    def served():
        r = compensation.sync_detailed(MACHINE, client=client)
        if r.status_code == 200 and isinstance(r.parsed, CompensationSet) \
                and r.parsed.cycle == order.cycle:
            return r
        return None

    r = until(f"compensation set of cycle {order.cycle}", served)
    comp = r.parsed
    etag = r.headers.get("etag")
    errors = ", ".join(f"{k} {v:.2f}+-{comp.sigma[k]:.2f}"
                       for k, v in sorted(comp.errors.additional_properties.items()))
    print(f"compensation: version {comp.version}, source {comp.source.value}, cycle "
          f"{comp.cycle}, ETag {etag}: {errors}")
    if not etag:
        raise Failed("the compensation answer has no ETag")
    again = compensation.sync_detailed(MACHINE, client=client, if_none_match=etag)
    print(f"compensation with If-None-Match {etag}: {int(again.status_code)}")
    if again.status_code != 304:
        raise Failed(f"If-None-Match with the current ETag answered {int(again.status_code)}")
    return (f"cycle {row.cycle} ok ({len(order.steps)} steps), compensation version "
            f"{comp.version}, 304 on its ETag")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--timeout-s", type=float, default=120.0)
    a = ap.parse_args()
    outdir = os.path.abspath(a.outdir)
    shutil.rmtree(outdir, ignore_errors=True)
    os.makedirs(outdir)
    binary = os.path.abspath(a.binary)
    version = importlib.metadata.version("openapi-python-client")
    proc = None
    try:
        template = template_detections(binary, outdir)
        proc, base = start(binary, outdir)
        dw, n_ops = generate(base, outdir)
        print(f"openapi-python-client {version}: {n_ops} operations generated")
        words = handshake(dw, base, template, a.timeout_s)
    except Failed as e:
        print(f"generated client: FAILED: {e}")
        return 1
    finally:
        if proc is not None:
            stop(proc)
    print(f"generated client: {n_ops} operations, {words}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
