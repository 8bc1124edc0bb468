//! The patent's first-order sum and difference relations, derived again for this project's
//! conventions (table axes in the ISO 841 sense, zero pose as reference), as an independent
//! cross-check of the exact solver. The setter of the patent layout (beam along table X
//! through `(0, -R, H)`) on every built-in machine family, each with the poses of its shipped
//! plan.
//!
//! # `table_bc` (the patent's machine, `config/plans/patent.toml`)
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

//!
//! # The C cycle on every family
//!
//! At the zero pose the C cycle is the same on every machine, with the C line's absolute
//! position `(Xc, Yc)` in place of `(a + xc, yc)`: `yc_abs = (y1 + y3)/2 + H alpha`,
//! `Xc = (x2 + x4)/2 - H beta`. Which errors `Xc` and `Yc` are: `head_*`: `(EX0C, EY0C)`;
//! `table_d45_c`: `(EX0D + EX0C, EY0C - EZ0D/sqrt2)`; `trunnion_ac`: `(EX0C, EY0A + EY0C)`.
//!
//! # The tilted poses (first order; `l` = feed x latency, moving end-face readings along the
//! motion)
//!
//! `head_b_table_c` (head B; a pivot error moves the tip by `(I - R) delta`), `a = EX0B`,
//! `e = EZ0B`:
//! ```text
//! B-90 C-90:  x = R + Xc + Yc + H(beta - alpha) - a - e + l      z = H + R(alpha - beta) + r_l + a - e
//! B+90 C-270: x = -R + Xc - Yc + H(alpha + beta) - a + e - l     z = H + R(alpha + beta) + r_l - a - e
//! ```
//! `trunnion_ac` (A about X, table sense), `ya = EY0A`, `za = EZ0A`:
//! ```text
//! A-90 C0:    z = -R + za - ya - l                               y = -H + ya + za - r_l
//! A-90 C-180: z = R + 2Yc - 2H alpha + za - ya - l               y = -H - 2R alpha + ya + za - r_l
//! ```
//! `table_d45_c` (D along (0, 1, 1)/sqrt2, table sense; at +-180 a line offset moves the table
//! by twice itself), `a = EX0D`, `e = EZ0D`:
//! ```text
//! D+-180 C0:  z = -R + sqrt2 e - l                               y = H - sqrt2 e + r_l
//! D-90 C0:    x = (H + R)/sqrt2 + a - e + r_l
//! ```
//! `head_d45_table_c` (head D; the tip moves by `(2a, -sqrt2 e, sqrt2 e)` at +-180):
//! ```text
//! D+-180 C-180: y = R + 2Yc - 2H alpha + sqrt2 e - l             z = H + 2R alpha + r_l - sqrt2 e
//! D180 C-45:    y = x0 - sqrt2 R + r - l - Xc - (sqrt2 - 1) Yc + H((sqrt2 - 1) alpha - beta) + 2a + sqrt2 e
//! ```
//! (`x0`: the commanded x of the C-45 reading. The end face meets the 45-degree beam of C-45
//! at its edge, `r` along it; the estimate keeps the edge's `sqrt(r^2 - dz^2)` for a beam
//! `dz` off the tool axis' height, 1 um at 0.1 mm.)
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
    #[error("no first-order relations are derived for machine '{0}'")]
    Family(String),
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

/// The C cycle's readings (every family), by role: (role, tilt angle, C angle, moving axis).
const C_CYCLE: [(&str, f64, f64, Axis); 8] = [
    ("z1", 0.0, 0.0, Axis::Z),
    ("y1", 0.0, 0.0, Axis::Y),
    ("z2", 0.0, -90.0, Axis::Z),
    ("x2", 0.0, -90.0, Axis::X),
    ("z3", 0.0, -180.0, Axis::Z),
    ("y3", 0.0, -180.0, Axis::Y),
    ("z4", 0.0, -270.0, Axis::Z),
    ("x4", 0.0, -270.0, Axis::X),
];

/// The tilted poses' readings of each family, by role.
fn tilt_roles(family: &str) -> Option<&'static [(&'static str, f64, f64, Axis)]> {
    Some(match family {
        "table_bc" => &[
            ("z5", -90.0, -270.0, Axis::Z),
            ("x5", -90.0, -270.0, Axis::X),
            ("z6", 90.0, -90.0, Axis::Z),
            ("x6", 90.0, -90.0, Axis::X),
        ],
        "head_b_table_c" => &[
            ("xb1", -90.0, -90.0, Axis::X),
            ("zb1", -90.0, -90.0, Axis::Z),
            ("xb2", 90.0, -270.0, Axis::X),
            ("zb2", 90.0, -270.0, Axis::Z),
        ],
        "trunnion_ac" => &[
            ("za1", -90.0, 0.0, Axis::Z),
            ("ya1", -90.0, 0.0, Axis::Y),
            ("za2", -90.0, -180.0, Axis::Z),
            ("ya2", -90.0, -180.0, Axis::Y),
        ],
        // D = +180 and -180 are one pose: their readings are averaged.
        "table_d45_c" => &[
            ("zd1", 180.0, 0.0, Axis::Z),
            ("yd1", 180.0, 0.0, Axis::Y),
            ("xd2", -90.0, 0.0, Axis::X),
        ],
        "head_d45_table_c" => &[
            ("yd1", 180.0, -180.0, Axis::Y),
            ("zd1", 180.0, -180.0, Axis::Z),
            ("yd2", 180.0, -45.0, Axis::Y),
            ("zd2", 180.0, -45.0, Axis::Z),
        ],
        _ => return None,
    })
}

/// One cycle's readings by role (repeats averaged), with each role's latency shift, and the
/// commanded positions they were latched at (summed).
struct Readings(
    BTreeMap<&'static str, (f64, usize, f64)>,
    BTreeMap<&'static str, crate::geometry::Vec3>,
);

impl Readings {
    /// The mean commanded position of a role's readings.
    fn at(&self, role: &'static str) -> Result<crate::geometry::Vec3, RelationsError> {
        let n = self.0.get(role).map(|v| v.1).unwrap_or(0);
        self.1
            .get(role)
            .filter(|_| n > 0)
            .map(|p| p / n as f64)
            .ok_or(RelationsError::Missing(role))
    }
    fn get(&self, role: &'static str) -> Result<f64, RelationsError> {
        self.0
            .get(role)
            .map(|(s, n, _)| s / *n as f64)
            .ok_or(RelationsError::Missing(role))
    }
    fn lat(&self, role: &str) -> f64 {
        self.0.get(role).map(|v| v.2).unwrap_or(0.0)
    }
}

/// What the C cycle gives on every family: the C tilts (rad), the setter's R and H, the C
/// line's absolute position (mm), the lateral radius less latency and the end-face latency.
struct CCycle {
    alpha: f64,
    beta: f64,
    rr: f64,
    h: f64,
    xc: f64,
    yc: f64,
    r_l: f64,
    l_z: f64,
}

fn c_cycle(k: &Kinematics, m: &Readings) -> Result<CCycle, RelationsError> {
    let r = k.tool_radius;
    let r_l = r - m.lat("y1");
    let l_z = m.lat("z1");
    let (z1, y1, z2, x2, z3, y3, z4, x4) = (
        m.get("z1")?,
        m.get("y1")?,
        m.get("z2")?,
        m.get("x2")?,
        m.get("z3")?,
        m.get("y3")?,
        m.get("z4")?,
        m.get("x4")?,
    );
    let h = z1 + l_z;
    let rr = -y1 - r_l;
    let (mut alpha, mut beta) = (0.0f64, 0.0f64);
    for _ in 0..6 {
        alpha = (z3 - z1 - 2.0 * r * beta.abs()) / (2.0 * rr);
        beta = (z4 - z2 - r * ((beta - alpha).abs() - (alpha + beta).abs())) / (2.0 * rr);
    }
    Ok(CCycle {
        alpha,
        beta,
        rr,
        h,
        xc: (x2 + x4) / 2.0 - h * beta,
        yc: (y1 + y3) / 2.0 + h * alpha,
        r_l,
        l_z,
    })
}

/// Apply the relations of the machine's family to one cycle's observations (repeated
/// readings are averaged).
pub fn estimate(k: &Kinematics, obs: &[Observation]) -> Result<RelationsEstimate, RelationsError> {
    let p = k.setter.point;
    let d = k.setter.direction;
    if (d - crate::geometry::Vec3::x()).norm() > 1e-12 || p.x.abs() > 1e-12 || p.y >= 0.0 {
        return Err(RelationsError::Layout);
    }
    let tilt = tilt_roles(&k.name).ok_or_else(|| RelationsError::Family(k.name.clone()))?;
    let mut sums: BTreeMap<&'static str, (f64, usize, f64)> = BTreeMap::new();
    let mut at: BTreeMap<&'static str, crate::geometry::Vec3> = BTreeMap::new();
    for o in obs {
        for (role, b, c, axis) in C_CYCLE.iter().chain(tilt) {
            if o.approach.axis == *axis
                && wrap_deg(o.angles[0] - b).abs() < 1e-9
                && wrap_deg(o.angles[1] - c).abs() < 1e-9
            {
                let e = sums.entry(role).or_insert((0.0, 0, 0.0));
                e.0 += o.reading();
                e.1 += 1;
                e.2 = o.approach.feed_mm_min / 60.0 * k.setter.latency_s;
                *at.entry(role).or_default() += o.position;
            }
        }
    }
    let m = Readings(sums, at);
    let c = c_cycle(k, &m)?;
    let (alpha, beta, rr, h) = (c.alpha, c.beta, c.rr, c.h);
    let s2 = std::f64::consts::SQRT_2;
    // Each family's tilt relations (module docs), in um and urad by name.
    let values: Vec<(&str, f64)> = match k.name.as_str() {
        "table_bc" => {
            let (z5, x5) = (m.get("z5")?, m.get("x5")?);
            let (a, e, xc) = match (m.get("z6"), m.get("x6")) {
                (Ok(z6), Ok(x6)) => {
                    let a = (x5 + x6) / 2.0 - rr * beta;
                    let xc = (z6 - z5) / 2.0 - h * beta;
                    let e = (z5 + z6) / 2.0 + c.l_z - rr - c.yc + h * alpha;
                    (a, e, xc)
                }
                _ => {
                    let pp = x5 - h - c.r_l - rr * (alpha + beta);
                    let q = z5 + c.l_z - rr - c.yc + h * (alpha + beta);
                    let a = (c.xc + pp + q) / 2.0;
                    (a, a - pp, c.xc - a)
                }
            };
            vec![("EX0B", a), ("EZ0B", e), ("EY0C", c.yc), ("EX0C", xc)]
        }
        "head_b_table_c" => {
            let (xb1, zb1, xb2, zb2) = (m.get("xb1")?, m.get("zb1")?, m.get("xb2")?, m.get("zb2")?);
            let a = (zb1 - zb2) / 2.0 + rr * beta;
            let e = rr + c.yc - h * alpha + c.l_z - (xb1 - xb2) / 2.0;
            vec![("EX0B", a), ("EZ0B", e), ("EX0C", c.xc), ("EY0C", c.yc)]
        }
        "trunnion_ac" => {
            let (za1, ya1, za2, ya2) = (m.get("za1")?, m.get("ya1")?, m.get("za2")?, m.get("ya2")?);
            // za - ya and za + ya, each the mean of the two poses.
            let diff = (za1 + rr + c.l_z + za2 - rr - 2.0 * c.yc + 2.0 * h * alpha + c.l_z) / 2.0;
            let sum = (ya1 + h + c.r_l + ya2 + h + 2.0 * rr * alpha + c.r_l) / 2.0;
            let (za, ya) = ((sum + diff) / 2.0, (sum - diff) / 2.0);
            vec![
                ("EY0A", ya),
                ("EZ0A", za),
                ("EX0C", c.xc),
                ("EY0C", c.yc - ya),
            ]
        }
        "table_d45_c" => {
            let (zd1, yd1, xd2) = (m.get("zd1")?, m.get("yd1")?, m.get("xd2")?);
            let e = (zd1 - yd1 + rr + h + c.l_z + c.r_l) / (2.0 * s2);
            let a = xd2 - (h + rr) / s2 + e - c.r_l;
            vec![
                ("EX0D", a),
                ("EZ0D", e),
                ("EX0C", c.xc - a),
                ("EY0C", c.yc + e / s2),
            ]
        }
        "head_d45_table_c" => {
            let (yd1, zd1, yd2) = (m.get("yd1")?, m.get("zd1")?, m.get("yd2")?);
            let e1 = (yd1 + c.l_z - rr - 2.0 * c.yc + 2.0 * h * alpha) / s2;
            let e2 = (h + 2.0 * rr * alpha + c.r_l - zd1) / s2;
            let e = (e1 + e2) / 2.0;
            // The diagonal beam of C-45 under the end face: the reading follows the beam's y
            // at the commanded x, and the face's edge meets it sqrt(r^2 - dz^2) along, dz the
            // beam's height over the tool axis (kept: 0.1 mm of setter height is 1 um here).
            let p = m.at("yd2")?;
            let hh = std::f64::consts::FRAC_1_SQRT_2;
            let dz = h + rr * ((1.0 - hh) * alpha - hh * beta) - p.z - s2 * e;
            let r = k.tool_radius;
            let edge = (r * r - dz * dz).max(0.0).sqrt();
            let a = (yd2 - p.x + s2 * rr - edge + c.l_z + c.xc + (s2 - 1.0) * c.yc
                - h * ((s2 - 1.0) * alpha - beta)
                - s2 * e)
                / 2.0;
            vec![("EX0D", a), ("EZ0D", e), ("EX0C", c.xc), ("EY0C", c.yc)]
        }
        other => return Err(RelationsError::Family(other.to_string())),
    };
    let errors = values
        .into_iter()
        .map(|(n, v)| (n.to_string(), v * 1e3))
        .chain([
            ("EA0C".to_string(), alpha * 1e6),
            ("EB0C".to_string(), beta * 1e6),
        ])
        .collect();
    Ok(RelationsEstimate {
        errors,
        r_mm: rr,
        h_mm: h,
    })
}
