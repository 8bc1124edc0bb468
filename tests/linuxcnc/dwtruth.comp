component dwtruth "The true machine behind the test: a C rotary table on a tilting axis whose lines are where they really are, a laser tool setter fixed on the table, and the true tool tip";

description """
Written from driftwatch's docs/kinematics-conventions.md (frames, lines, chain), not from
driftwatch's simulator. Every servo period it reads the joint positions (x, y, z of the tool
reference point, the tilting axis and C in degrees), and

- sets *trip* while the laser beam (a segment of a line fixed to the table, *beam-half-length*
  either side of its point, as between a setter's emitter and receiver) meets the tool (a
  cylinder of radius *tool-radius* along +Z from the tip up to *tool-length*), so that motion
  latches the position in the same period as a real skip input would;
- gives the true tool tip in the table frame (*tip-x*, *tip-y*, *tip-z*), which the test compares
  with the point it commanded in TCP mode.

The chain is p_machine = T_T(t) * T_C(c) * p_table with T(a) = Tr(q) * Rot(u, sense * a) *
Tr(-q): the tilting axis' line through (tq-x, tq-y, tq-z) along (tu-x, tu-y, tu-z), the C line as
seen at t = 0 through (cq-x, cq-y, cq-z) along (cu-x, cu-y, cu-z), mm. The harness computes the
lines from named location errors; the directions are normalised here. sense +1 (direct: a
positive command turns the table positively, as LinuxCNC's trt kinematics assume) or -1 (the
ISO 841 table sense). All geometry pins may be set at any time (halcmd setp).
""";

pin in float x;
pin in float y;
pin in float z;
pin in float tilt "tilting axis position, deg (B or A)";
pin in float c "C position, deg";

pin in float beam_px = 0.0;
pin in float beam_py = -100.0;
pin in float beam_pz = 70.0;
pin in float beam_dx = 1.0;
pin in float beam_dy = 0.0;
pin in float beam_dz = 0.0;
pin in float beam_half_length = 40.0 "the beam runs this far either side of its point (emitter to receiver), mm";
pin in float tool_radius = 5.0;
pin in float tool_length = 60.0;

pin in float tq_x = 0.0;
pin in float tq_y = 0.0;
pin in float tq_z = 0.0;
pin in float tu_x = 0.0;
pin in float tu_y = 1.0;
pin in float tu_z = 0.0;
pin in float cq_x = 0.0;
pin in float cq_y = 0.0;
pin in float cq_z = 0.0;
pin in float cu_x = 0.0;
pin in float cu_y = 0.0;
pin in float cu_z = 1.0;
pin in float sense = 1.0;
pin in bit enable = 1;

pin out bit trip;
pin out s32 trips;
pin out float tip_x;
pin out float tip_y;
pin out float tip_z;

function _;
license "MIT";
author "driftwatch";
;;

#include "rtapi_math.h"

typedef struct { double v[3]; } vec;

/* Helpers take no argument named after a pin: halcompile makes every pin name a macro. */
static vec mk(double v0, double v1, double v2) { vec r = {{v0, v1, v2}}; return r; }
static vec sub(vec a, vec b) { return mk(a.v[0] - b.v[0], a.v[1] - b.v[1], a.v[2] - b.v[2]); }
static vec add(vec a, vec b) { return mk(a.v[0] + b.v[0], a.v[1] + b.v[1], a.v[2] + b.v[2]); }
static vec scale(vec a, double s) { return mk(a.v[0] * s, a.v[1] * s, a.v[2] * s); }
static double dot(vec a, vec b) { return a.v[0] * b.v[0] + a.v[1] * b.v[1] + a.v[2] * b.v[2]; }
static vec cross(vec a, vec b) {
    return mk(a.v[1] * b.v[2] - a.v[2] * b.v[1], a.v[2] * b.v[0] - a.v[0] * b.v[2],
              a.v[0] * b.v[1] - a.v[1] * b.v[0]);
}
static vec unit(vec a) { double n = sqrt(dot(a, a)); return n > 0 ? scale(a, 1.0 / n) : a; }

/* Rodrigues: p turned by angle t (rad) about the unit vector u, right-handed. */
static vec rot(vec u, double t, vec p) {
    double ct = cos(t), st = sin(t);
    return add(add(scale(p, ct), scale(cross(u, p), st)), scale(u, dot(u, p) * (1.0 - ct)));
}

/* A point (is_dir 0) or a direction (1) turned about the line through q along u. */
static vec about(vec q, vec u, double t, vec p, int is_dir) {
    if (is_dir) return rot(u, t, p);
    return add(q, rot(u, t, sub(p, q)));
}

FUNCTION(_) {
    vec tq = mk(tq_x, tq_y, tq_z), tu = unit(mk(tu_x, tu_y, tu_z));
    vec cq = mk(cq_x, cq_y, cq_z), cu = unit(mk(cu_x, cu_y, cu_z));
    double s = sense >= 0 ? 1.0 : -1.0;
    double t_rad = s * tilt * M_PI / 180.0, c_rad = s * c * M_PI / 180.0;

    /* The true tip: the joint position (perfect linear axes, tool length 0) carried back to
       the table frame through the inverse chain. */
    vec a = mk(x, y, z);
    vec back = about(cq, cu, -c_rad, about(tq, tu, -t_rad, a, 0), 0);
    tip_x = back.v[0];
    tip_y = back.v[1];
    tip_z = back.v[2];

    /* The beam in the machine frame. */
    vec p = about(tq, tu, t_rad, about(cq, cu, c_rad, mk(beam_px, beam_py, beam_pz), 0), 0);
    vec e = about(tq, tu, t_rad, about(cq, cu, c_rad, unit(mk(beam_dx, beam_dy, beam_dz)), 1), 1);

    /* The beam line p + s e meets the solid cylinder (axis +Z through the tip, from z to
       z + tool_length) when, over the stretch of s where the line is within that height,
       its horizontal distance to the axis comes within the radius. The squared distance is
       convex in s, so its minimum over the stretch is at the free minimum clamped. */
    int hit = 0;
    double lo = -beam_half_length, hi = beam_half_length;
    int in_height = 1;
    if (fabs(e.v[2]) > 1e-12) {
        double s1 = (z - p.v[2]) / e.v[2], s2 = (z + tool_length - p.v[2]) / e.v[2];
        if (s1 > s2) { double t = s1; s1 = s2; s2 = t; }
        if (s1 > lo) lo = s1;
        if (s2 < hi) hi = s2;
        in_height = lo <= hi;
    } else if (!(z <= p.v[2] && p.v[2] <= z + tool_length)) {
        in_height = 0;
    }
    if (in_height) {
        double exy2 = e.v[0] * e.v[0] + e.v[1] * e.v[1], sm;
        if (exy2 < 1e-18) {
            sm = (lo <= 0.0 && 0.0 <= hi) ? 0.0 : (lo > 0.0 ? lo : hi);
        } else {
            sm = ((x - p.v[0]) * e.v[0] + (y - p.v[1]) * e.v[1]) / exy2;
            if (sm < lo) sm = lo;
            if (sm > hi) sm = hi;
        }
        double qx = p.v[0] + sm * e.v[0] - x, qy = p.v[1] + sm * e.v[1] - y;
        hit = qx * qx + qy * qy <= tool_radius * tool_radius;
    }
    hit = hit && enable;
    if (hit && !trip) trips++;
    trip = hit;
}
