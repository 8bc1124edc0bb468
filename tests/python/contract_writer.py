"""Independent writer of contract recordings (recording format v1) for the `table_bc` machine.

This module is the *second writer* of the recording contract: it was written from the contract
documents only (docs/kinematics-conventions.md, docs/recording-format.md,
config/machines/table_bc.toml, config/plans/patent.toml), without reading driftwatch's sources.
It simulates the patent's laser tool-setter cycle (JP6803043, Fig. 1) on a machine with given
true location errors and writes what an NC gateway would record: an MCAP file with `json`
messages and `jsonschema` schemas on `/machine/info`, `/machine/state`, `/spindle` and
`/probe/detection` (plus, in some layouts, a vendor topic the readers must ignore), and a sidecar
`<file>.truth.json` with the true (apparent) errors of each cycle.

Geometry (kinematics-conventions.md), in mm and rad inside this module:

    p_machine = T_B(b) * T_C(c) * p_table
    T_B(b) = Tr(q_B) Rot(u_B, -b) Tr(-q_B), q_B = (EX0B, 0, EZ0B),        u_B = Rz(EC0B) Rx(EA0B) Y
    T_C(c) = Tr(q_C) Rot(u_C, -c) Tr(-q_C), q_C = (EX0B + EX0C, EY0C, 0), u_C = Ry(EB0C) Rx(EA0C) Z

so that at B = C = 0 the table frame is the machine frame whatever the errors. The beam is the
table-frame line through (d, -R, H) = (0, -100, 70) mm (plus an optional setter offset) along
table X. The tool is a vertical cylinder of radius r = 5 mm whose flat end is the tool reference
point; its actual tip is the commanded position plus an optional tool-tip displacement `s`.

* Lateral approach (x or y): trip where the horizontal distance between the tool axis and the
  beam line equals r, coming from outside, the tool end below the beam.
* Vertical approach (-z): trip where the end face reaches the highest point of the beam line
  within r (horizontally) of the tool axis.
* The latched (commanded) position is the trip plus `feed * latency` along the motion, plus
  Gaussian noise (sigma 0.5 um by default) on the moving axis.

The truth written to the sidecar is the *apparent* error set (EX0B - sx, EZ0B - sz, EY0C - sy,
the others unchanged), which is what `/cycle/result` must report.

The cycle's moves (poses, approach axes and directions, start positions, feed) are derived here
from the documents; they agree move for move with what `driftwatch plan --machine table_bc
--plan patent` prints (check_conformance.py checks that too). Labels follow the scheme that
command prints ("B0C-90/x#1", the pass after '#') unless a case says otherwise.

Cases (CASES below; `--list` prints them): plain, explicit_ok, repeated_labels, retry,
foreign_labels, other_layout, other_layout_lz4, setter_tool_offsets, latency, aborted,
angle_aliases, minimal, duplicate_message, sequential, cut_short, multi_cycle.

CLI:
    python3 contract_writer.py CASE OUT.mcap [--seed N] [--cycles N]   # one case
    python3 contract_writer.py all OUTDIR [--seed N] [--cycles N]       # every case + cases.json
    python3 contract_writer.py --list
"""
from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
import zlib
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from mcap.writer import CompressionType, Writer

Vec = Tuple[float, float, float]

# --------------------------------------------------------------------------------------------
# The machine and the plan, as documented (config/machines/table_bc.toml, config/plans/patent.toml)
# --------------------------------------------------------------------------------------------
MACHINE = "table_bc"
BEAM_POINT_MM: Vec = (0.0, -100.0, 70.0)     # table frame (d, -R, H)
BEAM_DIRECTION: Vec = (1.0, 0.0, 0.0)        # table X
TOOL_ID = "EM10"
TOOL_RADIUS_MM = 5.0
SIGMA_UM = 0.5
LATENCY_MS = 0.0                             # calibrated skip latency of the config

FEED_MM_MIN = 100.0
SPINDLE_RPM = 20000.0
CLEARANCE_MM = 1.0
OVERTRAVEL_MM = 1.5
LATERAL_DEPTH_MM = 3.0
POSES = [(0.0, 0.0), (0.0, -90.0), (0.0, -180.0), (0.0, -270.0), (-90.0, -270.0), (90.0, -90.0)]

IDENTIFIED = ["EX0B", "EZ0B", "EY0C", "EX0C", "EA0C", "EB0C"]
POSITION_ERRORS = {"EX0B", "EZ0B", "EY0C", "EX0C"}   # um; the rest urad

T0_NS = 1_709_625_600_000_000_000                   # 2024-03-05T08:00:00Z


# --------------------------------------------------------------------------------------------
# Small vector algebra (no numpy)
# --------------------------------------------------------------------------------------------
def add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def scale(a: Vec, k: float) -> Vec:
    return (a[0] * k, a[1] * k, a[2] * k)


def dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def unit(a: Vec) -> Vec:
    return scale(a, 1.0 / math.sqrt(dot(a, a)))


def rot(u: Vec, t: float, p: Vec) -> Vec:
    """Right-handed rotation of p by angle t (rad) about the unit vector u (Rodrigues)."""
    c, s = math.cos(t), math.sin(t)
    return add(add(scale(p, c), scale(cross(u, p), s)), scale(u, dot(u, p) * (1.0 - c)))


def rot_x(t: float, p: Vec) -> Vec:
    return rot((1.0, 0.0, 0.0), t, p)


def rot_y(t: float, p: Vec) -> Vec:
    return rot((0.0, 1.0, 0.0), t, p)


def rot_z(t: float, p: Vec) -> Vec:
    return rot((0.0, 0.0, 1.0), t, p)


# --------------------------------------------------------------------------------------------
# The machine model
# --------------------------------------------------------------------------------------------
@dataclass
class Truth:
    """The machine's true state during one detection. Errors in um / urad (contract units)."""
    errors: Dict[str, float]                          # the six identified errors
    held: Dict[str, float] = field(default_factory=lambda: {"EA0B": 0.0, "EC0B": 0.0})
    setter_offset_um: Vec = (0.0, 0.0, 0.0)           # beam point shift, table frame
    tool_shift_um: Vec = (0.0, 0.0, 0.0)              # tool-tip displacement s, machine frame
    radius_mm: float = TOOL_RADIUS_MM
    latency_ms: float = LATENCY_MS

    def apparent(self) -> Dict[str, float]:
        """The apparent (tool-relative) errors a cycle measures (kinematics-conventions.md)."""
        sx, sy, sz = self.tool_shift_um
        e = dict(self.errors)
        e["EX0B"] -= sx
        e["EY0C"] -= sy
        e["EZ0B"] -= sz
        return e


def table_to_machine(truth: Truth, b_deg: float, c_deg: float, p: Vec, is_direction=False) -> Vec:
    """p_machine = T_B(b) T_C(c) p_table with the actual axis lines (points or directions)."""
    e, h = truth.errors, truth.held
    um, urad = 1e-3, 1e-6
    q_b = (e["EX0B"] * um, 0.0, e["EZ0B"] * um)
    u_b = unit(rot_z(h["EC0B"] * urad, rot_x(h["EA0B"] * urad, (0.0, 1.0, 0.0))))
    q_c = ((e["EX0B"] + e["EX0C"]) * um, e["EY0C"] * um, 0.0)
    u_c = unit(rot_y(e["EB0C"] * urad, rot_x(e["EA0C"] * urad, (0.0, 0.0, 1.0))))
    b = math.radians(math.fmod(b_deg, 360.0))
    c = math.radians(math.fmod(c_deg, 360.0))
    if is_direction:
        return rot(u_b, -b, rot(u_c, -c, p))
    p = add(q_c, rot(u_c, -c, sub(p, q_c)))
    return add(q_b, rot(u_b, -b, sub(p, q_b)))


def beam_in_machine(truth: Truth, b_deg: float, c_deg: float) -> Tuple[Vec, Vec]:
    """The beam line (point, unit direction) in the machine frame at pose (b, c)."""
    point = add(BEAM_POINT_MM, scale(truth.setter_offset_um, 1e-3))
    return (table_to_machine(truth, b_deg, c_deg, point),
            unit(table_to_machine(truth, b_deg, c_deg, BEAM_DIRECTION, is_direction=True)))


@dataclass(frozen=True)
class Approach:
    """One move of the cycle, as the NC receives it."""
    pose: Tuple[float, float]          # commanded (b_deg, c_deg)
    axis: str                          # "x" | "y" | "z"
    direction: int                     # -1 | +1
    start: Vec                         # commanded start position, mm
    feed: float = FEED_MM_MIN
    kind: str = ""                     # "z" or "lateral" (the plan's approach name)

    @property
    def index(self) -> int:
        return "xyz".index(self.axis)

    def end(self) -> Vec:
        """End of the move: the nominal trip plus the overtravel, along the motion."""
        s = list(self.start)
        s[self.index] += self.direction * (CLEARANCE_MM + OVERTRAVEL_MM)
        return tuple(s)


def nominal_approaches() -> List[Approach]:
    """The patent cycle's 12 approaches (as listed), derived from the documents.

    Per pose the plan lists "z" then "lateral". The z approach comes down on the beam's nominal
    probed point; the lateral one moves across the beam (the horizontal axis perpendicular to it)
    from the side away from the rotary table (outside: for B = -90 from +X as the convention
    says, for the B = 0 poses from outside the setter radius R), the tool end 3 mm below it.
    """
    nominal = Truth(errors={k: 0.0 for k in IDENTIFIED})
    out = []
    for b, c in POSES:
        p, d = beam_in_machine(nominal, b, c)
        p = tuple(round(v, 9) + 0.0 for v in p)
        out.append(Approach((b, c), "z", -1, (p[0], p[1], p[2] + CLEARANCE_MM), kind="z"))
        # lateral axis: the horizontal machine axis across the (horizontal) beam
        axis = "y" if abs(d[0]) > abs(d[1]) else "x"
        i = "xyz".index(axis)
        if b == 0.0:
            outward = 1.0 if p[i] > 0 else -1.0          # away from the C axis
        else:
            outward = 1.0 if p[0] > 0 else -1.0          # the table top faces +-X: from outside
        trip = list(p)
        trip[i] += outward * TOOL_RADIUS_MM
        trip[2] = p[2] - LATERAL_DEPTH_MM
        start = list(trip)
        start[i] += outward * CLEARANCE_MM
        out.append(Approach((b, c), axis, -int(outward), tuple(start), kind="lateral"))
    return out


def time_symmetric(approaches: Sequence[Approach]) -> List[Approach]:
    """Every approach forward, then every approach again in reverse order (24 for the patent)."""
    return list(approaches) + list(reversed(approaches))


def trip(truth: Truth, a: Approach) -> Vec:
    """Commanded position (mm) at the trip of approach `a`, before latency and noise."""
    p, d = beam_in_machine(truth, *a.pose)
    s = scale(truth.tool_shift_um, 1e-3)
    r = truth.radius_mm
    actual = add(a.start, s)                                   # actual tool tip at the start
    if a.axis == "z":
        # beam points within r of the tool axis: |p_xy + t d_xy - q_xy| <= r
        qx, qy = actual[0] - p[0], actual[1] - p[1]
        A = d[0] ** 2 + d[1] ** 2
        B = -2.0 * (d[0] * qx + d[1] * qy)
        C = qx * qx + qy * qy - r * r
        disc = B * B - 4 * A * C
        if disc < 0:
            raise ValueError(f"z approach at {a.pose} misses the beam")
        t1, t2 = (-B - math.sqrt(disc)) / (2 * A), (-B + math.sqrt(disc)) / (2 * A)
        z_top = p[2] + max(t1 * d[2], t2 * d[2])
        if actual[2] < z_top:
            raise ValueError(f"z approach at {a.pose} starts below the beam")
        return (a.start[0], a.start[1], z_top - s[2])
    # lateral: signed horizontal distance f = dhat_xy x (q - p)_xy, linear in the moving axis
    n = math.hypot(d[0], d[1])
    dx, dy = d[0] / n, d[1] / n

    def f(q: Vec) -> float:
        return dx * (q[1] - p[1]) - dy * (q[0] - p[0])

    f0 = f(actual)
    slope = dx if a.axis == "y" else -dy                       # df / d(moving coordinate)
    side = 1.0 if f0 > 0 else -1.0
    if abs(f0) <= r or side * slope * a.direction >= 0:
        raise ValueError(f"lateral approach at {a.pose} does not come from outside")
    u = actual[a.index] + (side * r - f0) / slope
    pos = list(actual)
    pos[a.index] = u
    # the tool end must be below the beam at the contact
    t_c = (pos[0] - p[0]) * d[0] + (pos[1] - p[1]) * d[1]
    if pos[2] >= p[2] + t_c * d[2]:
        raise ValueError(f"lateral approach at {a.pose}: tool end not below the beam")
    return tuple(pos[i] - s[i] for i in range(3))


def latched(truth: Truth, a: Approach, rng: random.Random, sigma_um: float) -> Vec:
    """The position the NC latches: trip + feed * latency along the motion + noise (mm)."""
    pos = list(trip(truth, a))
    pos[a.index] += a.direction * a.feed / 60.0 * truth.latency_ms * 1e-3
    if sigma_um > 0:
        pos[a.index] += rng.gauss(0.0, sigma_um) * 1e-3
    return tuple(pos)


# --------------------------------------------------------------------------------------------
# Labels
# --------------------------------------------------------------------------------------------
def fmt_deg(v: float) -> str:
    return f"{v:g}"


# --------------------------------------------------------------------------------------------
# Recording
# --------------------------------------------------------------------------------------------
DRAFT_2020 = "https://json-schema.org/draft/2020-12/schema"
DRAFT_07 = "http://json-schema.org/draft-07/schema#"


def schemas(draft: str) -> Dict[str, dict]:
    num = {"type": "number"}
    return {
        "/machine/info": {
            "$schema": draft, "title": "machine_info", "type": "object",
            "properties": {"machine_id": {"type": "string"}, "kinematics": {"type": "string"},
                           "software": {"type": "string"}},
            "required": ["machine_id", "kinematics"]},
        "/machine/state": {
            "$schema": draft, "title": "machine_state", "type": "object",
            "properties": {"state": {"enum": ["off", "idle", "cutting", "measuring", "alarm"]},
                           "program": {"type": ["string", "null"]}},
            "required": ["state"]},
        "/spindle": {
            "$schema": draft, "title": "spindle", "type": "object",
            "properties": {"rpm": num}, "required": ["rpm"]},
        "/probe/detection": {
            "$schema": draft, "title": "probe_detection", "type": "object",
            "properties": {
                "cycle": {"type": "integer"}, "step": {"type": "string"},
                "b_deg": num, "c_deg": num, "axis": {"enum": ["x", "y", "z"]},
                "direction": {"enum": [-1, 1]}, "feed_mm_min": num, "spindle_rpm": num,
                "tool_id": {"type": "string"}, "x_mm": num, "y_mm": num, "z_mm": num,
                "status": {"enum": ["ok", "no_trip", "aborted"]}},
            "required": ["cycle", "step", "b_deg", "c_deg", "axis", "direction", "feed_mm_min",
                         "spindle_rpm", "tool_id", "x_mm", "y_mm", "z_mm"]},
        "/vendor/coolant": {
            "$schema": draft, "title": "vendor_coolant", "type": "object",
            "properties": {"pressure_bar": num, "on": {"type": "boolean"}}},
    }


@dataclass
class Options:
    """How a recording is written (the conformance cases differ only here)."""
    cycles: int = 3
    seed: int = 20240305
    sigma_um: float = SIGMA_UM
    resolution_mm: float = 1e-4          # the NC's latch resolution (0.1 um)
    latency_ms: float = LATENCY_MS       # true skip latency (the solve must be told the same)
    labels: str = "plan"                 # "plan": unique per move, "same": both passes alike,
                                         # "foreign": P01, P02, ... in order of recording
    status: str = "absent"               # "absent" | "ok" (explicit on every detection)
    retry: bool = False                  # one approach per cycle fails once, then retried
    retry_status: str = "no_trip"        # how it fails: "no_trip" (x/y/z = end of the move) or
                                         # "aborted" (stopped 0.4 mm into the move)
    c_alias: bool = False                # write c_deg modulo 360 in [0, 360) (-270 as 90)
    duplicate: bool = False              # one detection per cycle recorded twice (a gateway
                                         # resend: same time, same body); it counts once
    order: str = "time_symmetric"        # or "as_listed"
    compression: str = "zstd"            # "zstd" | "lz4" | "none"
    chunk_size: int = 1 << 20
    channel_order: Sequence[str] = ("/machine/info", "/machine/state", "/spindle",
                                    "/probe/detection")
    write_by_channel: bool = False       # write all of one channel, then the next (per-channel
                                         # time order only, as the contract allows)
    extra_fields: bool = False           # unknown fields in detections
    vendor_topic: bool = False           # an unknown topic with its own schema
    schema_draft: str = DRAFT_2020
    step_s: float = 5.0                  # time between detections
    cycle_gap_s: float = 600.0           # from one cycle's end to the next one's start
    cutting: bool = False                # cut between cycles (multi-cycle thermal case)
    cut_rpm: Sequence[float] = (12000.0,)
    drift: Optional[Callable[[float], Dict[str, float]]] = None   # hours -> error change
    errors: Dict[str, float] = field(default_factory=lambda: dict(DEFAULT_ERRORS))
    setter_offset_um: Vec = (0.0, 0.0, 0.0)
    tool_shift_um: Vec = (0.0, 0.0, 0.0)
    cut_fraction: Optional[float] = None     # cut the file (power loss) inside the chunk that
                                             # holds this fraction of the detections


DEFAULT_ERRORS = {"EX0B": 12.0, "EZ0B": -8.0, "EY0C": 6.0, "EX0C": -15.0,
                  "EA0C": 40.0, "EB0C": -25.0}


def step_labels(moves: Sequence[Approach], opts: Options) -> List[str]:
    """Labels of one cycle's moves.

    "plan": the scheme `driftwatch plan` prints, "B0C-90/x#1" (pass number after '#');
    "same": "B0C-90/x" on both passes; "foreign": "P01", "P02", ... in order of recording.
    """
    seen: Dict[str, int] = {}
    labels = []
    for i, a in enumerate(moves):
        base = f"B{fmt_deg(a.pose[0])}C{fmt_deg(a.pose[1])}/{a.axis}"
        seen[base] = seen.get(base, 0) + 1
        if opts.labels == "foreign":
            labels.append(f"P{i + 1:02d}")
        elif opts.labels == "same":
            labels.append(base)
        else:
            labels.append(f"{base}#{seen[base]}")
    return labels


def quantise(v: float, step: float) -> float:
    """A latched coordinate at the NC's resolution, printed without binary noise."""
    digits = max(0, -int(math.floor(math.log10(step) + 1e-9)))
    return round(round(v / step) * step, digits) + 0.0


def _errors_at(opts: Options, t_ns: int) -> Dict[str, float]:
    """The true errors at time t_ns (constant plus the optional drift)."""
    err = dict(opts.errors)
    if opts.drift:
        for k, v in opts.drift((t_ns - T0_NS) / 3.6e12).items():
            err[k] += v
    return err


def write_recording(path: str, opts: Options, case: str = "custom") -> dict:
    """Simulate `opts.cycles` cycles and write `path` and `path + ".truth.json"`.

    Timeline: idle at the start; before each cycle after the first either a cutting run (state
    `cutting`, spindle at a cutting speed) and a minute of idle, or an idle gap; each cycle is
    state `measuring` with the spindle at 20000 min^-1 (logged every 10 s), one detection every
    `step_s` seconds, then `idle` with the spindle stopped. Returns the sidecar's content.
    """
    rng = random.Random(opts.seed)
    base = nominal_approaches()
    moves = time_symmetric(base) if opts.order == "time_symmetric" else list(base)
    labels = step_labels(moves, opts)
    msgs: Dict[str, List[Tuple[int, dict]]] = {t: [] for t in schemas(DRAFT_2020)}
    sec = 1_000_000_000

    def spindle_run(t_from: int, t_to: int, rpm: float) -> None:
        """A turning spindle: logged at the change, then every 10 s."""
        tt = t_from
        while tt < t_to:
            msgs["/spindle"].append((tt, {"rpm": rpm}))
            tt += 10 * sec

    t = T0_NS
    msgs["/machine/info"].append((t, {"machine_id": "bc-independent-1", "kinematics": MACHINE,
                                      "software": "contract_writer.py (independent)"}))
    msgs["/machine/state"].append((t, {"state": "idle", "program": None}))
    msgs["/spindle"].append((t, {"rpm": 0.0}))
    if opts.vendor_topic:
        msgs["/vendor/coolant"].append((t, {"pressure_bar": 0.0, "on": False}))
    truth_cycles = []
    for cycle in range(1, opts.cycles + 1):
        if cycle > 1 and opts.cutting:
            rpm = opts.cut_rpm[(cycle - 2) % len(opts.cut_rpm)]
            cut_end = t + int((opts.cycle_gap_s - 180.0) * sec)
            msgs["/machine/state"].append((t, {"state": "cutting", "program": "O1001"}))
            spindle_run(t, cut_end, rpm)
            t = cut_end
            msgs["/spindle"].append((t, {"rpm": 0.0}))
            msgs["/machine/state"].append((t, {"state": "idle", "program": None}))
            t += 60 * sec
        elif cycle > 1:
            t += int(opts.cycle_gap_s * sec)
        # the measurement cycle
        cycle_start = t
        msgs["/machine/state"].append((t, {"state": "measuring", "program": "O9810"}))
        if opts.vendor_topic:
            msgs["/vendor/coolant"].append((t, {"pressure_bar": 6.5, "on": True}))
        t += 5 * sec                                  # spindle up, tool to the first pose
        fail_at = rng.randrange(len(moves)) if opts.retry else -1
        detections: List[Tuple[int, dict]] = []
        for i, (label, a) in enumerate(zip(labels, moves)):
            for status in ([opts.retry_status, "ok"] if i == fail_at else ["ok"]):
                t += int(opts.step_s * sec)
                truth = Truth(errors=_errors_at(opts, t), setter_offset_um=opts.setter_offset_um,
                              tool_shift_um=opts.tool_shift_um, latency_ms=opts.latency_ms)
                if status == "no_trip":
                    pos = a.end()                     # the move ended without a trip
                elif status == "aborted":             # stopped before the trip
                    pos = list(a.start)
                    pos[a.index] += a.direction * 0.4
                else:
                    pos = latched(truth, a, rng, opts.sigma_um)
                c_deg = a.pose[1] % 360.0 if opts.c_alias else a.pose[1]
                body = {"cycle": cycle, "step": label, "b_deg": a.pose[0], "c_deg": c_deg,
                        "axis": a.axis, "direction": a.direction, "feed_mm_min": a.feed,
                        "spindle_rpm": SPINDLE_RPM, "tool_id": TOOL_ID,
                        "x_mm": quantise(pos[0], opts.resolution_mm),
                        "y_mm": quantise(pos[1], opts.resolution_mm),
                        "z_mm": quantise(pos[2], opts.resolution_mm)}
                if status != "ok" or opts.status == "ok":
                    body["status"] = status
                if opts.extra_fields:
                    body["operator"] = "A"
                    body["beam_intensity"] = round(0.9 + 0.05 * rng.random(), 3)
                detections.append((t, body))
        spindle_run(cycle_start + 5 * sec, t + 2 * sec, SPINDLE_RPM)
        t += 2 * sec
        msgs["/spindle"].append((t, {"rpm": 0.0}))
        msgs["/machine/state"].append((t, {"state": "idle", "program": None}))
        if opts.vendor_topic:
            msgs["/vendor/coolant"].append((t, {"pressure_bar": 0.0, "on": False}))
        msgs["/probe/detection"].extend(detections)
        if opts.duplicate:
            msgs["/probe/detection"].append(detections[rng.randrange(len(detections))])
        ok = [tt for tt, body in detections if body.get("status", "ok") == "ok"]
        t_ref = sum(ok) // len(ok)
        err = _errors_at(opts, t_ref)     # slow drift, time-symmetric order: truth at t_ref
        ref = Truth(errors=err, tool_shift_um=opts.tool_shift_um)
        truth_cycles.append({
            "cycle": cycle, "t_ns": t_ref,
            "errors": {k: round(v, 6) for k, v in ref.apparent().items()},
            "true_errors": {k: round(v, 6) for k, v in err.items()},
            "detections": len(detections), "accepted": len(ok)})
        t += 10 * sec

    _write_mcap(path, msgs, opts)
    cut = None
    if opts.cut_fraction is not None:
        times = sorted(tt for tt, _ in msgs["/probe/detection"])
        t_cut = times[int(opts.cut_fraction * (len(times) - 1))]
        cut = _cut_short(path, t_cut)
        # keep the cycles with any detection left; mark those wholly in complete chunks
        last = {}
        for tt, body in msgs["/probe/detection"]:
            last[body["cycle"]] = max(last.get(body["cycle"], 0), tt)
        first = {}
        for tt, body in msgs["/probe/detection"]:
            first[body["cycle"]] = min(first.get(body["cycle"], tt), tt)
        truth_cycles = [dict(c, complete=last[c["cycle"]] <= cut["complete_until_ns"])
                        for c in truth_cycles if first[c["cycle"]] <= cut["complete_until_ns"]]
    sidecar = {
        "writer": "tests/python/contract_writer.py (independent second writer of the contract)",
        "case": case, "machine": MACHINE, "seed": opts.seed, "sigma_um": opts.sigma_um,
        "units": {k: ("um" if k in POSITION_ERRORS else "urad") for k in IDENTIFIED},
        "note": "errors: the apparent (tool-relative) values /cycle/result must report; "
                "true_errors: the axis lines' actual errors; t_ns: the mean timestamp of the "
                "accepted detections; setter_apparent_um: the beam's shift in the table frame "
                "relative to the tool tip (setter offset minus tool-tip shift)",
        "setter_offset_um": list(opts.setter_offset_um),
        "tool_shift_um": list(opts.tool_shift_um),
        "setter_apparent_um": [round(a - b, 6) for a, b in
                               zip(opts.setter_offset_um, opts.tool_shift_um)],
        "latency_ms": opts.latency_ms,
        "labels": opts.labels, "status": opts.status, "retry": opts.retry,
        "retry_status": opts.retry_status if opts.retry else None, "c_alias": opts.c_alias,
        "duplicate": opts.duplicate,
        "compression": opts.compression,
        "cut_short": cut,
        "cycles": truth_cycles,
    }
    with open(path + ".truth.json", "w") as f:
        json.dump(sidecar, f, indent=1)
        f.write("\n")
    return sidecar


def _write_mcap(path: str, msgs: Dict[str, List[Tuple[int, dict]]], opts: Options) -> None:
    """Register the channels in `opts.channel_order` and write the messages: in global time
    order, or (write_by_channel) channel after channel, each in its own time order."""
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE}[opts.compression]
    topics = list(opts.channel_order)
    if opts.vendor_topic and "/vendor/coolant" not in topics:
        topics.insert(1, "/vendor/coolant")
    sch = schemas(opts.schema_draft)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=opts.chunk_size, compression=comp)
        w.start(profile="", library="driftwatch tests/python/contract_writer.py")
        ids = {}
        for topic in topics:
            sid = w.register_schema(name=sch[topic]["title"], encoding="jsonschema",
                                    data=json.dumps(sch[topic]).encode())
            ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        records = []
        for k, topic in enumerate(topics):
            for seq, (tt, body) in enumerate(sorted(msgs[topic], key=lambda m: m[0])):
                records.append((k if opts.write_by_channel else 0, tt, k, seq, topic, body))
        records.sort(key=lambda r: r[:4])
        for _, tt, _, seq, topic, body in records:
            w.add_message(channel_id=ids[topic], log_time=tt, publish_time=tt,
                          sequence=seq + 1, data=json.dumps(body).encode())
        w.finish()


def _cut_short(path: str, t_ns: int) -> dict:
    """Cut `path` half-way into the chunk that holds time `t_ns`, as a power loss would: no
    summary, no footer. Returns where, and the last log time of the complete chunks."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    k = next(i for i, c in enumerate(chunks) if c.message_end_time >= t_ns)
    if k == 0:
        raise ValueError("the cut would leave no complete chunk")
    at = chunks[k].chunk_start_offset + chunks[k].chunk_length // 2
    with open(path, "r+b") as f:
        f.truncate(at)
    return {"at_byte": at, "complete_chunks": k,
            "complete_until_ns": max(c.message_end_time for c in chunks[:k])}


# --------------------------------------------------------------------------------------------
# The conformance cases
# --------------------------------------------------------------------------------------------
def _multi_drift(h: float) -> Dict[str, float]:
    """Slow thermal-like drift over a few hours (um, urad)."""
    g = 1.0 - math.exp(-h / 1.5)
    return {"EX0B": 6.0 * g, "EZ0B": -10.0 * g, "EY0C": 4.0 * g, "EX0C": 3.0 * g,
            "EA0C": 8.0 * g, "EB0C": -5.0 * g}


CASES: Dict[str, dict] = {
    # name: (options, extra solve arguments, what it exercises)
    "plain": dict(opts=dict(), solve_args=[],
                  what="baseline: unique labels, status absent, zstd chunks"),
    "explicit_ok": dict(opts=dict(status="ok"), solve_args=[], diagnose=True,
                        what='every detection carries "status": "ok"; also diagnosed'),
    "repeated_labels": dict(opts=dict(labels="same"), solve_args=[],
                            what="time-symmetric cycle, the same label on both passes"),
    "retry": dict(opts=dict(retry=True), solve_args=[], diagnose=True,
                  what="one approach per cycle fails (no_trip at the end of the move), "
                       "retried under the same label; also diagnosed (the no_trip is no row)"),
    "foreign_labels": dict(opts=dict(labels="foreign"), solve_args=["--plan", "patent"],
                           what="labels P01.. of the writer's own scheme, matched by content "
                                "against --plan patent"),
    "other_layout": dict(opts=dict(compression="none", chunk_size=2048,
                                   channel_order=("/probe/detection", "/spindle",
                                                  "/machine/state", "/machine/info"),
                                   write_by_channel=True, extra_fields=True, vendor_topic=True,
                                   schema_draft=DRAFT_07),
                         solve_args=[],
                         what="detections registered first, info last, written channel by "
                              "channel, uncompressed 2 KB chunks, unknown fields and topic, "
                              "draft-07 schemas"),
    "other_layout_lz4": dict(opts=dict(compression="lz4", chunk_size=4096,
                                       channel_order=("/probe/detection", "/spindle",
                                                      "/machine/state", "/machine/info"),
                                       extra_fields=True, vendor_topic=True),
                             solve_args=[],
                             what="as other_layout, lz4 chunks, globally time-ordered"),
    "setter_tool_offsets": dict(opts=dict(setter_offset_um=(0.0, 25.0, -18.0),
                                          tool_shift_um=(4.0, -3.0, 9.0)),
                                solve_args=[],
                                what="setter off its nominal place and a tool-tip shift "
                                     "(truth = apparent errors)"),
    "latency": dict(opts=dict(latency_ms=3.0), solve_args=[], machine_edit={"latency_ms": 3.0},
                    what="a 3 ms skip latency (5 um at F100) on every approach, z as well, "
                         "solved with a machine file whose latency_ms is 3"),
    "aborted": dict(opts=dict(retry=True, retry_status="aborted"), solve_args=[],
                    what="one approach per cycle aborted (stopped 0.4 mm into the move), "
                         "retried under the same label"),
    "angle_aliases": dict(opts=dict(c_alias=True), solve_args=["--plan", "patent"],
                          what="c_deg written modulo 360 in [0, 360) (C -270 as 90, -180 as "
                               "180, -90 as 270), matched against --plan patent"),
    "minimal": dict(opts=dict(channel_order=("/spindle", "/probe/detection")), solve_args=[],
                    what="no /machine/info and no /machine/state (both optional for readers)"),
    "duplicate_message": dict(opts=dict(duplicate=True), solve_args=[],
                              what="one detection per cycle recorded twice (same time and "
                                   "body, a gateway resend); beyond the contract's text: "
                                   "driftwatch counts it once"),
    "sequential": dict(opts=dict(order="as_listed"), solve_args=[],
                       what="the patent's 12 approaches once, in the listed order "
                            "(plan patent_sequential)"),
    "cut_short": dict(opts=dict(chunk_size=4096, cut_fraction=0.8),
                      solve_args=["--recover"],
                      what="a file cut short inside a chunk (no summary, no footer), read "
                           "with --recover up to its last complete chunk"),
    "multi_cycle": dict(opts=dict(cycles=12, status="ok", cutting=True, cycle_gap_s=900.0,
                                  cut_rpm=(8000.0, 12000.0, 15000.0), drift=_multi_drift),
                        solve_args=[], diagnose=True,
                        what="12 cycles over 3 h with cutting between them, drifting errors, "
                             "spindle log, explicit status ok; also diagnosed"),
}


def case_options(name: str, seed: int, cycles: Optional[int] = None) -> Options:
    o = dict(CASES[name]["opts"])
    o.setdefault("cycles", 3)
    if cycles is not None and name != "multi_cycle":
        o["cycles"] = cycles
    o["seed"] = seed + zlib.crc32(name.encode()) % 1000     # stable per case
    return Options(**o)


def write_case(name: str, path: str, seed: int = 20240305, cycles: Optional[int] = None) -> dict:
    return write_recording(path, case_options(name, seed, cycles), case=name)


MACHINE_TOML = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config",
                            "machines", "table_bc.toml")


def machine_file(outdir: str, case: str, edit: dict) -> str:
    """A copy of config/machines/table_bc.toml with some `key = value` lines changed (for a
    case whose machine differs from the shipped configuration, e.g. a calibrated latency)."""
    lines = open(MACHINE_TOML).read().splitlines()
    for key, value in edit.items():
        hits = [i for i, l in enumerate(lines) if l.split("=")[0].strip() == key]
        if len(hits) != 1:
            raise ValueError(f"{key}: {len(hits)} lines in {MACHINE_TOML}")
        lines[hits[0]] = f"{key} = {value!r}"
    path = os.path.join(outdir, f"{case}.table_bc.toml")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def write_all(outdir: str, seed: int = 20240305, cycles: Optional[int] = None) -> dict:
    """Write every case into outdir, with `cases.json`: per case its file, truth sidecar,
    machine (built-in name or file), extra solve arguments and whether it is diagnosed."""
    os.makedirs(outdir, exist_ok=True)
    manifest = {"seed": seed, "cycles": cycles, "cases": {}}
    for name, case in CASES.items():
        path = os.path.join(outdir, f"{name}.mcap")
        write_case(name, path, seed, cycles)
        machine = MACHINE
        if case.get("machine_edit"):
            machine = os.path.basename(machine_file(outdir, name, case["machine_edit"]))
        manifest["cases"][name] = {
            "recording": f"{name}.mcap", "truth": f"{name}.mcap.truth.json",
            "machine": machine, "solve_args": case["solve_args"],
            "diagnose": bool(case.get("diagnose")), "what": case["what"]}
    with open(os.path.join(outdir, "cases.json"), "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    return manifest


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", nargs="?", help="a case name, or 'all'")
    ap.add_argument("out", nargs="?", help="output file (or directory with 'all')")
    ap.add_argument("--seed", type=int, default=20240305)
    ap.add_argument("--cycles", type=int, default=None,
                    help="cycles per recording (not for multi_cycle, which has 12)")
    ap.add_argument("--list", action="store_true", help="list the cases")
    args = ap.parse_args(argv)
    if args.list or not args.case:
        for k, v in CASES.items():
            print(f"{k:20s} {v['what']}")
        return 0
    if args.case == "all":
        for k in write_all(args.out, args.seed, args.cycles)["cases"]:
            p = os.path.join(args.out, f"{k}.mcap")
            print(p, os.path.getsize(p), "bytes")
        return 0
    if args.case not in CASES:
        print(f"unknown case {args.case}; see --list", file=sys.stderr)
        return 2
    write_case(args.case, args.out, args.seed, args.cycles)
    print(args.out, os.path.getsize(args.out), "bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
