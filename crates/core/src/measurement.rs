//! The laser tool-setter measurement in exact geometry: a turning tool (a cylinder of the
//! effective radius along the spindle axis, flat end) moved into the beam line, and the
//! commanded position the NC latches at the skip signal.
//!
//! - Lateral approach (a linear axis across the tool axis): the trip is where the distance
//!   between the tool axis and the beam line, measured across the tool axis, equals the radius,
//!   coming from outside, with the tool end past the beam.
//! - End-face approach (the linear axis along the tool axis, moving the tip out of the
//!   spindle: -z for a vertical spindle): the trip is where the end face reaches the nearest
//!   point of the beam line within one radius of the tool axis (a beam sloping by s along its
//!   length meets the end face r |s| earlier than at the axis; the corner of |s| at 0 is
//!   rounded over 1 urad, a change under 1 urad times the half chord: 5 nm on a beam level to
//!   the end face with a 5 mm radius, 9.6 nm on the shipped plans' steepest beam).
//! - Skip latency: the latched position lies `feed * latency` further along the motion.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::geometry::Vec3;
use crate::kinematics::{Kinematics, MachineState, PoseGeometry};

#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Axis::X => "x",
            Axis::Y => "y",
            Axis::Z => "z",
        }
    }
}

/// One approach as commanded: the axis that moves, its direction and feed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Approach {
    pub axis: Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
}

impl Approach {
    /// Latency shift of the latched position, mm (signed along the machine axis).
    pub fn latency_shift(&self, latency_s: f64) -> f64 {
        f64::from(self.direction) * self.feed_mm_min / 60.0 * latency_s
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum NoTrip {
    #[error("the tool moves parallel to the beam and never reaches it")]
    Parallel,
    #[error("the tool axis passes {distance_mm:.3} mm from the beam, more than the radius")]
    Misses { distance_mm: f64 },
    #[error("the tool end is {above_mm:.3} mm above the beam at the trip point")]
    AboveBeam { above_mm: f64 },
    #[error("the tool starts inside the beam or moves away from it")]
    WrongSide,
    #[error(
        "the trip lies {needed_mm:.3} mm from the start, beyond the allowed travel {max_mm:.3} mm"
    )]
    BeyondTravel { needed_mm: f64, max_mm: f64 },
    #[error(
        "an approach along the tool axis must move the tip out of the spindle (-z for a vertical spindle)"
    )]
    IntoSpindle,
    #[error(
        "the motion is {angle_deg:.1} deg from the tool axis: neither along it nor across it \
         (within 15 deg), so neither the end face nor the side is known to meet the beam first"
    )]
    Oblique { angle_deg: f64 },
}

/// Slope (rad) below which the corner of `|slope|` is rounded.
const SLOPE_ROUNDING: f64 = 1e-6;

/// `|x|` with the corner at 0 rounded over `SLOPE_ROUNDING`: it lies below `|x|` by less than
/// `SLOPE_ROUNDING`, so the end-face trip moves by less than that times the half chord along
/// the beam, `r / cos theta` (theta the beam's angle to the end face): under 5 nm on a beam
/// level to the end face with a 5 mm radius, 7.1 nm at 45 deg, 9.6 nm on the shipped plans'
/// steepest beam (58.6 deg on table_d45_c at D = -90; a fiftieth of the trip noise). It lets
/// Gauss-Newton converge where a beam slope crosses zero.
fn rounded_abs(x: f64) -> f64 {
    (x * x + SLOPE_ROUNDING * SLOPE_ROUNDING).sqrt() - SLOPE_ROUNDING
}

/// Where the approach starts and how far it may go (the simulator checks these; the estimator
/// does not know them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Travel {
    pub start: f64,
    pub max_mm: f64,
}

/// The latched commanded coordinate of the moving axis at the trip.
///
/// `commanded` holds the commanded position; its moving coordinate is ignored (the start is in
/// `travel`, when known).
pub fn latched(
    k: &Kinematics,
    s: &MachineState,
    angles_deg: &[f64],
    approach: &Approach,
    commanded: &Vec3,
    travel: Option<Travel>,
) -> Result<f64, NoTrip> {
    latched_at(
        s,
        &k.pose_geometry(s, angles_deg),
        approach,
        commanded,
        travel,
    )
}

/// Largest angle (deg) between the motion and the tool axis (end face) or its normal plane
/// (lateral) for which a trip model holds: beyond it the end's rim and the side could meet
/// the beam first, and neither model says which.
pub const MAX_OBLIQUE_DEG: f64 = 15.0;

/// Whether an approach along `axis` is an end-face approach (along the tool axis `w`, within
/// [`MAX_OBLIQUE_DEG`]) or a lateral one (across it, within as much); `None` in between.
pub fn along_tool(axis: Axis, w: &Vec3) -> Option<bool> {
    let c = w[axis.index()].abs();
    let limit = MAX_OBLIQUE_DEG.to_radians();
    if c >= limit.cos() {
        Some(true)
    } else if c <= limit.sin() {
        Some(false)
    } else {
        None
    }
}

/// As [`latched`], with the beam line and the tool already computed for the pose.
pub fn latched_at(
    s: &MachineState,
    pose: &PoseGeometry,
    approach: &Approach,
    commanded: &Vec3,
    travel: Option<Travel>,
) -> Result<f64, NoTrip> {
    let v = if s.linear.has_components() {
        // The ISO 230-1 component errors move the tip by `e(p)`, slowly along the travel:
        // taken at the trip point found with them at the previous guess, three times, the
        // trip is off by their slope cubed times the distance (far below a nanometre).
        let i = approach.axis.index();
        let mut p = commanded - pose.tool.nominal;
        p[i] = travel.map(|t| t.start).unwrap_or(commanded[i]) - pose.tool.nominal[i];
        let mut v = 0.0;
        for _ in 0..3 {
            let e = s.linear.component_error(&p, &pose.tool.actual);
            v = trip(s, pose, approach, commanded, travel, &e)?;
            p[i] = v - pose.tool.nominal[i];
        }
        v
    } else {
        trip(s, pose, approach, commanded, travel, &Vec3::zeros())?
    };
    Ok(v + approach.latency_shift(s.latency_s))
}

/// The commanded coordinate of the moving axis where the tool, displaced further by `extra`
/// (mm), meets the beam (no latency).
fn trip(
    s: &MachineState,
    pose: &PoseGeometry,
    approach: &Approach,
    commanded: &Vec3,
    travel: Option<Travel>,
    extra: &Vec3,
) -> Result<f64, NoTrip> {
    let (beam_p, beam_e) = (&pose.beam_point, &pose.beam_dir);
    let w = pose.tool.axis;
    let a_mat = s.linear.matrix();
    let i = approach.axis.index();
    let col = a_mat.column(i).into_owned();
    let mut c0 = *commanded;
    c0[i] = 0.0;
    // Actual tool-tip position as an affine function of the moving coordinate v: the linear
    // axes stand at the commanded position less the NC's head offset.
    let a0 = a_mat * (c0 - pose.tool.nominal) + pose.tool.actual + extra;
    let e_perp = beam_e - w * beam_e.dot(&w);
    let e_perp_norm = e_perp.norm();
    if e_perp_norm < 1e-12 {
        return Err(NoTrip::Parallel);
    }
    let e_hat = e_perp / e_perp_norm;
    let n = w.cross(&e_hat);
    let r = s.radius;
    let Some(end_face) = along_tool(approach.axis, &w) else {
        return Err(NoTrip::Oblique {
            angle_deg: w[i].abs().clamp(0.0, 1.0).acos().to_degrees(),
        });
    };
    let v = match end_face {
        true => {
            if f64::from(approach.direction) * w[i] > 0.0 {
                return Err(NoTrip::IntoSpindle);
            }
            let dh = col.dot(&w);
            let mut v = travel.map(|t| t.start).unwrap_or(commanded[i]);
            for _ in 0..4 {
                let a = a0 + col * v;
                let d = a - beam_p;
                let delta = n.dot(&d);
                if delta.abs() >= r {
                    return Err(NoTrip::Misses {
                        distance_mm: delta.abs(),
                    });
                }
                let t0 = d.dot(&e_perp) / (e_perp_norm * e_perp_norm);
                let half = (r * r - delta * delta).sqrt() / e_perp_norm;
                let ew = beam_e.dot(&w);
                let top = beam_p.dot(&w) + t0 * ew + rounded_abs(ew) * half;
                v = (top - a0.dot(&w)) / dh;
            }
            v
        }
        false => {
            let g = n.dot(&col);
            if g.abs() < 1e-12 {
                return Err(NoTrip::Parallel);
            }
            let f0 = n.dot(&(a0 - beam_p));
            let side = -(f64::from(approach.direction) * g).signum();
            let v = (side * r - f0) / g;
            let a = a0 + col * v;
            let d = a - beam_p;
            let t = d.dot(&e_perp) / (e_perp_norm * e_perp_norm);
            let beam_height = (beam_p + beam_e * t).dot(&w);
            let tip_height = a.dot(&w);
            if tip_height >= beam_height {
                return Err(NoTrip::AboveBeam {
                    above_mm: tip_height - beam_height,
                });
            }
            v
        }
    };
    if let Some(t) = travel {
        let ahead = f64::from(approach.direction) * (v - t.start);
        if ahead < 0.0 {
            return Err(NoTrip::WrongSide);
        }
        if ahead > t.max_mm {
            return Err(NoTrip::BeyondTravel {
                needed_mm: ahead,
                max_mm: t.max_mm,
            });
        }
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup() -> (Kinematics, MachineState) {
        let k = Kinematics::builtin("table_bc").unwrap();
        let s = k.nominal_state();
        (k, s)
    }

    fn ap(axis: Axis, direction: i8) -> Approach {
        Approach {
            axis,
            direction,
            feed_mm_min: 200.0,
        }
    }

    #[test]
    fn nominal_readings_of_the_patent_poses() {
        let (k, s) = setup();
        let (r, rr, h) = (5.0, 100.0, 70.0);
        // C = 0: beam at y = -R; tool from -Y moving +Y.
        let y1 = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Y, 1),
            &Vec3::new(0.0, 0.0, 65.0),
            None,
        );
        assert!((y1.unwrap() - (-rr - r)).abs() < 1e-12);
        let z1 = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Z, -1),
            &Vec3::new(0.0, -rr, 0.0),
            None,
        );
        assert!((z1.unwrap() - h).abs() < 1e-12);
        // C = -90: beam at x = +R; tool from +X moving -X.
        let x2 = latched(
            &k,
            &s,
            &[0.0, -90.0],
            &ap(Axis::X, -1),
            &Vec3::new(0.0, 0.0, 65.0),
            None,
        );
        assert!((x2.unwrap() - (rr + r)).abs() < 1e-12);
        // B = -90 (C = -270): table top faces +X, beam at x = H, z = R; tool from +X.
        let x5 = latched(
            &k,
            &s,
            &[-90.0, -270.0],
            &ap(Axis::X, -1),
            &Vec3::new(0.0, 0.0, 95.0),
            None,
        );
        assert!((x5.unwrap() - (h + r)).abs() < 1e-12);
        let z5 = latched(
            &k,
            &s,
            &[-90.0, -270.0],
            &ap(Axis::Z, -1),
            &Vec3::new(h, 0.0, 0.0),
            None,
        );
        assert!((z5.unwrap() - rr).abs() < 1e-12);
    }

    /// The y and z readings at B = 0, C = 0 (the setter on the -Y side).
    fn y1_z1(k: &Kinematics, s: &MachineState) -> (f64, f64) {
        let c = [0.0, 0.0];
        let y = latched(k, s, &c, &ap(Axis::Y, 1), &Vec3::new(0.0, 0.0, 65.0), None).unwrap();
        let z = latched(
            k,
            s,
            &c,
            &ap(Axis::Z, -1),
            &Vec3::new(0.0, -100.0, 0.0),
            None,
        )
        .unwrap();
        (y, z)
    }

    #[test]
    fn latency_moves_the_reading_along_the_motion() {
        let (k, mut s) = setup();
        s.latency_s = 0.003;
        let (y, z) = y1_z1(&k, &s);
        assert!((y - (-105.0 + 200.0 / 60.0 * 0.003)).abs() < 1e-12);
        assert!((z - (70.0 - 0.01)).abs() < 1e-12);
    }

    #[test]
    fn tool_tip_drift_shifts_readings_by_minus_s() {
        let (k, mut s) = setup();
        s.tool_tip = Vec3::new(0.004, -0.002, -0.030);
        let (y, z) = y1_z1(&k, &s);
        assert!((y - (-105.0 + 0.002)).abs() < 1e-12);
        assert!((z - 70.030).abs() < 1e-12);
    }

    #[test]
    fn flat_end_meets_a_sloping_beam_at_its_high_end() {
        let (k, mut s) = setup();
        // Tilt the beam in the table frame by 300 urad about Y: slope along X.
        s.beam_dir = Vec3::new(1.0, 0.0, 300e-6).normalize();
        let z = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Z, -1),
            &Vec3::new(0.0, -100.0, 0.0),
            None,
        )
        .unwrap();
        // Within the 5 nm of the rounded corner.
        assert!((z - (70.0 + 300e-6 * 5.0)).abs() < 6e-6, "{z}");
    }

    /// The end-face trip in exact geometry, found independently of [`trip`]: the commanded
    /// coordinate of the moving axis where the highest point (along the tool axis) of the beam
    /// within `r` of the tool axis reaches the flat end, by bisection within 10 um of `near`.
    /// Perfect linear axes, no latency.
    fn exact_end_face(
        pose: &PoseGeometry,
        r: f64,
        approach: &Approach,
        commanded: &Vec3,
        near: f64,
    ) -> f64 {
        let (p, e, w) = (pose.beam_point, pose.beam_dir, pose.tool.axis);
        let i = approach.axis.index();
        // How far the beam's highest point within r lies past the end face: < 0 before the
        // trip, > 0 after it.
        let past = |v: f64| {
            let mut c = *commanded;
            c[i] = v;
            let d = p - (c - pose.tool.nominal + pose.tool.actual);
            let (a0, a1) = (d - w * d.dot(&w), e - w * e.dot(&w));
            let (qa, qb, qc) = (a1.dot(&a1), 2.0 * a0.dot(&a1), a0.dot(&a0) - r * r);
            let root = (qb * qb - 4.0 * qa * qc).sqrt();
            assert!(
                root.is_finite(),
                "the beam passes farther than r from the tool axis"
            );
            let (t1, t2) = ((-qb - root) / (2.0 * qa), (-qb + root) / (2.0 * qa));
            d.dot(&w) + (t1 * e.dot(&w)).max(t2 * e.dot(&w))
        };
        let dir = f64::from(approach.direction);
        let (mut before, mut after) = (near - dir * 0.01, near + dir * 0.01);
        assert!(past(before) < 0.0 && past(after) > 0.0);
        for _ in 0..200 {
            let mid = 0.5 * (before + after);
            if past(mid) < 0.0 {
                before = mid;
            } else {
                after = mid;
            }
        }
        0.5 * (before + after)
    }

    /// The rounded corner of `|e.w|` moves an end-face reading further along the motion than
    /// the exact trip by `(|e.w| - |e.w|_eps) sqrt(r^2 - delta^2) / (|e_perp| |m.w|)`
    /// (the contract, kinematics-conventions "Tool and laser tool setter"): never less than 0,
    /// under `eps r / (cos theta cos phi)` (theta the beam's angle to the end face, phi the
    /// motion's to the tool axis). Checked against an independent exact trip on every shipped
    /// plan's end-face steps, nominal and with errors that slope the beams, and the largest
    /// change on the shipped plans is the figure the documents give.
    #[test]
    fn the_rounded_slope_corner_moves_end_face_readings_by_the_stated_amount() {
        use crate::kinematics::BUILTIN_MACHINES;
        use crate::plan::{BUILTIN_PLANS, Plan, PlanConfig};
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let eps = SLOPE_ROUNDING;
        // (largest change, its beam angle to the end face, where), mm and deg.
        let mut worst = (0.0f64, 0.0f64, String::new());
        for (plan_name, _) in BUILTIN_PLANS {
            // This plan's largest change and steepest beam.
            let (mut most, mut steepest) = (0.0f64, 0.0f64);
            let machine = BUILTIN_MACHINES
                .iter()
                .map(|(m, _)| *m)
                .find(|m| plan_name.starts_with(m))
                .unwrap_or("table_bc");
            let k = Kinematics::builtin(machine).unwrap();
            let plan = Plan::build(&k, &PlanConfig::load(plan_name).unwrap()).unwrap();
            for n in 0..30 {
                let mut s = k.nominal_state();
                if n > 0 {
                    // Errors and a setter tilt that slope every beam a little.
                    for id in &k.identify {
                        let lim = if id.is_position() { 100.0 } else { 300.0 };
                        s.loc[id.axis][id.slot] = rng.random_range(-lim..lim) * id.scale();
                    }
                    s.beam_dir = Vec3::new(
                        1.0,
                        rng.random_range(-3e-4..3e-4),
                        rng.random_range(-3e-4..3e-4),
                    )
                    .normalize();
                    s.tool_tip = Vec3::new(0.01, -0.01, -0.05);
                }
                for st in plan.steps.iter().filter(|st| {
                    along_tool(st.approach.axis, &k.pose_geometry(&s, &st.angles).tool.axis)
                        == Some(true)
                }) {
                    let pose = k.pose_geometry(&s, &st.angles);
                    let v = latched(&k, &s, &st.angles, &st.approach, &st.start, None).unwrap();
                    let exact = exact_end_face(&pose, s.radius, &st.approach, &st.start, v);
                    let further = f64::from(st.approach.direction) * (v - exact);
                    // The stated change.
                    let (e, w) = (pose.beam_dir, pose.tool.axis);
                    let i = st.approach.axis.index();
                    let e_perp = (e - w * e.dot(&w)).norm();
                    let mut c = st.start;
                    c[i] = v;
                    let d = c - pose.tool.nominal + pose.tool.actual - pose.beam_point;
                    let delta = w.cross(&(e - w * e.dot(&w))).dot(&d) / e_perp;
                    let ew = e.dot(&w).abs();
                    let stated = (ew - rounded_abs(ew))
                        * (s.radius * s.radius - delta * delta).sqrt()
                        / (e_perp * w[i].abs());
                    assert!(
                        (further - stated).abs() < 1e-11,
                        "{plan_name} {}: {further} vs {stated}",
                        st.label
                    );
                    let bound = eps * s.radius / (e_perp * w[i].abs());
                    assert!(
                        further > -1e-12 && further < bound,
                        "{plan_name} {}",
                        st.label
                    );
                    let theta = ew.asin().to_degrees();
                    // Within 0.5 deg of level: at most eps r (5 nm).
                    assert!(
                        theta > 0.5 || further <= eps * s.radius,
                        "{plan_name} {}",
                        st.label
                    );
                    steepest = steepest.max(theta);
                    most = most.max(further);
                    if further > worst.0 {
                        worst = (further, theta, format!("{plan_name} {} (n {n})", st.label));
                    }
                }
            }
            println!(
                "{plan_name} on {machine}: largest change {:.3} nm, steepest beam {steepest:.1} deg \
                 to the end face",
                most * 1e6
            );
        }
        println!(
            "largest change {:.3} nm at a beam {:.1} deg to the end face ({})",
            worst.0 * 1e6,
            worst.1,
            worst.2
        );
        // The documents' figure: at most 9.61 nm on the shipped plans (the steepest beam,
        // 58.6 deg on table_d45_c at D = -90).
        assert!(worst.0 < 9.61e-6, "{worst:?}");
    }

    #[test]
    fn failures_are_named() {
        let (k, s) = setup();
        let miss = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Z, -1),
            &Vec3::new(0.0, -90.0, 0.0),
            None,
        );
        assert!(matches!(miss, Err(NoTrip::Misses { .. })));
        let above = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Y, 1),
            &Vec3::new(0.0, 0.0, 75.0),
            None,
        );
        assert!(matches!(above, Err(NoTrip::AboveBeam { .. })));
        let far = latched(
            &k,
            &s,
            &[0.0, 0.0],
            &ap(Axis::Y, 1),
            &Vec3::new(0.0, 0.0, 65.0),
            Some(Travel {
                start: -120.0,
                max_mm: 3.0,
            }),
        );
        assert!(matches!(far, Err(NoTrip::BeyondTravel { .. })));
    }
}
