//! Whether a plan's moves keep the tool out of the setter's beam: the tool as a solid cylinder
//! (the effective radius about the tool axis, from its end face up along the axis), the beam
//! as a segment of its line on either side of the probed point (a real beam runs between an
//! emitter and a receiver), the move a straight line of the tip at fixed angles.
//!
//! A probing move ends where the tool meets the beam (that is the measurement), past the trip
//! by the skip latency's travel, and its back-off retraces it from there: neither is checked.
//! Every other move counts as a contact where the beam would be inside the tool, more than
//! [`TOUCH_MM`] past its surface (`plan::beam_contacts` walks a plan's moves).

use crate::geometry::Vec3;
use crate::kinematics::Kinematics;

/// Half-length of the beam segment checked, mm: the beam on either side of the probed point.
pub const BEAM_HALF_LENGTH_MM: f64 = 40.0;

/// Length of the tool cylinder checked, mm, from the end face up along the tool axis (stick-out
/// of a setter tool; the holder and spindle nose above it are wider, and stay above the safe Z).
pub const TOOL_LENGTH_MM: f64 = 100.0;

/// How far inside the tool's surface the beam must be to count as a contact, mm: 0.1 um, above
/// the touch at a probing move's end (the nominal trip, within the end-face model's rounding of
/// under 10 nm) and far below anything a machine would feel.
pub const TOUCH_MM: f64 = 1e-4;

/// The tool at a pose: the tip position of commanded position `c` is `c + offset`; axis `w`
/// (unit, from the tip into the spindle), radius `r`, length `length` (mm).
#[derive(Debug, Clone, Copy)]
pub struct ToolCylinder {
    pub offset: Vec3,
    pub axis: Vec3,
    pub radius: f64,
    pub length: f64,
}

/// A segment of the beam line: `point + t dir`, `|t| <= half_length` (dir unit).
#[derive(Debug, Clone, Copy)]
pub struct BeamSegment {
    pub point: Vec3,
    pub dir: Vec3,
    pub half_length: f64,
}

/// The smallest distance from the tool axis, square to it, of any beam point level with the
/// tool (between its end face and its top, the end face counted from [`TOUCH_MM`] above the
/// tip) over a straight move of the tip from `from` to `to`; `None` when no beam point is ever
/// level with the tool. The beam is inside the tool where this is below the radius.
///
/// Exact: with the tip at `from + u d` (`d` unit, `0 <= u <= |to - from|`) and the beam point
/// at `p + t e`, the height along the tool axis is linear in `(t, u)` and the squared distance
/// from the axis a convex quadratic; its minimum over the polygon where `(t, u)` lie within
/// their ranges and the height within the tool is at the quadratic's own minimum, if that lies
/// in the polygon, or on one of its edges.
pub fn closest_approach(
    tool: &ToolCylinder,
    beam: &BeamSegment,
    from_tip: &Vec3,
    to_tip: &Vec3,
) -> Option<f64> {
    let w = tool.axis;
    let travel = to_tip - from_tip;
    let len = travel.norm();
    let d = if len > 0.0 { travel / len } else { w };
    let q0 = beam.point - from_tip;
    let perp = |v: Vec3| v - w * v.dot(&w);
    let (a, ae, bd) = (perp(q0), perp(beam.dir), perp(d));
    // Height along the axis: s0 + t se - u sd.
    let (s0, se, sd) = (q0.dot(&w), beam.dir.dot(&w), d.dot(&w));
    let height = |t: f64, u: f64| s0 + t * se - u * sd;
    let h = beam.half_length;
    let mut poly = vec![(-h, 0.0), (h, 0.0), (h, len), (-h, len)];
    // Keep height >= TOUCH_MM and height <= length.
    poly = clip(&poly, |t, u| height(t, u) - TOUCH_MM);
    poly = clip(&poly, |t, u| tool.length - height(t, u));
    if poly.is_empty() {
        return None;
    }
    let f = |t: f64, u: f64| (a + ae * t - bd * u).norm_squared();
    let mut best = f64::INFINITY;
    for i in 0..poly.len() {
        let (t0, u0) = poly[i];
        let (t1, u1) = poly[(i + 1) % poly.len()];
        let v0 = a + ae * t0 - bd * u0;
        let dv = ae * (t1 - t0) - bd * (u1 - u0);
        let dd = dv.norm_squared();
        let lambda = if dd > 0.0 {
            (-v0.dot(&dv) / dd).clamp(0.0, 1.0)
        } else {
            0.0
        };
        best = best.min((v0 + dv * lambda).norm_squared());
    }
    // The quadratic's own minimum, where it is unique and inside the polygon.
    let (aa, ab, bb) = (ae.dot(&ae), ae.dot(&bd), bd.dot(&bd));
    let det = ab * ab - aa * bb;
    if det.abs() > 1e-12 * (aa * bb).max(1e-300) {
        // t aa - u ab = -a.ae, t ab - u bb = -a.bd (the gradient's zero).
        let (r1, r2) = (-a.dot(&ae), -a.dot(&bd));
        let t = (ab * r2 - bb * r1) / det;
        let u = (aa * r2 - ab * r1) / det;
        let inside = t.abs() <= h
            && (0.0..=len).contains(&u)
            && height(t, u) >= TOUCH_MM
            && height(t, u) <= tool.length;
        if inside {
            best = best.min(f(t, u));
        }
    }
    Some(best.sqrt())
}

/// Margin of a crossing, mm: the tool grown by this much all round (radius and end face) passes
/// clear of the beam. It is the least clearance of the level-beam crossings of the shipped plans
/// (a horizontal tool over a level beam at the start of an end-face approach + 5: its side 1 mm
/// above the beam; a vertical tool crosses a level beam 2 mm above it on the lateral
/// approaches' `start + 5`, 6 mm on the end face's), so those stay as they were.
pub const CROSSING_MARGIN_MM: f64 = 1.0;

/// The tool grown by `m` all round: radius `r + m`, end face `m` further out.
fn grown(tool: &ToolCylinder, m: f64) -> ToolCylinder {
    ToolCylinder {
        offset: tool.offset - tool.axis * m,
        axis: tool.axis,
        radius: tool.radius + m,
        length: tool.length + m,
    }
}

/// Whether the tool clears the beam over a straight move of its commanded position.
fn clear(tool: &ToolCylinder, beam: &BeamSegment, from: &Vec3, to: &Vec3) -> bool {
    closest_approach(tool, beam, &(from + tool.offset), &(to + tool.offset))
        .is_none_or(|g| g >= tool.radius - TOUCH_MM)
}

/// The lowest commanded Z, at least `z_min`, at which a horizontal move of the commanded
/// position from `from` to `to` (their X and Y) keeps the tool grown by [`CROSSING_MARGIN_MM`]
/// clear of the beam.
///
/// A vertical tool (axis +Z) at tip height `z` contains exactly the points above `z` within its
/// radius of its axis, so over the move it meets the beam exactly where a beam point within the
/// radius of the axis' XY segment lies above the tip. The beam's height is linear along it and
/// its XY distance from the segment convex, so the beam points within `R = r + margin` of the
/// segment form one stretch of it and the highest is at one of its ends: the answer is that
/// height plus the margin (bisection to 1e-9 mm for the ends). Any other tool axis: the lowest
/// height from `z_min` up, in 1 mm steps then by bisection to 1 um, at which the grown tool is
/// clear.
pub fn crossing_height(
    tool: &ToolCylinder,
    beam: &BeamSegment,
    from: &Vec3,
    to: &Vec3,
    z_min: f64,
) -> f64 {
    let m = CROSSING_MARGIN_MM;
    let g = grown(tool, m);
    let at = |z: f64| (Vec3::new(from.x, from.y, z), Vec3::new(to.x, to.y, z));
    let (a, b) = at(z_min);
    if clear(&g, beam, &a, &b) {
        return z_min;
    }
    let w = tool.axis;
    if w.z > 1.0 - 1e-12 {
        let (a, b) = (a + tool.offset, b + tool.offset);
        let reach = tool.radius + m;
        let point = |t: f64| beam.point + beam.dir * t;
        let dist = |t: f64| {
            let q = point(t);
            let (ab, aq) = ((b - a).xy(), (q - a).xy());
            let l = ab.norm_squared();
            let f = if l > 0.0 {
                (aq.dot(&ab) / l).clamp(0.0, 1.0)
            } else {
                0.0
            };
            (aq - ab * f).norm()
        };
        // The nearest beam point (the distance is convex along the beam): golden section.
        let h = beam.half_length;
        let (mut lo, mut hi) = (-h, h);
        let phi = (5f64.sqrt() - 1.0) / 2.0;
        while hi - lo > 1e-9 {
            let (t1, t2) = (hi - phi * (hi - lo), lo + phi * (hi - lo));
            if dist(t1) < dist(t2) {
                hi = t2;
            } else {
                lo = t1;
            }
        }
        let near = 0.5 * (lo + hi);
        // The end of the stretch within `reach` on the side where the beam rises.
        let up = if beam.dir.z >= 0.0 { h } else { -h };
        let end = if dist(up) <= reach {
            up
        } else {
            let (mut inside, mut outside) = (near, up);
            while (outside - inside).abs() > 1e-9 {
                let mid = 0.5 * (inside + outside);
                if dist(mid) <= reach {
                    inside = mid;
                } else {
                    outside = mid;
                }
            }
            inside
        };
        let top = point(end).z.max(point(near).z);
        return z_min.max(top + m - tool.offset.z);
    }
    // Any other tool axis: step up until clear, then back down by bisection.
    let (mut low, mut high) = (z_min, z_min + 1.0);
    while !{
        let (a, b) = at(high);
        clear(&g, beam, &a, &b)
    } {
        low = high;
        high += 1.0;
        if high > z_min + 1000.0 {
            return high;
        }
    }
    while high - low > 1e-3 {
        let mid = 0.5 * (low + high);
        let (a, b) = at(mid);
        if clear(&g, beam, &a, &b) {
            high = mid;
        } else {
            low = mid;
        }
    }
    high
}

/// The part of a convex polygon where `g >= 0` (`g` affine), Sutherland-Hodgman.
fn clip(poly: &[(f64, f64)], g: impl Fn(f64, f64) -> f64) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for i in 0..poly.len() {
        let p = poly[i];
        let q = poly[(i + 1) % poly.len()];
        let (gp, gq) = (g(p.0, p.1), g(q.0, q.1));
        if gp >= 0.0 {
            out.push(p);
        }
        if (gp >= 0.0) != (gq >= 0.0) {
            let l = gp / (gp - gq);
            out.push((p.0 + l * (q.0 - p.0), p.1 + l * (q.1 - p.1)));
        }
    }
    out
}

/// The tool and the beam segment at a pose in the machine's nominal state (the state plans are
/// laid out in).
pub fn pose_cylinder_and_beam(k: &Kinematics, angles_deg: &[f64]) -> (ToolCylinder, BeamSegment) {
    let s = k.nominal_state();
    let g = k.pose_geometry(&s, angles_deg);
    (
        ToolCylinder {
            offset: g.tool.actual - g.tool.nominal,
            axis: g.tool.axis,
            radius: s.radius,
            length: TOOL_LENGTH_MM,
        },
        BeamSegment {
            point: g.beam_point,
            dir: g.beam_dir,
            half_length: BEAM_HALF_LENGTH_MM,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vertical_tool() -> ToolCylinder {
        ToolCylinder {
            offset: Vec3::zeros(),
            axis: Vec3::z(),
            radius: 5.0,
            length: TOOL_LENGTH_MM,
        }
    }

    fn beam(slope_deg: f64) -> BeamSegment {
        let a = slope_deg.to_radians();
        BeamSegment {
            point: Vec3::new(0.0, 0.0, 70.0),
            dir: Vec3::new(a.cos(), 0.0, a.sin()),
            half_length: BEAM_HALF_LENGTH_MM,
        }
    }

    /// A vertical tool crossing a beam along X in Y: on a level beam the end clears it at any
    /// height above it; on a 45-degree beam only above its height at x = r.
    #[test]
    fn a_crossing_clears_the_beam_only_above_its_highest_point_within_the_radius() {
        let tool = vertical_tool();
        let cross = |b: &BeamSegment, z: f64| {
            closest_approach(
                &tool,
                b,
                &Vec3::new(0.0, -20.0, z),
                &Vec3::new(0.0, 20.0, z),
            )
        };
        let clear = |g: Option<f64>| g.is_none_or(|g| g >= tool.radius);
        let level = beam(0.0);
        assert_eq!(cross(&level, 70.001), None);
        assert!(cross(&level, 69.999).unwrap() < 1e-9);
        let steep = beam(45.0);
        // Highest point within 5 mm of the axis: z = 75 at x = 5.
        assert!(clear(cross(&steep, 75.001)));
        assert!(!clear(cross(&steep, 74.999)));
        let g = cross(&steep, 74.0).unwrap();
        assert!((g - 4.0).abs() < 1e-3, "{g}");
        assert!(cross(&steep, 72.0).unwrap() < tool.radius);
        // Standing beside the beam, level with it: clear by the gap.
        let beside = closest_approach(
            &tool,
            &level,
            &Vec3::new(0.0, -6.0, 67.0),
            &Vec3::new(0.0, -6.0, 67.0),
        )
        .unwrap();
        assert!((beside - 6.0).abs() < 1e-9, "{beside}");
    }

    /// The crossing height over a beam along X (the tool moving in Y over it): a level beam
    /// needs nothing above `z_min` once the grown end clears it; a 45-degree one its height at
    /// `x = r + margin` plus the margin; a horizontal tool is lifted until its grown side clears.
    #[test]
    fn crossing_heights_over_level_and_sloping_beams() {
        let tool = vertical_tool();
        let (from, to) = (Vec3::new(0.0, -6.0, 0.0), Vec3::new(0.0, 6.0, 0.0));
        let m = CROSSING_MARGIN_MM;
        assert_eq!(crossing_height(&tool, &beam(0.0), &from, &to, 72.0), 72.0);
        let z = crossing_height(&tool, &beam(0.0), &from, &to, 65.0);
        assert!((z - (70.0 + m)).abs() < 1e-9, "{z}");
        let z = crossing_height(&tool, &beam(45.0), &from, &to, 72.0);
        assert!((z - (70.0 + tool.radius + m + m)).abs() < 1e-6, "{z}");
        let g = grown(&tool, m);
        let at = |z: f64| (Vec3::new(0.0, -6.0, z), Vec3::new(0.0, 6.0, z));
        let (a, b) = at(z);
        assert!(clear(&tool, &beam(45.0), &a, &b));
        let (a, b) = at(z - 0.01);
        assert!(!clear(&g, &beam(45.0), &a, &b));
        // A horizontal tool (axis +X, pointing -X) whose side spans a level beam along Y: lifted
        // until its grown side clears the beam.
        let side = ToolCylinder {
            axis: Vec3::x(),
            ..tool
        };
        let across = BeamSegment {
            dir: Vec3::y(),
            ..beam(0.0)
        };
        let (from, to) = (Vec3::new(-20.0, 0.0, 0.0), Vec3::new(-3.0, 0.0, 0.0));
        let z = crossing_height(&side, &across, &from, &to, 72.0);
        assert!((z - (70.0 + tool.radius + m)).abs() < 2e-3, "{z}");
    }
}
