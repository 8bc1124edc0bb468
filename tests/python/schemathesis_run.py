"""Property-based API test of a driftwatch binary with Schemathesis, against its own OpenAPI document.

usage: python3 schemathesis_run.py BINARY OUTDIR [--max-examples N] [--seed S]

Starts `BINARY serve` (600x time, data in OUTDIR/data, a free loopback port, an operator token
with role write from DRIFTWATCH_OPERATOR_TOKEN), waits for GET /healthz, then until the plant's
first two cycles are validated (about 2 s; fails if not within 30 s) so that cycles, detections
and compensation sets exist (the first alerts come later, while the runs go on), asks one
diagnosis (it must be made, 201) so that /diagnoses/{n} has something to read, then runs two
`st run` on /api/v1/openapi.json at once:
  * pass "token": every operation but POST .../diagnoses (a multi-second computation, 429 while
    another runs), Authorization: Bearer <token>, N examples per operation;
  * pass "anonymous": the same without a token (anonymous reads are allowed), N/4 examples.
N defaults to 200; test.sh gives 150: about 6 000 requests, about 40 s on 2 cores.
All of Schemathesis' checks run (among them not_a_server_error, status_code_conformance,
content_type_conformance, response_schema_conformance, negative_data_rejection,
positive_data_acceptance, ignored_auth). Path parameters come from a small dictionary (machine
sim-1, numbers 1-3) part of the time so that requests reach past the 404s.
From Schemathesis' NDJSON event reports (OUTDIR/<pass>/) it counts every request sent, the 5xx
answers and the distinct failures per check (operation, check, title), prints each failure with
one request and its response, and closes with
  schemathesis: N requests, K 5xx, F failures (check: count, ...)
The exit status is 1 on any 5xx or failure (or if Schemathesis could not run), else 0.
"""
from __future__ import annotations

import argparse
import base64
import glob
import json
import os
import secrets
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request

from served import stop, wait_served

CONFIG = """\
[dictionaries.machines]
values = ["sim-1"]
[dictionaries.numbers]
values = [1, 2, 3]
[parameters]
"path.id" = { dictionary = "machines", probability = 0.8 }
"path.n" = { dictionary = "numbers", probability = 0.5 }
"path.alert" = { dictionary = "numbers", probability = 0.5 }
"""

# Two refusals OpenAPI cannot state, so generated queries are kept clear of them: a window's
# `from` after its `to` (400 bad_window: a constraint between two parameters; windows are put
# in order) and a prediction `at` before the model's last input (400 before_last_input: it
# depends on the service's state; times are moved to 2033-2065, which also asks the model
# decades ahead).
# Two more on the compensation endpoint in an NC's form: FANUC and LinuxCNC need the
# commissioned value of each parameter or pin they write (`fanuc_nominal`, `linuxcnc_nominal`,
# required with `format=fanuc` or `format=linuxcnc` only: another constraint between
# parameters; LinuxCNC's form is also refused for a machine in the ISO table sense, 409
# offsets_refused), and a set whose step from the previous one exceeds the
# validation limit is refused (409 offsets_refused: it depends on the served history).
# Two on a verification's reference: its error names must be the machine's identified ones
# and each needs its sigma > 0 in a second map, its time not ahead of the service clock (400
# bad_reference: constraints between a map's keys, another map and the service's state), and
# an accepted tool-setter result must lie near its time (422 no_setter_result: the store's
# state).
# One on a linear-axis geometry: each coefficient's limit inside its array, the component
# names (a map's keys) and the stack naming X, Y and Z once each (400 bad_geometry; the
# source's length and the stack's letters are in the document).
UNSTATABLE = ("bad_window", "before_last_input", "missing_nominal", "offsets_refused",
              "bad_reference", "no_setter_result", "bad_geometry")

HOOKS = """\
import schemathesis


@schemathesis.hook
def map_query(ctx, query):
    if isinstance(query, dict):
        a, b = query.get("from"), query.get("to")
        if isinstance(a, int) and isinstance(b, int) and a > b:
            query["from"], query["to"] = b, a
        at = query.get("at")
        if isinstance(at, int) and at < 2 * 10**18:
            query["at"] = 2 * 10**18 + abs(at) % 10**18
    return query
"""


def http(method: str, url: str, token: str | None = None, body: bytes | None = None) -> int:
    req = urllib.request.Request(url, data=body, method=method)
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    if body is not None:
        req.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code


def start(binary: str, outdir: str, token: str) -> tuple[subprocess.Popen, str]:
    env = dict(os.environ, DRIFTWATCH_OPERATOR_TOKEN=token)
    path = os.path.join(outdir, "service.log")
    offset = os.path.getsize(path) if os.path.exists(path) else 0
    log = open(path, "ab")
    proc = subprocess.Popen(
        [binary, "serve", "--time-scale", "600", "--until", "100000",
         "--data-dir", os.path.join(outdir, "data"), "--listen", "127.0.0.1:0"],
        env=env, stdout=log, stderr=subprocess.STDOUT)
    base = wait_served(proc, path, offset)
    deadline = time.monotonic() + 30
    while base and time.monotonic() < deadline and proc.poll() is None:
        try:
            if http("GET", base + "/healthz") == 200:
                return proc, base
        except OSError:
            pass
        time.sleep(0.2)
    stop(proc)
    sys.exit("schemathesis: the service did not answer /healthz (see service.log)")


def start_st(base: str, outdir: str, name: str, n: int, seed: int, token: str | None):
    """`st run` started on the document, its log in OUTDIR/<name>.log, its report in
    OUTDIR/<name>/."""
    st = [shutil.which("st")] if shutil.which("st") else [sys.executable, "-m", "schemathesis.cli"]
    repdir = os.path.join(outdir, name)
    shutil.rmtree(repdir, ignore_errors=True)
    os.makedirs(repdir)
    cfg = os.path.join(outdir, "schemathesis.toml")
    cmd = st + ["--config-file", cfg, "run", base + "/api/v1/openapi.json", "--checks", "all",
                "--max-examples", str(n), "--seed", str(seed), "--workers", "2",
                "--generation-database", "none", "--request-timeout", "30",
                "--exclude-operation-id", "request_diagnosis",
                "--report", "ndjson", "--report-dir", repdir, "--no-color"]
    if token:
        cmd += ["--header", f"Authorization: Bearer {token}"]
    env = dict(os.environ, SCHEMATHESIS_HOOKS="driftwatch_hooks",
               PYTHONPATH=os.pathsep.join(filter(None, [outdir, os.environ.get("PYTHONPATH")])))
    out = open(os.path.join(outdir, f"{name}.log"), "w")
    return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=outdir, env=env), out


def finish_st(outdir: str, name: str, started) -> str:
    """The NDJSON report of a pass once its `st run` has ended."""
    proc, out = started
    proc.wait()
    out.close()
    found = glob.glob(os.path.join(outdir, name, "*.ndjson"))
    if not found:
        sys.exit(f"schemathesis: pass {name} wrote no report (see {name}.log)")
    return found[0]


def wait_ok_cycles(base: str, n: int, timeout_s: float) -> int:
    """Poll the machine's cycles until `n` are validated (ok), `timeout_s` at the latest;
    returns how many are."""
    deadline = time.monotonic() + timeout_s
    ok = 0
    while True:
        try:
            with urllib.request.urlopen(base + "/api/v1/machines/sim-1/cycles?limit=1000",
                                        timeout=10) as r:
                ok = sum(c["status"] == "ok" for c in json.load(r))
        except (urllib.error.URLError, OSError, ValueError):
            pass
        if ok >= n or time.monotonic() >= deadline:
            return ok
        time.sleep(0.1)


def body_text(resp: dict) -> str:
    c = resp.get("content") or {}
    raw = base64.b64decode(c["$base64"]) if "$base64" in c else (c.get("string") or "").encode()
    return raw.decode("utf-8", "replace")[:400]


def tally(report: str, stats: dict) -> None:
    for line in open(report, encoding="utf-8"):
        ev = json.loads(line).get("ScenarioFinished")
        if not ev:
            continue
        rec = ev["recorder"]
        inter = rec.get("interactions") or {}
        for i in inter.values():
            stats["requests"] += 1
            code = (i.get("response") or {}).get("status_code") or 0
            if code >= 500:
                stats["5xx"] += 1
        for case_id, checks in (rec.get("checks") or {}).items():
            for c in checks:
                if c.get("status") != "failure":
                    continue
                f = (c.get("failure_info") or {}).get("failure") or {}
                resp = ((inter.get(case_id) or {}).get("response")) or {}
                # The refusals OpenAPI cannot state (see HOOKS and UNSTATABLE): phases that
                # bypass the hooks still send them, and the API is right to refuse them.
                if c["name"] == "positive_data_acceptance" and any(
                        f'"code":"{code}"' in body_text(resp) for code in UNSTATABLE):
                    stats["unstatable"] += 1
                    continue
                key = (f.get("operation") or rec.get("label"), c["name"], f.get("title"))
                if key in stats["failures"]:
                    continue
                i = inter.get(case_id) or {}
                req, resp = i.get("request") or {}, i.get("response") or {}
                stats["failures"][key] = (
                    f"{stats['pass']}: {key[0]} [{key[1]}] {f.get('title')}: "
                    f"{(f.get('message') or '').splitlines()[0][:200] if f.get('message') else ''}\n"
                    f"    request: {req.get('method')} {req.get('uri')} body={req.get('body')!r:.300}\n"
                    f"    response: {resp.get('status_code')} {body_text(resp)}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--max-examples", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    outdir = os.path.abspath(a.outdir)
    os.makedirs(outdir, exist_ok=True)
    shutil.rmtree(os.path.join(outdir, "data"), ignore_errors=True)
    with open(os.path.join(outdir, "schemathesis.toml"), "w") as f:
        f.write(CONFIG)
    with open(os.path.join(outdir, "driftwatch_hooks.py"), "w") as f:
        f.write(HOOKS)
    token = secrets.token_hex(16)
    proc, base = start(os.path.abspath(a.binary), outdir, token)
    stats = {"requests": 0, "5xx": 0, "failures": {}, "unstatable": 0}
    passes = []
    try:
        # Two validated cycles of the plant's morning (about 2 s at 600x): their cycles,
        # detections and compensation sets for the reads, and readings in more than one cycle
        # for the diagnosis.
        ok = wait_ok_cycles(base, 2, timeout_s=30.0)
        if ok < 2:
            sys.exit(f"schemathesis: {ok} validated cycles within 30 s, not 2 (see service.log)")
        code = http("POST", base + "/api/v1/machines/sim-1/diagnoses", token, b"{}")
        if code != 201:
            sys.exit(f"schemathesis: the diagnosis to read was not made: {code}")
        # Both passes at once: each is one Python process that keeps about one core busy, and
        # the service takes little; run one after the other they left a core idle.
        for name, n, tok in (("token", a.max_examples, token),
                             ("anonymous", max(1, a.max_examples // 4), None)):
            passes.append((name, start_st(base, outdir, name, n, a.seed, tok)))
        for name, st in passes:
            stats["pass"] = name
            tally(finish_st(outdir, name, st), stats)
    finally:
        for _, (st, _) in passes:
            if st.poll() is None:
                st.kill()
                st.wait()
        stop(proc)
    per_check: dict[str, int] = {}
    for (_, check, _), text in stats["failures"].items():
        per_check[check] = per_check.get(check, 0) + 1
        print(text)
    detail = ", ".join(f"{k}: {v}" for k, v in sorted(per_check.items()))
    nf = len(stats["failures"])
    print(f"schemathesis: {stats['requests']} requests, {stats['5xx']} 5xx, {nf} failures"
          + (f" ({detail})" if detail else "")
          + f"; {stats['unstatable']} refusals OpenAPI cannot state (not failures)")
    return 1 if stats["5xx"] or nf else 0


if __name__ == "__main__":
    sys.exit(main())
