"""A full disk under a running driftwatch: what the NC is served must be what the store holds.

usage: python3 full_disk.py BINARY OUTDIR [--size-kib N] [--free-kib N] [--seconds S]

Needs root (it mounts a small tmpfs). The data directory lies on a tmpfs of --size-kib (8192)
that a filler file has filled but for --free-kib (500): the new database and the first
recording fit, the morning's writes do not (the write-ahead log alone grows past it). `BINARY serve --time-scale 600`
runs on it; every 0.2 s the script reads, in this order, what the NC is served
(`GET /api/v1/machines/sim-1/compensation`: version, ETag, body), then the largest version the
database holds (its own read-only SQLite connection), `/readyz` and the machine's `failing`.
After --seconds (40) the filler is removed (the disk has room again); after as long again the
service is stopped (SIGTERM) and started again on the same directory, and watched once more.

It fails (exit 1) if at any poll the served version is above the stored one (a set served that
the store did not hold), if one ETag ever names two different bodies (across the restart too),
if the service never said it was failing while the disk was full (no 503 on /readyz), or if it
did not recover after the filler went (served version = stored version, /readyz 200). It
prints each phase's figures and closes with `full disk: N polls, ...`.
"""
from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import time
import urllib.error
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from served import wait_served  # noqa: E402

MACHINE = "sim-1"


def get(base, path, timeout=2.0):
    """(status, headers, body bytes); (0, {}, b"") when the service does not answer."""
    try:
        with urllib.request.urlopen(base + path, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()
    except (urllib.error.URLError, OSError):
        return 0, {}, b""


def stored_max(db):
    """The largest compensation version the database holds (0: none; None: unreadable)."""
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0)
        try:
            row = con.execute(
                "SELECT MAX(version) FROM compensation_sets WHERE machine_id = ?", (MACHINE,)
            ).fetchone()
            return row[0] or 0
        finally:
            con.close()
    except sqlite3.Error:
        return None


class Serve:
    def __init__(self, binary, data, log):
        self.log = open(log, "ab")
        offset = self.log.tell()
        self.proc = subprocess.Popen(
            [binary, "serve", "--time-scale", "600", "--listen", "127.0.0.1:0",
             "--data-dir", data],
            stdout=self.log, stderr=self.log, stdin=subprocess.DEVNULL,
            env=dict(os.environ, RUST_LOG="warn"),
        )
        self.base = wait_served(self.proc, log, offset)
        if self.base is None:
            raise RuntimeError(f"serve did not start; see {log}")

    def stop(self):
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        finally:
            self.log.close()


def watch(svc, db, seconds, phase, seen, problems):
    """Poll for `seconds`; returns the phase's figures."""
    polls = failing = readyz_503 = 0
    served_max = stored_seen = 0
    last = None
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        code, headers, body = get(svc.base, f"/api/v1/machines/{MACHINE}/compensation")
        stored = stored_max(db)
        rcode, _, rbody = get(svc.base, "/readyz")
        mcode, _, mbody = get(svc.base, f"/api/v1/machines/{MACHINE}")
        polls += 1
        if rcode == 503:
            readyz_503 += 1
        if mcode == 200 and json.loads(mbody).get("failing"):
            failing += 1
        if code == 200:
            version = json.loads(body)["version"]
            etag = headers.get("ETag") or headers.get("etag")
            served_max = max(served_max, version)
            if stored is not None:
                stored_seen = max(stored_seen, stored)
                if version > stored:
                    problems.append(f"{phase}: served v{version}, the store holds up to v{stored}")
            if etag in seen and seen[etag] != body:
                problems.append(f"{phase}: ETag {etag} names two different sets")
            seen.setdefault(etag, body)
            last = (version, stored, rcode)
        time.sleep(0.2)
    return {
        "polls": polls, "served_max": served_max, "stored_max": stored_seen,
        "readyz_503": readyz_503, "failing": failing, "last": last,
        "ready_text": rbody.decode(errors="replace")[:300],
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--size-kib", type=int, default=8192)
    ap.add_argument("--free-kib", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=40.0)
    a = ap.parse_args()
    if os.geteuid() != 0:
        print("full disk: needs root to mount a tmpfs (run as root, as CI does)")
        return 2
    os.makedirs(a.outdir, exist_ok=True)
    mnt = os.path.join(a.outdir, "small")
    os.makedirs(mnt, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={a.size_kib}k", "tmpfs", mnt],
                   check=True)
    problems, seen, rows = [], {}, []
    try:
        filler = os.path.join(mnt, "filler")
        with open(filler, "wb") as f:
            f.write(b"\0" * ((a.size_kib - a.free_kib) * 1024))
        data = os.path.join(mnt, "d")
        db = os.path.join(data, "driftwatch.db")
        log = os.path.join(a.outdir, "serve.log")
        svc = Serve(a.binary, data, log)
        try:
            rows.append(("disk full", watch(svc, db, a.seconds, "disk full", seen, problems)))
            os.remove(filler)
            rows.append(("room again", watch(svc, db, a.seconds, "room again", seen, problems)))
        finally:
            svc.stop()
        svc = Serve(a.binary, data, log)
        try:
            rows.append(("restarted", watch(svc, db, a.seconds / 2, "restarted", seen, problems)))
        finally:
            svc.stop()
    finally:
        subprocess.run(["umount", mnt], check=False)
    for name, r in rows:
        print(f"{name:>10}: {r['polls']} polls, served up to v{r['served_max']}, stored up to "
              f"v{r['stored_max']}, /readyz 503 in {r['readyz_503']}, failing in {r['failing']}, "
              f"last (served, stored, readyz) {r['last']}")
    full, room = rows[0][1], rows[1][1]
    if full["readyz_503"] == 0 or full["failing"] == 0:
        problems.append("the full disk was never reported (/readyz 503, failing)")
    if room["last"] is None or room["last"][0] != room["last"][1] or room["last"][2] != 200:
        problems.append(f"no recovery once the disk had room: last {room['last']}")
    if rows[2][1]["last"] is None or rows[2][1]["served_max"] < room["served_max"]:
        problems.append(f"after the restart the served version went back: {rows[2][1]}")
    for p in problems[:20]:
        print("PROBLEM:", p)
    polls = sum(r["polls"] for _, r in rows)
    print(f"full disk: {polls} polls, {len(seen)} ETags, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
