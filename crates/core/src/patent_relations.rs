//! The patent's first-order sum and difference relations, derived again for this project's
//! conventions (table axes in the ISO 841 sense, zero pose as reference), as an independent
//! cross-check of the exact solver. Patent layout only: beam along table X through
//! `(0, -R, H)`, the poses of `config/plans/patent.toml`.
//!
//! First-order readings, with `a = EX0B, e = EZ0B, yc = EY0C, xc = EX0C, alpha = EA0C,
//! beta = EB0C`, `r_l` the effective radius minus feed x latency of lateral approaches,
//! `l_z` the latency shift of vertical ones and `r` the tool radius:
//!
//! ```text
//! z1 = H - l_z                                y1 = -R - r_l
//! z2 = H + R(alpha - beta) + r|alpha + beta| - l_z
//! x2 =  R + r_l + a + xc + yc + H(beta - alpha)
//! z3 = H + 2R alpha + 2r|beta| - l_z           y3 = R + r_l + 2yc - 2H alpha
//! z4 = H + R(alpha + beta) + r|beta - alpha| - l_z
//! x4 = -R - r_l + a + xc - yc + H(alpha + beta)
//! z5 = R + e - xc + yc - H(alpha + beta) - l_z  x5 = H + r_l + a - e + R(alpha + beta)
//! z6 = R + e + xc + yc + H(beta - alpha) - l_z  x6 = -H - r_l + a + e + R(beta - alpha)
//! ```
//! (1, 2, 3, 4: B = 0 at C = 0, -90, -180, -270; 5: B = -90, C = -270; 6: B = +90, C = -90.)
//! The `r|...|` terms are the flat end face meeting a sloping beam at its high end; the patent's
//! relations omit them. Hence the patent's sums hold as quoted,
//! `y1 + y3 = 2 EY0C - 2 z1 EA0C` and `x2 + x4 = 2(EX0B + EX0C) + 2 z2 EB0C`, and so does
//! `z3 - z1 = (y3 - y1) EA0C` to first order (lever 2R), but the X difference is
//! `z4 - z2 = (x2 - x4) EB0C`, with the sign opposite to the quoted text.

use std::collections::BTreeMap;

use thiserror::Error;

use crate::geometry::wrap_deg;
use crate::identify::Observation;
use crate::kinematics::Kinematics;
use crate::measurement::Axis;

#[derive(Debug, Error, PartialEq)]
pub enum RelationsError {
    #[error(
        "the relations need the patent layout (beam along table X through (0, -R, H)); this setter differs"
    )]
    Layout,
    #[error("reading {0} (pose and axis of the patent cycle) is missing")]
    Missing(&'static str),
}

/// Estimates from the first-order relations: um and urad, and the setter's R and H in mm.
#[derive(Debug, Clone, PartialEq)]
pub struct RelationsEstimate {
    pub errors: BTreeMap<String, f64>,
    pub r_mm: f64,
    pub h_mm: f64,
}

const ROLES: [(&str, f64, f64, Axis); 12] = [
    ("z1", 0.0, 0.0, Axis::Z),
    ("y1", 0.0, 0.0, Axis::Y),
    ("z2", 0.0, -90.0, Axis::Z),
    ("x2", 0.0, -90.0, Axis::X),
    ("z3", 0.0, -180.0, Axis::Z),
    ("y3", 0.0, -180.0, Axis::Y),
    ("z4", 0.0, -270.0, Axis::Z),
    ("x4", 0.0, -270.0, Axis::X),
    ("z5", -90.0, -270.0, Axis::Z),
    ("x5", -90.0, -270.0, Axis::X),
    ("z6", 90.0, -90.0, Axis::Z),
    ("x6", 90.0, -90.0, Axis::X),
];

/// Apply the relations to one cycle's observations (repeated readings are averaged).
pub fn estimate(k: &Kinematics, obs: &[Observation]) -> Result<RelationsEstimate, RelationsError> {
    let p = k.setter.point;
    let d = k.setter.direction;
    if (d - crate::geometry::Vec3::x()).norm() > 1e-12 || p.x.abs() > 1e-12 || p.y >= 0.0 {
        return Err(RelationsError::Layout);
    }
    let mut sums: BTreeMap<&str, (f64, usize, f64)> = BTreeMap::new();
    for o in obs {
        for (role, b, c, axis) in ROLES {
            if o.approach.axis == axis
                && wrap_deg(o.angles[0] - b).abs() < 1e-9
                && wrap_deg(o.angles[1] - c).abs() < 1e-9
            {
                let e = sums.entry(role).or_insert((0.0, 0, 0.0));
                e.0 += o.reading();
                e.1 += 1;
                e.2 = o.approach.feed_mm_min / 60.0 * k.setter.latency_s;
            }
        }
    }
    let get = |role: &'static str| {
        sums.get(role)
            .map(|(s, n, _)| s / *n as f64)
            .ok_or(RelationsError::Missing(role))
    };
    let lat = |role: &str| sums.get(role).map(|v| v.2).unwrap_or(0.0);
    let r = k.tool_radius;
    let r_l = r - lat("y1");
    let l_z = lat("z1");
    let (z1, y1, z2, x2, z3, y3, z4, x4, z5, x5) = (
        get("z1")?,
        get("y1")?,
        get("z2")?,
        get("x2")?,
        get("z3")?,
        get("y3")?,
        get("z4")?,
        get("x4")?,
        get("z5")?,
        get("x5")?,
    );
    let h = z1 + l_z;
    let rr = -y1 - r_l;
    let (mut alpha, mut beta) = (0.0f64, 0.0f64);
    for _ in 0..6 {
        alpha = (z3 - z1 - 2.0 * r * beta.abs()) / (2.0 * rr);
        beta = (z4 - z2 - r * ((beta - alpha).abs() - (alpha + beta).abs())) / (2.0 * rr);
    }
    let yc = (y1 + y3) / 2.0 + h * alpha;
    let s = (x2 + x4) / 2.0 - h * beta;
    let (a, e, xc) = match (get("z6"), get("x6")) {
        (Ok(z6), Ok(x6)) => {
            let a = (x5 + x6) / 2.0 - rr * beta;
            let xc = (z6 - z5) / 2.0 - h * beta;
            let e = (z5 + z6) / 2.0 + l_z - rr - yc + h * alpha;
            (a, e, xc)
        }
        _ => {
            let pp = x5 - h - r_l - rr * (alpha + beta);
            let q = z5 + l_z - rr - yc + h * (alpha + beta);
            let a = (s + pp + q) / 2.0;
            (a, a - pp, s - a)
        }
    };
    let errors = [
        ("EX0B", a * 1e3),
        ("EZ0B", e * 1e3),
        ("EY0C", yc * 1e3),
        ("EX0C", xc * 1e3),
        ("EA0C", alpha * 1e6),
        ("EB0C", beta * 1e6),
    ]
    .into_iter()
    .map(|(n, v)| (n.to_string(), v))
    .collect();
    Ok(RelationsEstimate {
        errors,
        r_mm: rr,
        h_mm: h,
    })
}
