"""A full disk under a running driftwatch: what the NC is served must be what the store holds.

usage: python3 full_disk.py BINARY OUTDIR [--size-kib N] [--seconds S] [--start-full-kib N]

Needs root (it mounts a small tmpfs). The data directory lies on a tmpfs of --size-kib (8192).
`BINARY serve --time-scale 600` runs on it; every 0.2 s the script reads, in this order, what
the NC is served (`GET /api/v1/machines/sim-1/compensation`: version, ETag, body), then the
largest version the database holds (its own read-only SQLite connection), `/readyz` and the
machine (`failing`, its count of failed steps `faults`, the service clock). Each phase ends
as soon as what it waits for is seen, and after --seconds (30) at the latest (the restart's
after half of it):
  1. room: until the morning's first set is stored and served (/readyz 200);
  2. disk full: a filler file takes every free byte; the service must go on serving the last
     stored set, never a newer one, and say it is failing. The phase lasts until the fault
     is reported and the loop has failed FULL_ATTEMPTS steps and the service clock has gone
     FULL_PLANT_MIN minutes of the plant day past the fill (see those constants for why);
  3. room again: the filler is removed; until the pending writes are stored and a newer set
     served (served version = stored version, /readyz 200);
  4. restarted: the service is stopped (SIGTERM) and started again on the same directory;
     until it serves the stored set again, /readyz 200, and has stored and served a newer
     one (its loop goes on from the store).
With --start-full-kib N the disk is full from the start but for N KiB (the new database and
the first recording fit, the morning's writes do not) and phase 1 is left out.

It fails (exit 1) if at any poll the served version is above the stored one (a set served that
the store did not hold), if one ETag ever names two different bodies (across the restart too),
if the full disk was never reported (no 503 on /readyz), if the disk-full phase did not span
its failed steps and plant minutes within --seconds, if the served version moved while the
disk was full, or if the service did not recover (served version = stored version, /readyz
200; after the restart no version going back). It prints each phase's figures (its wall
seconds, and for the full disk the failed steps and plant minutes it spanned) and closes with
`full disk: N polls, ...`.
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


def fill(path):
    """Write zeros to `path` until the filesystem has no byte left."""
    chunk = b"\0" * (64 * 1024)
    with open(path, "wb", buffering=0) as f:
        try:
            while True:
                f.write(chunk)
        except OSError:
            pass
    with open(path, "ab", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 512)
        except OSError:
            pass


# The disk-full phase must span enough of the service's own activity for "the served set did
# not move" to mean something, counted in what the service does, not in wall seconds:
# - FULL_ATTEMPTS failed steps of the machine loop (its `faults`), each a fresh attempt at the
#   same pending write that must neither be skipped nor let a set be served: 12 take the
#   retry wait through its whole doubling from 1 s to its cap of 10 min of machine time and
#   one wait at the cap (27 min of machine time);
# - FULL_PLANT_MIN minutes of the plant day on the service clock since the fill: two of the
#   default schedule's 30-min warm-up intervals, so that the plant has cycles due in the
#   window (a loop that went on past its failed write would solve and serve them; while the
#   NC cuts they wait, so the sets the window held are counted from the store afterwards
#   and printed).
# At 600x that is about 6 s. --seconds bounds it, and a phase that reaches the bound short of
# this span fails.
FULL_ATTEMPTS = 12
FULL_PLANT_MIN = 60.0
NS_PER_MIN = 60 * 10**9


def watch(svc, db, seconds, phase, seen, problems, done=None):
    """Poll until `done(figures)` holds after a poll, or for `seconds` at the latest; returns
    the phase's figures."""
    polls = failing = readyz_503 = 0
    served_max = stored_seen = 0
    served_min = None
    last = None
    faults = clock = None
    faults0 = clock0 = None
    t0 = time.monotonic()
    deadline = t0 + seconds
    figures = {}
    while time.monotonic() < deadline:
        code, headers, body = get(svc.base, f"/api/v1/machines/{MACHINE}/compensation")
        stored = stored_max(db)
        rcode, _, rbody = get(svc.base, "/readyz")
        mcode, _, mbody = get(svc.base, f"/api/v1/machines/{MACHINE}")
        polls += 1
        if rcode == 503:
            readyz_503 += 1
        if mcode == 200:
            m = json.loads(mbody)
            if m.get("failing"):
                failing += 1
            faults, clock = m.get("faults"), m.get("service_clock_ns")
            if faults0 is None:
                faults0, clock0 = faults, clock
        if code == 200:
            version = json.loads(body)["version"]
            etag = headers.get("ETag") or headers.get("etag")
            served_max = max(served_max, version)
            served_min = version if served_min is None else min(served_min, version)
            if stored is not None:
                stored_seen = max(stored_seen, stored)
                if version > stored:
                    problems.append(f"{phase}: served v{version}, the store holds up to v{stored}")
            if etag in seen and seen[etag] != body:
                problems.append(f"{phase}: ETag {etag} names two different sets")
            seen.setdefault(etag, body)
            last = (version, stored, rcode)
        figures = {
            "polls": polls, "served_max": served_max, "stored_max": stored_seen,
            "served_min": served_min or 0,
            "readyz_503": readyz_503, "failing": failing, "last": last,
            "ready_text": rbody.decode(errors="replace")[:300],
            "faults": (faults - faults0) if faults0 is not None else 0,
            "plant_min": (clock - clock0) / NS_PER_MIN if clock0 is not None and clock else 0.0,
            "clock_from": clock0, "clock_to": clock,
            "wall_s": time.monotonic() - t0,
        }
        if done is not None and done(figures):
            break
        time.sleep(0.2)
    return figures


def recovered(r, above):
    """Served = stored, /readyz 200, and a set newer than version `above` served."""
    return (r["last"] is not None and r["last"][0] == r["last"][1] and r["last"][2] == 200
            and r["served_max"] > above)


def sets_between(db, t0, t1):
    """How many sets the store holds valid from service-clock times in [t0, t1]."""
    if t0 is None or t1 is None:
        return None
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0)
        try:
            return con.execute(
                "SELECT COUNT(*) FROM compensation_sets WHERE machine_id = ? "
                "AND valid_from_ns BETWEEN ? AND ?", (MACHINE, t0, t1)).fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--size-kib", type=int, default=8192)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--start-full-kib", type=int, default=None)
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
        data = os.path.join(mnt, "d")
        db = os.path.join(data, "driftwatch.db")
        log = os.path.join(a.outdir, "serve.log")
        if a.start_full_kib is not None:
            with open(filler, "wb") as f:
                f.write(b"\0" * ((a.size_kib - a.start_full_kib) * 1024))
        svc = Serve(a.binary, data, log)
        try:
            if a.start_full_kib is None:
                rows.append(("room", watch(svc, db, a.seconds, "room", seen, problems,
                                           done=lambda r: recovered(r, 0))))
                fill(filler)
            rows.append(("disk full", watch(
                svc, db, a.seconds, "disk full", seen, problems,
                done=lambda r: (r["readyz_503"] > 0 and r["failing"] > 0
                                and r["faults"] >= FULL_ATTEMPTS
                                and r["plant_min"] >= FULL_PLANT_MIN))))
            os.remove(filler)
            above = rows[-1][1]["served_max"]
            rows.append(("room again", watch(svc, db, a.seconds, "room again", seen, problems,
                                             done=lambda r: recovered(r, above))))
        finally:
            svc.stop()
        full = rows[-2][1]
        # What the plant made while the disk was full, stored in the catch-up once it had
        # room: the sets the phase kept from being served before they were stored.
        full["sets_in_window"] = sets_between(db, full["clock_from"], full["clock_to"])
        svc = Serve(a.binary, data, log)
        try:
            above = rows[-1][1]["served_max"]
            rows.append(("restarted", watch(svc, db, a.seconds / 2, "restarted", seen, problems,
                                            done=lambda r: recovered(r, above))))
        finally:
            svc.stop()
    finally:
        subprocess.run(["umount", mnt], check=False)
    for name, r in rows:
        print(f"{name:>10}: {r['wall_s']:.1f} s, {r['polls']} polls, served "
              f"v{r['served_min']}..v{r['served_max']}, stored up to v{r['stored_max']}, "
              f"/readyz 503 in {r['readyz_503']}, failing in {r['failing']}, {r['faults']} "
              f"failed steps, {r['plant_min']:.0f} plant min, last (served, stored, readyz) "
              f"{r['last']}" + (f", {r['sets_in_window']} sets of the plant in its window "
                                "stored afterwards" if "sets_in_window" in r else ""))
    full, again, restarted = (r for _, r in rows[-3:])
    if a.start_full_kib is None and rows[0][1]["served_max"] == 0:
        problems.append("no set was served before the disk filled: nothing to keep serving")
    if full["readyz_503"] == 0 or full["failing"] == 0:
        problems.append("the full disk was never reported (/readyz 503, failing)")
    if full["faults"] < FULL_ATTEMPTS or full["plant_min"] < FULL_PLANT_MIN:
        problems.append(f"the disk-full phase spanned {full['faults']} failed steps and "
                        f"{full['plant_min']:.0f} plant min in {full['wall_s']:.0f} s, not "
                        f"{FULL_ATTEMPTS} and {FULL_PLANT_MIN:.0f}: too little to show the "
                        "served set staying put")
    if full["served_max"] != full["served_min"]:
        problems.append(f"the served set changed while the disk was full: {full}")
    if again["last"] is None or again["last"][0] != again["last"][1] or again["last"][2] != 200:
        problems.append(f"no recovery once the disk had room: last {again['last']}")
    if again["served_max"] <= full["served_max"]:
        problems.append("no new set was served once the disk had room")
    if restarted["last"] is None or restarted["served_min"] < again["served_max"]:
        problems.append(f"after the restart the served version went back: {restarted}")
    for p in problems[:20]:
        print("PROBLEM:", p)
    polls = sum(r["polls"] for _, r in rows)
    print(f"full disk: {polls} polls, {len(seen)} ETags, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
