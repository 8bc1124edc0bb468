//! The in-process correction table of seed 003 (Okuma, JP H5-318287, a super-precision lathe):
//! face a part, measure the face on the machine, correct the Z positioning along X from the
//! measured profile, cut again until the face is flat to the tolerance.
//!
//! **The table, as the seed defines it.** The reference is the work centre; the table starts
//! at the edge, `x_n = D/2`, with the error there set to zero; along the section through the
//! centre the correction at each radial position is `d1(x_i) = dz(x_i) - dz(x_n)`. The NC's
//! resolution bounds the number of radial divisions: `resolution <= D / (2 n)`, so
//! `n_max = D / (2 resolution)`.
//!
//! **The loop.** Cut, measure, build the table, and if `dz_max = max |d1| > dz_a` shift the Z
//! command at each X by `-d1` (linearly between the table's points) and cut again; stop with
//! GOOD when within `dz_a`, or at the iteration cap with the reason.
//!
//! **The simulated face.** The surface height at radius `x` is the command plus the X axis'
//! straightness in Z, the thermal growth of Z while the tool crosses the face (a drift rate
//! that changes from cut to cut: the part of the error a table cannot learn) and the
//! corrections so far; the measurement adds its noise.

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::axis_errors::Profile;

/// The largest number of radial divisions the NC can resolve: `D / (2 resolution)`.
pub fn n_max(diameter_mm: f64, resolution_um: f64) -> usize {
    (diameter_mm / (2.0 * resolution_um * 1e-3)).floor() as usize
}

/// A correction table: radial positions from the edge (`D/2`) to the centre, mm, and the
/// correction `d1` at each, um (zero at the edge).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Table {
    pub x_mm: Vec<f64>,
    pub d1_um: Vec<f64>,
}

impl Table {
    /// The seed's table from a profile measured at the table's positions.
    pub fn from_profile(x_mm: &[f64], dz_um: &[f64]) -> Table {
        let edge = dz_um.first().copied().unwrap_or(0.0);
        Table {
            x_mm: x_mm.to_vec(),
            d1_um: dz_um.iter().map(|v| v - edge).collect(),
        }
    }

    /// The correction at radius `x` (linear between the points, constant beyond them).
    pub fn at(&self, x: f64) -> f64 {
        let n = self.x_mm.len();
        if n == 0 {
            return 0.0;
        }
        // Positions run from the edge (largest) down to the centre.
        for w in 0..n.saturating_sub(1) {
            let (x0, x1) = (self.x_mm[w], self.x_mm[w + 1]);
            if x <= x0 && x >= x1 {
                let f = if x0 > x1 { (x0 - x) / (x0 - x1) } else { 0.0 };
                return self.d1_um[w] + f * (self.d1_um[w + 1] - self.d1_um[w]);
            }
        }
        if x > self.x_mm[0] {
            self.d1_um[0]
        } else {
            self.d1_um[n - 1]
        }
    }

    pub fn max_abs_um(&self) -> f64 {
        self.d1_um.iter().map(|v| v.abs()).fold(0.0, f64::max)
    }

    /// The table as the NC loads it: a CSV of `x_mm,dz_um` (the correction to add to Z).
    pub fn csv(&self) -> String {
        let mut s = String::from("x_mm,dz_um\n");
        for (x, d) in self.x_mm.iter().zip(&self.d1_um) {
            s += &format!("{x:.4},{:.4}\n", -d);
        }
        s
    }
}

/// The face and the machine that cuts it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Face {
    pub diameter_mm: f64,
    /// The X axis' straightness in Z over the radius (edge to centre), um.
    pub straightness: Profile,
    /// Facing feed, mm/min (the time the tool takes from the edge to each radius).
    pub feed_mm_min: f64,
    /// Z growth while cutting: a mean rate and its spread from cut to cut, um/min.
    pub drift_um_per_min: f64,
    pub drift_sd_um_per_min: f64,
    /// Measurement noise per point, um.
    pub noise_um: f64,
}

impl Face {
    /// The face's height error at radius `x` for one cut with this drift rate, um.
    fn height_um(&self, x: f64, drift: f64, correction: &Table) -> f64 {
        let r = self.diameter_mm / 2.0;
        let t_min = (r - x) / self.feed_mm_min;
        self.straightness.at(r - x, r) + drift * t_min - correction.at(x)
    }
}

/// Loop settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoopSettings {
    /// Radial divisions (at most `n_max`).
    pub divisions: usize,
    /// The NC's resolution, um.
    pub resolution_um: f64,
    /// Tolerance `dz_a`, um.
    pub tolerance_um: f64,
    pub max_iterations: usize,
}

/// One cut of the loop.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Cut {
    pub iteration: usize,
    /// The measured profile's table (`d1`) and its largest magnitude, um.
    pub measured: Table,
    pub dz_max_um: f64,
    /// The face's true flatness (largest minus smallest height), um: what the part has.
    pub true_flatness_um: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopResult {
    pub cuts: Vec<Cut>,
    /// "GOOD" when within tolerance, else why it stopped.
    pub verdict: String,
    pub good: bool,
    /// The correction table in force at the end.
    pub table: Table,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LoopError {
    #[error(
        "{divisions} divisions exceed n_max = {n_max} for D = {diameter_mm} mm at a {resolution_um} um resolution"
    )]
    Divisions {
        divisions: usize,
        n_max: usize,
        diameter_mm: f64,
        resolution_um: f64,
    },
    #[error("{0} must be positive")]
    NotPositive(&'static str),
}

/// Cuts, measures and corrects until the face is within tolerance or the cap is reached.
pub fn run(face: &Face, s: &LoopSettings, rng: &mut impl Rng) -> Result<LoopResult, LoopError> {
    for (name, v) in [
        ("diameter_mm", face.diameter_mm),
        ("feed_mm_min", face.feed_mm_min),
        ("resolution_um", s.resolution_um),
        ("tolerance_um", s.tolerance_um),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(LoopError::NotPositive(name));
        }
    }
    let limit = n_max(face.diameter_mm, s.resolution_um);
    if s.divisions == 0 || s.divisions > limit {
        return Err(LoopError::Divisions {
            divisions: s.divisions,
            n_max: limit,
            diameter_mm: face.diameter_mm,
            resolution_um: s.resolution_um,
        });
    }
    let r = face.diameter_mm / 2.0;
    let xs: Vec<f64> = (0..=s.divisions)
        .map(|i| r - i as f64 * r / s.divisions as f64)
        .collect();
    let mut table = Table {
        x_mm: xs.clone(),
        d1_um: vec![0.0; xs.len()],
    };
    let mut cuts = Vec::new();
    for iteration in 1..=s.max_iterations.max(1) {
        let z: f64 = StandardNormal.sample(rng);
        let drift = face.drift_um_per_min + face.drift_sd_um_per_min * z;
        let heights: Vec<f64> = xs
            .iter()
            .map(|x| face.height_um(*x, drift, &table))
            .collect();
        let measured: Vec<f64> = heights
            .iter()
            .map(|h| {
                let z: f64 = StandardNormal.sample(rng);
                h + face.noise_um * z
            })
            .collect();
        let m = Table::from_profile(&xs, &measured);
        let dz_max = m.max_abs_um();
        let (lo, hi) = heights
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
        cuts.push(Cut {
            iteration,
            measured: m.clone(),
            dz_max_um: dz_max,
            true_flatness_um: hi - lo,
        });
        if dz_max <= s.tolerance_um {
            return Ok(LoopResult {
                cuts,
                verdict: "GOOD".into(),
                good: true,
                table,
            });
        }
        if iteration == s.max_iterations.max(1) {
            break;
        }
        // Correct the Z command by the measured table, rounded to the NC's resolution.
        for (d, add) in table.d1_um.iter_mut().zip(&m.d1_um) {
            *d = ((*d + add) / s.resolution_um).round() * s.resolution_um;
        }
    }
    let last = cuts.last().map_or(f64::NAN, |c| c.dz_max_um);
    let floor = 2.0 * face.noise_um * 2f64.sqrt();
    let why = if floor > s.tolerance_um {
        format!(
            "the measurement's noise ({} um per point, about {floor:.2} um between two points at 2 sigma) is above the tolerance",
            face.noise_um
        )
    } else {
        "the error changes from cut to cut more than the tolerance allows (drift between cuts)"
            .to_string()
    };
    Ok(LoopResult {
        verdict: format!(
            "NOT GOOD after {} cuts: dz_max {last:.3} um > dz_a {} um; {why}",
            cuts.len(),
            s.tolerance_um
        ),
        cuts,
        good: false,
        table,
    })
}
