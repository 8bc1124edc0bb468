"""Conformance of a driftwatch binary with the recording contract, against recordings written by
the independent second writer (contract_writer.py).

usage: python3 check_conformance.py BINARY OUTDIR [--seed N] [--cycles N] [--only CASE,...]

First it checks that the writer's moves are those `BINARY plan --machine table_bc --plan patent`
prints (check plan_moves). Then, for every case of contract_writer.CASES, it writes
OUTDIR/<case>.mcap (and its truth sidecar), runs `BINARY solve --machine table_bc --recording F
--json` (plus the case's arguments, e.g. `--plan patent` for foreign_labels; for the latency
case --machine is a copy of config/machines/table_bc.toml with latency_ms = 3) and checks:
  * the solve exits 0 and prints one /cycle/result per cycle of the recording, same numbers;
  * every cycle has status "ok" and the /cycle/result fields of the contract;
  * every estimate is within 4 sigma of the writer's truth (apparent errors);
  * t_ns is the mean timestamp of the cycle's accepted detections (within 1 us);
  * driftwatch's extension field `nuisance` (when present): the setter height and lateral
    place within 2 um of the truth (this is how the latency case is seen at all: a skip
    latency common to every approach only moves the apparent setter).
A cycle cut short by the end of a truncated file (case cut_short) may be absent or rejected;
if it is solved, its estimates are checked too.
For the diagnosed cases (explicit_ok, retry, multi_cycle) it also runs `BINARY diagnose
--machine table_bc --recording F --out DIR` and checks: exit 0, DIR/diagnosis.json exists, no
refusal with "no usable detections", every accepted detection read (`readings`, `cycles`,
`unparsed_detections` 0).

It prints one line per check (PASS/FAIL and why), the z-scores' RMS over all estimates, and
closes with `N passed, M failed`; the exit status is non-zero on any failure.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import contract_writer as cw  # noqa: E402

Z_MAX = 4.0
CONTRACT_FIELDS = {"cycle", "t_ns", "status", "reason", "errors", "sigma", "residual_rms_um"}
SETTER_TOL_UM = 2.0          # 4 x the Cramer-Rao 0.42 um of the 12-approach plan, rounded up


def run(cmd, timeout=600):
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout, p.stderr


def tail(text: str, n: int = 200) -> str:
    text = " ".join(text.split())
    return text if len(text) <= n else "..." + text[-n:]


def check_solve(binary: str, path: str, truth: dict, extra, machine: str = cw.MACHINE) -> tuple:
    """Returns (problems, z-scores, summary)."""
    cmd = [binary, "solve", "--machine", machine, "--recording", path, "--json", *extra]
    rc, out, err = run(cmd)
    if rc != 0:
        return [f"solve exited {rc}: {tail(err or out)}"], [], ""
    results = []
    for line in out.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                results.append(json.loads(line))
            except json.JSONDecodeError:
                return [f"unparsable JSON line: {line[:80]}"], [], ""
    problems, zs = [], []
    expected = {c["cycle"]: c for c in truth["cycles"]}
    # a cycle cut short by a power loss may be absent, rejected, or solved from what is left
    partial = {c["cycle"] for c in truth["cycles"] if c.get("complete") is False}
    got = [r.get("cycle") for r in results]
    if sorted(set(got) | partial) != sorted(expected) or len(set(got)) != len(got):
        problems.append(f"cycles {got}, expected {sorted(expected)}"
                        + (f" (cycle {sorted(partial)} optional)" if partial else ""))
    worst = (0.0, "")
    for r in results:
        c = r.get("cycle")
        if c not in expected:
            continue
        if r.get("status") != "ok":
            if c not in partial:
                problems.append(f"cycle {c}: status {r.get('status')} ({r.get('reason')})")
            continue
        missing = CONTRACT_FIELDS - set(r)
        names = set(cw.IDENTIFIED)
        if missing or set(r["errors"]) != names or set(r["sigma"]) != names:
            problems.append(f"cycle {c}: /cycle/result fields {sorted(r)}, errors "
                            f"{sorted(r.get('errors', {}))}, sigma {sorted(r.get('sigma', {}))}")
            continue
        tr = expected[c]
        if c not in partial and abs(int(r.get("t_ns", 0)) - tr["t_ns"]) > 1000:
            problems.append(f"cycle {c}: t_ns {r.get('t_ns')} is not the mean of the accepted "
                            f"detections' times {tr['t_ns']} "
                            f"({int(r.get('t_ns', 0)) - tr['t_ns']:+d} ns)")
        for k in cw.IDENTIFIED:
            est, sig = r["errors"].get(k), r["sigma"].get(k)
            if est is None or not sig or sig <= 0:
                problems.append(f"cycle {c}: {k} missing or sigma {sig}")
                continue
            z = (est - tr["errors"][k]) / sig
            zs.append(z)
            if abs(z) > abs(worst[0]):
                worst = (z, f"cycle {c} {k} {est:.2f} vs {tr['errors'][k]:.2f} +- {sig:.2f}")
            if abs(z) > Z_MAX:
                problems.append(f"cycle {c}: {k} = {est:.3f}, truth {tr['errors'][k]:.3f}, "
                                f"sigma {sig:.3f}, z {z:+.1f}")
        # driftwatch's extension: the setter nuisance (not in the contract; checked when
        # present): height = table z shift, lateral = table y shift, relative to the tool tip
        nu = r.get("nuisance") or {}
        want = truth.get("setter_apparent_um")
        for key, i in (("setter_height_um", 2), ("setter_lateral_um", 1)):
            if want and key in nu and abs(nu[key] - want[i]) > SETTER_TOL_UM:
                problems.append(f"cycle {c}: nuisance {key} {nu[key]:.2f}, truth {want[i]:.2f}")
    rms = math.sqrt(sum(z * z for z in zs) / len(zs)) if zs else float("nan")
    summary = (f"{len(results)} cycles, {len(zs)} estimates, z RMS {rms:.2f}, "
               f"max |z| {abs(worst[0]):.2f} ({worst[1]})")
    return problems, zs, summary


def check_diagnose(binary: str, path: str, truth: dict, outdir: str) -> tuple:
    cmd = [binary, "diagnose", "--machine", cw.MACHINE, "--recording", path, "--out", outdir]
    rc, out, err = run(cmd)
    problems = []
    if "no usable detections" in (out + err):
        problems.append(f"refused: {tail(err + ' ' + out)}")
    if rc != 0:
        problems.append(f"diagnose exited {rc}: {tail(err or out)}")
    f = os.path.join(outdir, "diagnosis.json")
    if not os.path.exists(f):
        problems.append("no diagnosis.json")
        return problems, ""
    d = json.load(open(f))
    accepted = sum(c["accepted"] for c in truth["cycles"])
    if d.get("readings") != accepted:
        problems.append(f"readings {d.get('readings')}, the recording has {accepted} trips")
    if d.get("unparsed_detections"):
        problems.append(f"unparsed_detections {d.get('unparsed_detections')}")
    if d.get("cycles") != len(truth["cycles"]):
        problems.append(f"cycles {d.get('cycles')}, expected {len(truth['cycles'])}")
    return problems, (f"{d.get('readings')} readings, {d.get('cycles')} cycles, "
                      f"{len(d.get('accepted', []))} effects accepted")


def check_plan(binary: str) -> tuple:
    """The writer's moves against `BINARY plan --machine table_bc --plan patent` (its table:
    each "Probe LABEL" row ends at the nominal trip, the row before it at the start).
    Returns (problems, summary), or (None, why) when the table cannot be parsed."""
    rc, out, err = run([binary, "plan", "--machine", cw.MACHINE, "--plan", "patent"])
    if rc != 0:
        return [f"plan exited {rc}: {tail(err or out)}"], ""
    rows = []
    for line in out.splitlines():
        f = line.split()
        try:
            rows.append(([float(v) for v in f[2:7]], " ".join(f[7:])))
        except (ValueError, IndexError):
            continue
    probes = [(rows[i - 1][0], rows[i][0], rows[i][1].split()[1])
              for i in range(1, len(rows)) if rows[i][1].startswith("Probe ")]
    if not probes:
        return None, "no Probe rows in the plan's table"
    mine = cw.time_symmetric(cw.nominal_approaches())
    nominal = cw.Truth(errors={k: 0.0 for k in cw.IDENTIFIED})
    labels = cw.step_labels(mine, cw.Options())
    problems = []
    if len(probes) != len(mine):
        problems.append(f"{len(probes)} probe moves, the writer has {len(mine)}")
    for (start, end, label), a, my_label in zip(probes, mine, labels):
        trip = cw.trip(nominal, a)
        d = [e - s for e, s in zip(end[:3], start[:3])]
        moving = max(range(3), key=lambda i: abs(d[i]))
        same = (all(abs(x - y) < 1e-3 for x, y in zip(end[:3], trip))
                and all(abs(x - y) < 1e-3 for x, y in zip(start[:3], a.start))
                and (end[3], end[4]) == a.pose and "xyz"[moving] == a.axis
                and (1 if d[moving] > 0 else -1) == a.direction)
        if not same:
            problems.append(f"{label}: plan {start} -> {end}, writer {a.pose} {a.axis}"
                            f"{a.direction:+d} {a.start} -> {trip}")
        elif label != my_label:
            problems.append(f"label {label} vs the writer's {my_label}")
    return problems, f"{len(probes)} probe moves agree (pose, axis, direction, start, trip)"


def main() -> int:
    ap = argparse.ArgumentParser(description="conformance of driftwatch with the contract")
    ap.add_argument("binary")
    ap.add_argument("outdir")
    ap.add_argument("--seed", type=int, default=20240305)
    ap.add_argument("--cycles", type=int, default=None, help="cycles per case (default 3)")
    ap.add_argument("--only", default="", help="comma-separated case names")
    args = ap.parse_args()
    os.makedirs(args.outdir, exist_ok=True)
    names = [n for n in cw.CASES if not args.only or n in args.only.split(",")]
    passed = failed = 0
    all_z = []
    if not args.only or "plan_moves" in args.only.split(","):
        problems, summary = check_plan(args.binary)
        if problems is None:
            print(f"SKIP plan_moves: {summary}")
        elif problems:
            failed += 1
            print("FAIL plan_moves: " + "; ".join(problems[:4]))
        else:
            passed += 1
            print(f"PASS plan_moves: {summary}")
    for name in names:
        case = cw.CASES[name]
        path = os.path.join(args.outdir, f"{name}.mcap")
        truth = cw.write_case(name, path, args.seed, args.cycles)
        machine = cw.MACHINE
        if case.get("machine_edit"):
            machine = cw.machine_file(args.outdir, name, case["machine_edit"])
        problems, zs, summary = check_solve(args.binary, path, truth, case["solve_args"],
                                            machine)
        all_z += zs
        if problems:
            failed += 1
            print(f"FAIL {name}: {len(problems)} problems: " + "; ".join(problems[:4])
                  + (" ..." if len(problems) > 4 else "") + (f" [{summary}]" if summary else ""))
        else:
            passed += 1
            print(f"PASS {name}: {summary}")
        if case.get("diagnose"):
            ddir = os.path.join(args.outdir, f"{name}.diagnosis")
            problems, summary = check_diagnose(args.binary, path, truth, ddir)
            if problems:
                failed += 1
                print(f"FAIL {name}/diagnose: " + "; ".join(problems))
            else:
                passed += 1
                print(f"PASS {name}/diagnose: {summary}")
        sys.stdout.flush()
    if all_z:
        rms = math.sqrt(sum(z * z for z in all_z) / len(all_z))
        print(f"z RMS over all {len(all_z)} estimates: {rms:.2f} (expect about 1)")
    print(f"{passed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
