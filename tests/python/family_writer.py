"""Independent second writer of contract recordings for the `head_b_table_c` and `trunnion_ac`
machine layouts.

Written from the contract documents only (docs/kinematics-conventions.md, section "Other
machine types"; docs/recording-format.md; config/machines/{head_b_table_c,trunnion_ac}.toml;
config/plans/{head_b_table_c,trunnion_ac}_patent.toml), without reading driftwatch's sources.
The MCAP writing, schemas and message layout are reused from contract_writer.py (the table_bc
second writer); the geometry here is new.

Model (mm, rad inside; um, urad at the interfaces):

* Table chain, outermost first, table sense: T_i(a) = Tr(q_i) Rot(u_i, -a) Tr(-q_i).
    head_b_table_c: p_machine = T_C(c) p_table,  q_C = (EX0C, EY0C, 0), u_C = Ry(EB0C) Rx(EA0C) Z
    trunnion_ac:    p_machine = T_A(a) T_C(c) p_table,
                    q_A = (0, EY0A, EZ0A), u_A = Rz(EC0A) Ry(EB0A) X,
                    q_C = (EX0C, EY0A + EY0C, 0) (C carried by A, relative_to_parent),
                    u_C = Ry(EB0C) Rx(EA0C) Z
* Head chain (head_b_table_c only), head frame (origin at the tool tip at the zero pose),
  direct sense: H(b) = Tr(q_B) Rot(u_B, +b) Tr(-q_B), q_B = (EX0B, 0, L + EZ0B), L = 200 mm,
  u_B = Rz(EC0B) Rx(EA0B) Y. The NC's nominal model H_nom has q = (0, 0, L), u = Y.
  Actual tip = commanded - H_nom(b)(0) + H(b)(s); tool axis (tip into spindle) w = R_H(b) Z.
  On trunnion_ac the tip is commanded + s and w = Z.
* Beam: table line through (0, -100, 70) along table X. Tool: cylinder of radius 5 mm along w,
  flat end at the tip, occupying the tip side {(x - tip).w >= 0}.
* End-face ("z") approach, moving out of the spindle (-w nominally): the trip is the commanded
  position where the flat end first touches a beam point within r of the tool axis (bisection
  on the moving coordinate of g(u) = max over those beam points of (X - tip).w).
* Lateral approach, moving across the beam and the tool axis from the side away from the
  machine origin (as seen along the tool axis), the tool end lateral_depth_mm past the beam
  along the tool axis: the trip is where the distance between the tool axis line and the beam
  line equals r (bisection).
* Latched = trip + N(0, 0.5 um) on the moving axis (latency 0, the shipped config), at 1 nm.
* The true errors are drawn once per recording (positions +-50 um, orientations +-100 urad;
  held errors 0) and held over its cycles (drawing them per cycle trips the service's
  step-size validation). Cycles run time-symmetric, a few minutes apart, spindle at 20000.

Truth sidecar (<out>.truth.json): per cycle the apparent (tool-relative) errors: every line
(table and head) shifted by -s. head_b_table_c: EX0B - sx, EZ0B - sz, EX0C - sx, EY0C - sy.
trunnion_ac: EY0A - sy, EZ0A - sz, EX0C - sx, and EY0C unchanged (the C line is measured from
the A line, which moves by -sy too); "errors_alt" gives EY0C - sy for the other reading.

CLI:
    python3 family_writer.py MACHINE OUT.mcap [--seed N] [--cycles N] [--tool-shift SX SY SZ]
                             [--sigma-um S] [--print-moves] [--solve [--plan FILE|none]]
--solve runs `target/release/driftwatch solve --json` on the file and prints per error the
z = (identified - truth) / sigma of every cycle, max |z| and RMS.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
from typing import Dict, List, Optional, Sequence, Tuple

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import contract_writer as cw  # noqa: E402

from contract_writer import add, sub, scale, dot, cross, unit, rot  # noqa: E402

Vec = Tuple[float, float, float]
X: Vec = (1.0, 0.0, 0.0)
Y: Vec = (0.0, 1.0, 0.0)
Z: Vec = (0.0, 0.0, 1.0)
UM, URAD = 1e-3, 1e-6

BEAM_POINT_MM: Vec = (0.0, -100.0, 70.0)
BEAM_DIRECTION: Vec = X
TOOL_ID = "EM10"
RADIUS_MM = 5.0
SIGMA_UM = 0.5
PIVOT_L_MM = 200.0

# plan parameters (both plans alike)
FEED = 100.0
RPM = 20000.0
CLEARANCE = 1.0
OVERTRAVEL = 1.5
LATERAL_DEPTH = 3.0

MACHINES = {
    "head_b_table_c": dict(
        identify=["EX0B", "EZ0B", "EX0C", "EY0C", "EA0C", "EB0C"],
        held={"EA0B": 0.0, "EC0B": 0.0},
        positions={"EX0B", "EZ0B", "EX0C", "EY0C"},
        tilt_letter="B",
        poses=[(0.0, 0.0), (0.0, -90.0), (0.0, -180.0), (0.0, -270.0), (-90.0, -90.0),
               (90.0, -270.0)],
    ),
    "trunnion_ac": dict(
        identify=["EY0A", "EZ0A", "EX0C", "EY0C", "EA0C", "EB0C"],
        held={"EB0A": 0.0, "EC0A": 0.0},
        positions={"EY0A", "EZ0A", "EX0C", "EY0C"},
        tilt_letter="A",
        poses=[(0.0, 0.0), (0.0, -90.0), (0.0, -180.0), (0.0, -270.0), (-90.0, 0.0),
               (-90.0, -180.0)],
    ),
}


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------
def _e(err: Dict[str, float], k: str) -> float:
    return err.get(k, 0.0)


def turn(q: Vec, u: Vec, t: float, p: Vec) -> Vec:
    """Tr(q) Rot(u, t) Tr(-q) p."""
    return add(q, rot(u, t, sub(p, q)))


def table_to_machine(machine: str, err: Dict[str, float], tilt_deg: float, c_deg: float,
                     p: Vec, direction: bool = False) -> Vec:
    c = math.radians(c_deg)
    a = math.radians(tilt_deg)
    u_c = unit(cw.rot_y(_e(err, "EB0C") * URAD, cw.rot_x(_e(err, "EA0C") * URAD, Z)))
    if machine == "head_b_table_c":
        q_c = (_e(err, "EX0C") * UM, _e(err, "EY0C") * UM, 0.0)
        return rot(u_c, -c, p) if direction else turn(q_c, u_c, -c, p)
    # trunnion_ac
    q_a = (0.0, _e(err, "EY0A") * UM, _e(err, "EZ0A") * UM)
    u_a = unit(cw.rot_z(_e(err, "EC0A") * URAD, cw.rot_y(_e(err, "EB0A") * URAD, X)))
    q_c = (_e(err, "EX0C") * UM, (_e(err, "EY0A") + _e(err, "EY0C")) * UM, 0.0)
    if direction:
        return rot(u_a, -a, rot(u_c, -c, p))
    return turn(q_a, u_a, -a, turn(q_c, u_c, -c, p))


def beam(machine: str, err: Dict[str, float], tilt_deg: float, c_deg: float) -> Tuple[Vec, Vec]:
    return (table_to_machine(machine, err, tilt_deg, c_deg, BEAM_POINT_MM),
            unit(table_to_machine(machine, err, tilt_deg, c_deg, BEAM_DIRECTION, True)))


def tool(machine: str, err: Dict[str, float], tilt_deg: float, s_um: Vec) -> Tuple[Vec, Vec]:
    """(tip offset = actual tip - commanded, tool axis w (tip into spindle)), machine frame."""
    s = scale(s_um, UM)
    if machine == "trunnion_ac":
        return s, Z
    b = math.radians(tilt_deg)
    q = (_e(err, "EX0B") * UM, 0.0, PIVOT_L_MM + _e(err, "EZ0B") * UM)
    u = unit(cw.rot_z(_e(err, "EC0B") * URAD, cw.rot_x(_e(err, "EA0B") * URAD, Y)))
    q0 = (0.0, 0.0, PIVOT_L_MM)
    h_nom_0 = turn(q0, Y, b, (0.0, 0.0, 0.0))
    h_s = turn(q, u, b, s)
    return sub(h_s, h_nom_0), unit(rot(u, b, Z))


def end_face_gap(tip: Vec, w: Vec, p: Vec, d: Vec, r: float) -> Optional[float]:
    """max over beam points X within r of the tool axis of (X - tip).w; None if none is."""
    # radial part of X(t) - tip = (p - tip) + t d, minus its w component
    v0 = sub(p, tip)
    a0 = sub(v0, scale(w, dot(v0, w)))
    a1 = sub(d, scale(w, dot(d, w)))
    A, B, C = dot(a1, a1), 2.0 * dot(a0, a1), dot(a0, a0) - r * r
    disc = B * B - 4.0 * A * C
    if disc < 0.0:
        return None
    t1 = (-B - math.sqrt(disc)) / (2.0 * A)
    t2 = (-B + math.sqrt(disc)) / (2.0 * A)
    return max(dot(v0, w) + t1 * dot(d, w), dot(v0, w) + t2 * dot(d, w))


def axis_beam_distance(tip: Vec, w: Vec, p: Vec, d: Vec) -> float:
    n = unit(cross(w, d))
    return abs(dot(sub(tip, p), n))


def trip(machine: str, err: Dict[str, float], s_um: Vec, move: dict) -> Vec:
    """Commanded position (mm) at the exact trip of `move` (bisection on the moving axis)."""
    tilt, c = move["pose"]
    p, d = beam(machine, err, tilt, c)
    off, w = tool(machine, err, tilt, s_um)
    i, sgn = "xyz".index(move["axis"]), move["direction"]
    start = move["start"]

    def at(u: float) -> Vec:
        cmd = list(start)
        cmd[i] = start[i] + sgn * u
        return tuple(cmd)

    if move["kind"] == "z":
        def f(u: float) -> float:       # < 0 before contact, > 0 after
            g = end_face_gap(add(at(u), off), w, p, d, RADIUS_MM)
            if g is None:
                raise ValueError(f"end-face approach at {move['pose']} misses the beam")
            return g
    else:
        def f(u: float) -> float:
            return RADIUS_MM - axis_beam_distance(add(at(u), off), w, p, d)
    lo, hi = 0.0, CLEARANCE + OVERTRAVEL
    if not (f(lo) < 0.0 < f(hi)):
        raise ValueError(f"no single trip in the move at {move['pose']} {move['kind']}: "
                         f"f(start)={f(lo)}, f(end)={f(hi)}")
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if f(mid) < 0.0:
            lo = mid
        else:
            hi = mid
    pos = at(0.5 * (lo + hi))
    if move["kind"] == "lateral":   # the tool end must be past the beam along the tool axis
        g = dot(sub(p, add(pos, off)), w)
        if g <= 0.0:
            raise ValueError("lateral approach: tool end not past the beam")
    return pos


def axis_of(v: Vec) -> Tuple[str, int]:
    i = max(range(3), key=lambda k: abs(v[k]))
    if abs(v[i]) < 0.999999:
        raise ValueError(f"motion {v} is not along a machine axis")
    return "xyz"[i], (1 if v[i] > 0 else -1)


def clean(v: Vec) -> Vec:
    return tuple(round(x, 9) + 0.0 for x in v)


def nominal_moves(machine: str) -> List[dict]:
    """The plan's approaches as listed ("z" then "lateral" per pose), from the nominal model."""
    out = []
    zero: Dict[str, float] = {}
    for tilt, c in MACHINES[machine]["poses"]:
        p, d = beam(machine, zero, tilt, c)
        _, w = tool(machine, zero, tilt, (0.0, 0.0, 0.0))
        p, d, w = clean(p), clean(d), clean(w)
        # end face: along the tool axis out of the spindle, onto the beam's probed point
        m = scale(w, -1.0)
        ax, sg = axis_of(m)
        nominal_trip = p
        start = clean(sub(nominal_trip, scale(m, CLEARANCE)))
        out.append(dict(pose=(tilt, c), kind="z", axis=ax, direction=sg, start=start,
                        nominal_trip=nominal_trip))
        # lateral: across the beam and the tool axis, from the side away from the origin
        n = unit(cross(w, d))
        side = 1.0 if dot(p, n) > 0 else -1.0
        out_dir = scale(n, side)                       # from the beam towards the start
        nominal_trip = clean(add(add(p, scale(out_dir, RADIUS_MM)), scale(w, -LATERAL_DEPTH)))
        start = clean(add(nominal_trip, scale(out_dir, CLEARANCE)))
        ax, sg = axis_of(scale(out_dir, -1.0))
        out.append(dict(pose=(tilt, c), kind="lateral", axis=ax, direction=sg, start=start,
                        nominal_trip=nominal_trip))
    return out


def apparent(machine: str, err: Dict[str, float], s_um: Vec) -> Tuple[Dict, Dict]:
    """(apparent errors, alternative reading) per kinematics-conventions."""
    sx, sy, sz = s_um
    e = dict(err)
    if machine == "head_b_table_c":
        e["EX0B"] -= sx
        e["EZ0B"] -= sz
        e["EX0C"] -= sx
        e["EY0C"] -= sy
        return e, dict(e)
    e["EY0A"] -= sy
    e["EZ0A"] -= sz
    e["EX0C"] -= sx
    alt = dict(e)
    alt["EY0C"] -= sy            # if EY0C were read as absolute
    return e, alt


# --------------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------------
def random_errors(machine: str, rng: random.Random) -> Dict[str, float]:
    m = MACHINES[machine]
    return {k: (rng.uniform(-50.0, 50.0) if k in m["positions"] else rng.uniform(-100.0, 100.0))
            for k in m["identify"]}


def write(machine: str, path: str, seed: int = 1, cycles: int = 3,
          s_um: Vec = (0.0, 0.0, 0.0), sigma_um: float = SIGMA_UM,
          cycle_gap_s: float = 240.0) -> dict:
    rng = random.Random(seed)
    m = MACHINES[machine]
    base = nominal_moves(machine)
    moves = base + list(reversed(base))        # time_symmetric
    seen: Dict[str, int] = {}
    labels = []
    for mv in moves:
        lab = f"{m['tilt_letter']}{cw.fmt_deg(mv['pose'][0])}C{cw.fmt_deg(mv['pose'][1])}/{mv['axis']}"
        seen[lab] = seen.get(lab, 0) + 1
        labels.append(f"{lab}#{seen[lab]}")
    msgs: Dict[str, List[Tuple[int, dict]]] = {t: [] for t in cw.schemas(cw.DRAFT_2020)}
    sec = 1_000_000_000
    t = cw.T0_NS
    msgs["/machine/info"].append((t, {"machine_id": f"{machine}-independent-1",
                                      "kinematics": machine,
                                      "software": "family_writer.py (independent)"}))
    msgs["/machine/state"].append((t, {"state": "idle", "program": None}))
    msgs["/spindle"].append((t, {"rpm": 0.0}))
    truth_cycles = []
    err = random_errors(machine, rng)          # the machine's errors, held over the recording
    for cycle in range(1, cycles + 1):
        if cycle > 1:
            t += int(cycle_gap_s * sec)
        cycle_start = t
        msgs["/machine/state"].append((t, {"state": "measuring", "program": "O9810"}))
        t += 5 * sec
        dets = []
        for lab, mv in zip(labels, moves):
            t += 5 * sec
            pos = list(trip(machine, err, s_um, mv))
            pos["xyz".index(mv["axis"])] += rng.gauss(0.0, sigma_um) * UM
            dets.append((t, {"cycle": cycle, "step": lab, "b_deg": mv["pose"][0],
                             "c_deg": mv["pose"][1], "axis": mv["axis"],
                             "direction": mv["direction"], "feed_mm_min": FEED,
                             "spindle_rpm": RPM, "tool_id": TOOL_ID,
                             "x_mm": cw.quantise(pos[0], 1e-6),
                             "y_mm": cw.quantise(pos[1], 1e-6),
                             "z_mm": cw.quantise(pos[2], 1e-6)}))
        tt = cycle_start + 5 * sec
        while tt < t + 2 * sec:
            msgs["/spindle"].append((tt, {"rpm": RPM}))
            tt += 10 * sec
        t += 2 * sec
        msgs["/spindle"].append((t, {"rpm": 0.0}))
        msgs["/machine/state"].append((t, {"state": "idle", "program": None}))
        msgs["/probe/detection"].extend(dets)
        t_ref = sum(x for x, _ in dets) // len(dets)
        app, alt = apparent(machine, err, s_um)
        truth_cycles.append({"cycle": cycle, "t_ns": t_ref,
                             "errors": {k: round(v, 6) for k, v in app.items()},
                             "errors_alt": {k: round(v, 6) for k, v in alt.items()},
                             "true_errors": {k: round(v, 6) for k, v in err.items()},
                             "detections": len(dets)})
        t += 10 * sec
    cw._write_mcap(path, msgs, cw.Options())
    side = {"writer": "tests/python/family_writer.py (independent second writer)",
            "machine": machine, "seed": seed, "sigma_um": sigma_um,
            "tool_shift_um": list(s_um),
            "units": {k: ("um" if k in m["positions"] else "urad") for k in m["identify"]},
            "moves": [dict(label=l, pose=list(mv["pose"]), kind=mv["kind"], axis=mv["axis"],
                           direction=mv["direction"], start=list(mv["start"]))
                      for l, mv in zip(labels[:len(base)], base)],
            "cycles": truth_cycles}
    with open(path + ".truth.json", "w") as f:
        json.dump(side, f, indent=1)
        f.write("\n")
    return side


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("machine", choices=sorted(MACHINES))
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cycles", type=int, default=3)
    ap.add_argument("--tool-shift", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                    metavar=("SX", "SY", "SZ"), help="tool-tip displacement, um (head frame)")
    ap.add_argument("--sigma-um", type=float, default=SIGMA_UM)
    ap.add_argument("--print-moves", action="store_true")
    ap.add_argument("--solve", action="store_true",
                    help="run `driftwatch solve` on the file and print (identified - truth)/sigma")
    ap.add_argument("--binary", default=DEFAULT_BINARY)
    ap.add_argument("--plan", default=None, help="plan passed to solve (default: the patent "
                    "plan file config/plans/<machine>_patent.toml; 'none' for no --plan)")
    a = ap.parse_args(argv)
    side = write(a.machine, a.out, a.seed, a.cycles, tuple(a.tool_shift), a.sigma_um)
    if a.print_moves:
        for mv in side["moves"]:
            print(mv)
    print(a.out, os.path.getsize(a.out), "bytes")
    if a.solve:
        plan = a.plan or os.path.join(REPO, "config", "plans", f"{a.machine}_patent.toml")
        print(json.dumps(check(a.machine, a.out, side, a.binary,
                               None if plan == "none" else plan)))
    return 0


REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
DEFAULT_BINARY = os.path.join(REPO, "target", "release", "driftwatch")


def check(machine: str, path: str, side: dict, binary: str, plan: Optional[str]) -> dict:
    """Solve `path` with driftwatch and compare every cycle with the sidecar's truth.
    Returns per error the z values (identified - truth) / sigma, max |z| and RMS, for the
    documented truth ("errors") and the alternative reading ("errors_alt")."""
    import subprocess
    cmd = [binary, "solve", "--machine", machine, "--recording", path, "--json"]
    if plan:
        cmd += ["--plan", plan]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    results = {r["cycle"]: r for r in (json.loads(l) for l in out.splitlines() if l.strip())}
    report = {"command": " ".join(cmd)}
    for key in ("errors", "errors_alt"):
        zs: Dict[str, List[float]] = {k: [] for k in MACHINES[machine]["identify"]}
        for c in side["cycles"]:
            r = results[c["cycle"]]
            if r["status"] != "ok":
                if key == "errors":
                    report.setdefault("not_ok", []).append([c["cycle"], r["status"],
                                                            r.get("reason")])
                continue
            for k in zs:
                zs[k].append((r["errors"][k] - c[key][k]) / r["sigma"][k])
        report[key] = {k: {"z": [round(z, 3) for z in v],
                           "max_abs": round(max(abs(z) for z in v), 3),
                           "rms": round(math.sqrt(sum(z * z for z in v) / len(v)), 3)}
                       for k, v in zs.items()}
    return report


if __name__ == "__main__":
    sys.exit(main())
