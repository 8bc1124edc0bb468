//! The laser step diagonal measurement (seed 004, Kyoto University).
//!
//! A laser interferometer along a body diagonal of the work volume reads a flat mirror at the
//! tool point while the machine moves in steps of `a`: X, then Y, then Z, to the far corner;
//! the same on the four diagonals `ppp`, `npp`, `pnp`, `ppn` (the signs of their X, Y, Z
//! directions).
//!
//! **The reading.** A flat mirror reads the tool's displacement along its own normal, not
//! along the beam: `R = m . d` to first order (a beam off the mirror normal by a small angle
//! costs only its cosine). With the mirror normal `m = L + mu`, `L = (s_x, s_y, s_z)/sqrt 3`
//! and `mu` across `L` (the set-up error: nobody can square a mirror to a diagonal that only
//! the machine's own, erroneous motion defines), a step of `s_j a` along axis `j` reads
//!
//! ```text
//! sqrt3 dR_j = a + dE_jj + sum_{i != j} s_j s_i dE_ij + c_j,     c_j = sqrt3 s_j mu_j a
//! ```
//!
//! where `dE_ij` is the error increment in direction `i` over the step of axis `j` (taken in
//! the positive sense). `mu . L = 0` makes `c_x + c_y + c_z = 0` on every diagonal, and the
//! `c` are the same at every step: about 1.7 um per 10 mm step for a 100 urad mirror tilt,
//! which adds up to some 20 um over 12 steps.
//!
//! **Conventional formulation** (Wang 2000): three diagonals give nine equations per step for
//! the nine `dE`, with `c` taken as zero; every `c` goes straight into the estimates.
//!
//! **Set-up-robust formulation** (the seed's proposal, derived here for these conventions):
//! the positioning errors `dE_jj` are measured directly (the interferometer along each axis)
//! and known; the unknowns are the six transverse increments of every step and each
//! diagonal's two free `c`. Least squares over all steps of the four diagonals. The sum of a
//! diagonal's three readings at a step cancels its `c`; what differences across steps leave
//! identifiable is each transverse profile's shape, and the sums `dE_xy + dE_yx` etc. carry
//! the squareness. The gauge is the convention of `kinematics::LinearErrors`: X is the
//! reference (its straightness in y and z has zero end-point slope), Y's straightness in z
//! likewise; the squareness `sxy`, `sxz`, `syz` is then the mean slope of Y's x, Z's x and
//! Z's y errors.
//!
//! **Drift.** A linear drift `D` of the tool point (um/min) adds `m . D t` to a reading taken
//! at time `t` after the run's start: on a one-way run the same amount per move, which the
//! solves take for geometry (it lands mostly in the squareness). Run out and back
//! (`Setup::out_and_back`), each diagonal reads every point twice, at `t` and later on the
//! way back; the geometry is the same both times and the drift is not, so each diagonal's
//! rate along its beam, `m . D`, is estimated with the rest (`Estimate::drift_um_per_min`).

use driftwatch_core::geometry::Vec3;
use driftwatch_core::least_squares::{constrained, lsq};
use nalgebra::{DMatrix, DVector};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::axis_errors::ErrorField;
use driftwatch_core::linear_axes::{COMPONENT_UNIT_MM, LinearGeometry};

/// The four body diagonals by the signs of their X, Y, Z directions.
pub const DIAGONALS: [[f64; 3]; 4] = [
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, -1.0],
];

pub fn diagonal_name(s: &[f64; 3]) -> String {
    s.iter().map(|v| if *v > 0.0 { 'p' } else { 'n' }).collect()
}

/// How the measurement is set up and disturbed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Setup {
    /// Step, mm, and number of steps per axis (the cube's side is their product).
    pub step_mm: f64,
    pub steps: usize,
    /// Mirror normal off the diagonal, urad, per diagonal (two components across it).
    pub mirror_tilt_urad: [[f64; 2]; 4],
    /// Interferometer noise per reading, um.
    pub noise_um: f64,
    /// Noise of the direct positioning measurement, um per reading.
    pub positioning_noise_um: f64,
    /// Thermal drift of the tool point during the runs, um/min, and the time per move (one
    /// reading), s.
    pub drift_um_per_min: Vec3,
    pub step_time_s: f64,
    /// Each diagonal out and back: after the far corner the machine returns along the same
    /// staircase (Z, Y, X back in each step), reading at the same points, the clock running
    /// on; the last reading is at the start corner.
    #[serde(default)]
    pub out_and_back: bool,
    /// The beam off the mirror's normal, urad, per diagonal (an interferometer not quite
    /// square to its mirror): a plane mirror then reads `m . d / cos(theta)`, a cosine error
    /// (1.1e-8 of the reading at 150 urad). A beam's lateral offset changes nothing on a
    /// plane mirror at the tool point (its flatness aside), so it has no field.
    #[serde(default)]
    pub beam_tilt_urad: [f64; 4],
}

impl Setup {
    /// The seed's: 10 mm steps over 120 mm, mirror tilts of `tilt_urad` in random directions
    /// and the beams as far off their mirrors, 0.1 um noise, no drift, 5 s per step.
    pub fn seed(tilt_urad: f64, rng: &mut impl Rng) -> Setup {
        let mut mirror_tilt_urad = [[0.0; 2]; 4];
        for t in &mut mirror_tilt_urad {
            let phi = 2.0 * std::f64::consts::PI * rng.random::<f64>();
            *t = [tilt_urad * phi.cos(), tilt_urad * phi.sin()];
        }
        Setup {
            step_mm: 10.0,
            steps: 12,
            mirror_tilt_urad,
            noise_um: 0.1,
            positioning_noise_um: 0.1,
            drift_um_per_min: Vec3::zeros(),
            step_time_s: 5.0,
            out_and_back: false,
            beam_tilt_urad: [tilt_urad; 4],
        }
    }
}

/// One diagonal's readings: after each of the `3 n` moves (X, Y, Z of step 1, ...), um; out and
/// back, `6 n`: then the `3 n` moves of the return (Z, Y, X back of each step from the far
/// corner), the last one ending at the start corner.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiagonalRun {
    pub signs: [f64; 3],
    pub readings_um: Vec<f64>,
}

/// The direct positioning measurement: each axis' own error at the end of each step from its
/// start (um, X, Y, Z), as an interferometer along the axis reads it.
pub type Positioning = [Vec<f64>; 3];

/// Two unit vectors across the diagonal `l`.
fn across(l: &Vec3) -> (Vec3, Vec3) {
    let u = l.cross(&Vec3::z()).normalize();
    (u, l.cross(&u))
}

/// The staircase of a diagonal: the commanded positions after each move, from its start
/// corner, mm (positions within `[0, side]` on each axis).
pub fn staircase(signs: &[f64; 3], step_mm: f64, steps: usize) -> Vec<Vec3> {
    let side = step_mm * steps as f64;
    let mut p = Vec3::new(
        if signs[0] > 0.0 { 0.0 } else { side },
        if signs[1] > 0.0 { 0.0 } else { side },
        if signs[2] > 0.0 { 0.0 } else { side },
    );
    let mut out = vec![p];
    for _ in 0..steps {
        for (j, s) in signs.iter().enumerate() {
            p[j] += s * step_mm;
            out.push(p);
        }
    }
    out
}

/// Where reading `r` (0-based) of a run of `n` steps is taken: its index in the staircase
/// (`3 n` the far corner). The forward leg's reading `r` is after move `r + 1`; the return
/// leg's comes back down the same points to the start corner (index 0).
pub fn position(r: usize, n: usize) -> usize {
    if r < 3 * n { r + 1 } else { 6 * n - r - 1 }
}

/// Simulates the four diagonals (out and back with `setup.out_and_back`) and the direct
/// positioning measurement. Reading `r` is taken `(r + 1) step_time_s` after the run's start.
pub fn simulate(
    errors: &impl ErrorField,
    setup: &Setup,
    rng: &mut impl Rng,
) -> ([DiagonalRun; 4], Positioning) {
    let mut noise = |s: f64| -> f64 {
        let z: f64 = StandardNormal.sample(rng);
        s * z
    };
    let runs = std::array::from_fn(|d| {
        let signs = DIAGONALS[d];
        let l = Vec3::new(signs[0], signs[1], signs[2]) / 3f64.sqrt();
        let (u, v) = across(&l);
        let [t1, t2] = setup.mirror_tilt_urad[d];
        let m = (l + u * (t1 * 1e-6) + v * (t2 * 1e-6)).normalize();
        let path = staircase(&signs, setup.step_mm, setup.steps);
        let actual = |p: &Vec3, k: usize| {
            let t_min = k as f64 * setup.step_time_s / 60.0;
            p * 1e3 + errors.error_um(p) + setup.drift_um_per_min * t_min
        };
        let start = actual(&path[0], 0);
        let moves = if setup.out_and_back { 6 } else { 3 } * setup.steps;
        let readings_um = (0..moves)
            .map(|r| {
                let p = &path[position(r, setup.steps)];
                m.dot(&(actual(p, r + 1) - start)) / (setup.beam_tilt_urad[d] * 1e-6).cos()
                    + noise(setup.noise_um)
            })
            .collect();
        DiagonalRun { signs, readings_um }
    });
    // Along each axis, the others at their start (0): its own error at each step's end.
    let positioning = std::array::from_fn(|j| {
        (1..=setup.steps)
            .map(|k| {
                let mut b = Vec3::zeros();
                b[j] = k as f64 * setup.step_mm;
                errors.error_um(&b)[j] + noise(setup.positioning_noise_um)
            })
            .collect()
    });
    (runs, positioning)
}

/// What a formulation found: the profiles of `actual - commanded` along each axis from its
/// start (um at each step's end), the squareness (urad) and the positioning (um).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Estimate {
    /// Positioning error of X, Y, Z along their own travel, um at 1..=n steps.
    pub positioning_um: [Vec<f64>; 3],
    /// Straightness (end-point reference): Syx, Szx, Sxy, Szy, Sxz, Syz, um at 1..=n steps.
    pub straightness_um: [Vec<f64>; 6],
    /// Squareness sxy, sxz, syz, urad, and its standard uncertainty.
    pub squareness_urad: [f64; 3],
    pub squareness_sigma_urad: [f64; 3],
    /// The largest standard uncertainty of a straightness profile's points, um (same order
    /// as `straightness_um`).
    pub straightness_sigma_um: [f64; 6],
    /// Out-and-back runs only: each diagonal's drift of the tool point along its beam (the
    /// mirror normal), um/min, in the order of `DIAGONALS`, and its standard uncertainty.
    /// `None` for one-way runs: a drift then goes into the geometry.
    pub drift_um_per_min: Option<[f64; 4]>,
    pub drift_sigma_um_per_min: Option<[f64; 4]>,
}

impl Estimate {
    /// The scale (end-point slope of each positioning profile) and squareness as the
    /// kinematics' `LinearErrors`: what a machine's geometry takes from this measurement.
    pub fn linear_errors(&self, range_mm: f64) -> driftwatch_core::kinematics::LinearErrors {
        let slope = |p: &[f64]| p.last().copied().unwrap_or(0.0) * 1e-3 / range_mm;
        driftwatch_core::kinematics::LinearErrors {
            k: std::array::from_fn(|j| slope(&self.positioning_um[j])),
            sxy: self.squareness_urad[0] * 1e-6,
            sxz: self.squareness_urad[1] * 1e-6,
            syz: self.squareness_urad[2] * 1e-6,
            ..Default::default()
        }
    }

    /// The measurement as a machine geometry (what `POST .../geometry` and a machine file's
    /// `[linear]` take), the volume's start corner at `origin_mm` in machine coordinates:
    /// scales and squareness from the end-point lines, and each straightness and each
    /// positioning error beyond its scale as an ISO 230-1 component, a cubic through the
    /// measured points (least squares with a free constant, which no reading can see: a
    /// constant offset of the tool is the setter's). Angular errors are not measured by the
    /// step diagonal and stay zero.
    pub fn geometry(&self, step_mm: f64, origin_mm: &Vec3) -> LinearGeometry {
        let n = self.positioning_um[0].len();
        let range = step_mm * n as f64;
        let linear = self.linear_errors(range);
        let mut g = LinearGeometry::of(&linear);
        let fit = |j: usize, values: &[f64], slope: f64| -> [f64; 3] {
            let u = |k: usize| (origin_mm[j] + k as f64 * step_mm) / COMPONENT_UNIT_MM;
            let a = DMatrix::from_fn(n + 1, 4, |k, c| u(k).powi(c as i32));
            let b = DVector::from_fn(n + 1, |k, _| {
                let v = if k == 0 { 0.0 } else { values[k - 1] };
                v - slope * k as f64 * step_mm * 1e3
            });
            let c = lsq(&a, &b).beta;
            [c[1], c[2], c[3]]
        };
        const AXES: [char; 3] = ['X', 'Y', 'Z'];
        for (j, axis) in AXES.iter().enumerate() {
            let c = fit(j, &self.positioning_um[j], linear.k[j]);
            g.components.insert(format!("E{axis}{axis}"), c.to_vec());
        }
        // Syx, Szx, Sxy, Szy, Sxz, Syz: (direction, axis).
        let names = [(1, 0), (2, 0), (0, 1), (2, 1), (0, 2), (1, 2)];
        for (i, (dir, axis)) in names.into_iter().enumerate() {
            let c = fit(axis, &self.straightness_um[i], 0.0);
            g.components
                .insert(format!("E{}{}", AXES[dir], AXES[axis]), c.to_vec());
        }
        g
    }

    /// A squareness as the seed tabulates it: um over the measured range.
    pub fn squareness_um_over(&self, i: usize, range_mm: f64) -> f64 {
        self.squareness_urad[i] * range_mm * 1e-3
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    #[error("diagonal {0}: {1} readings, expected {2}")]
    Readings(String, usize, usize),
    #[error(
        "diagonal {0}: {1} readings where the others have {2}: all one-way (3 n) or all out and back (6 n)"
    )]
    MixedLegs(String, usize, usize),
    #[error("the least-squares system is singular")]
    Singular,
}

/// Whether the runs are out and back (`6 n` readings each) or one-way (`3 n`); all alike.
pub fn out_and_back(runs: &[DiagonalRun], n: usize) -> Result<bool, SolveError> {
    let first = runs.first().map_or(3 * n, |r| r.readings_um.len());
    if first != 3 * n && first != 6 * n {
        return Err(SolveError::Readings(
            diagonal_name(&runs[0].signs),
            first,
            3 * n,
        ));
    }
    for r in runs {
        if r.readings_um.len() != first {
            return Err(SolveError::MixedLegs(
                diagonal_name(&r.signs),
                r.readings_um.len(),
                first,
            ));
        }
    }
    Ok(first == 6 * n)
}

/// A drift rate along the beam from an out-and-back run: both legs read the same points, so
/// `R_back(p) - R_out(p) = rate (t_back - t_out)`; least squares over the points `0..3n`
/// (the start corner's outward reading is the zero at `t = 0`). Returns the rate (um/min), its
/// standard uncertainty for reading noise `noise_um`, and the forward readings with the drift
/// taken out (both legs averaged where both read).
fn drift_of_run(run: &DiagonalRun, n: usize, step_min: f64, noise_um: f64) -> (f64, f64, Vec<f64>) {
    let r = &run.readings_um;
    // The return reading at staircase point p is r[6n - 1 - p], taken at (6n - p) steps.
    let back = |p: usize| (r[6 * n - 1 - p], (6 * n - p) as f64 * step_min);
    let out = |p: usize| {
        if p == 0 {
            (0.0, 0.0)
        } else {
            (r[p - 1], p as f64 * step_min)
        }
    };
    let (mut num, mut den, mut var) = (0.0, 0.0, 0.0);
    for p in 0..3 * n {
        let ((vb, tb), (vo, to)) = (back(p), out(p));
        let tau = tb - to;
        num += (vb - vo) * tau;
        den += tau * tau;
        // The difference carries two readings' noise, one at the start corner.
        var += tau * tau * if p == 0 { 1.0 } else { 2.0 } * noise_um * noise_um;
    }
    let rate = num / den;
    let sigma = var.sqrt() / den;
    let forward = (1..=3 * n)
        .map(|p| {
            let (vo, to) = out(p);
            if p < 3 * n {
                let (vb, tb) = back(p);
                0.5 * ((vo - rate * to) + (vb - rate * tb))
            } else {
                vo - rate * to
            }
        })
        .collect();
    (rate, sigma, forward)
}

/// Reading increments of each move, `sqrt3 dR - a`, per diagonal and move (the forward leg).
fn increments(runs: &[DiagonalRun], a: f64, n: usize) -> Result<Vec<Vec<f64>>, SolveError> {
    out_and_back(runs, n)?;
    Ok(runs
        .iter()
        .map(|r| {
            let mut prev = 0.0;
            r.readings_um[..3 * n]
                .iter()
                .map(|v| {
                    let d = 3f64.sqrt() * (v - prev) - a * 1e3;
                    prev = *v;
                    d
                })
                .collect()
        })
        .collect())
}

/// The interval a diagonal's move along axis `j` at its step `k` covers: the same in the
/// positive sense, `n - 1 - k` in the negative (it starts from the far end).
fn interval(signs: &[f64; 3], j: usize, k: usize, n: usize) -> usize {
    if signs[j] > 0.0 { k } else { n - 1 - k }
}

/// Profiles (cumulative, um at 1..=n) from increments.
fn cumulative(inc: &[f64]) -> Vec<f64> {
    inc.iter()
        .scan(0.0, |acc, v| {
            *acc += v;
            Some(*acc)
        })
        .collect()
}

/// The conventional formulation: per step, the nine increments from the nine readings of
/// three diagonals (`ppp`, `npp`, `pnp`), set-up errors taken as zero. Out-and-back runs
/// first lose their drift: each diagonal's rate from the differences between its legs
/// (`drift_um_per_min` of the estimate, all four diagonals), then the legs averaged.
pub fn conventional(runs: &[DiagonalRun; 4], setup: &Setup) -> Result<Estimate, SolveError> {
    let (a, n) = (setup.step_mm, setup.steps);
    let mut drift = None;
    let corrected;
    let runs: &[DiagonalRun; 4] = if out_and_back(runs, n)? {
        let step_min = setup.step_time_s / 60.0;
        let d: [(f64, f64, Vec<f64>); 4] =
            std::array::from_fn(|i| drift_of_run(&runs[i], n, step_min, setup.noise_um));
        drift = Some((
            std::array::from_fn(|i| d[i].0),
            std::array::from_fn(|i| d[i].1),
        ));
        corrected = std::array::from_fn(|i| DiagonalRun {
            signs: runs[i].signs,
            readings_um: d[i].2.clone(),
        });
        &corrected
    } else {
        runs
    };
    let inc = increments(&runs[..3], a, n)?;
    let mut de: [[Vec<f64>; 3]; 3] = std::array::from_fn(|_| std::array::from_fn(|_| vec![0.0; n]));
    for j in 0..3 {
        for k in 0..n {
            // Rows: the three diagonals' moves of axis j over interval k (a diagonal that
            // runs negatively along j covers it at its step n-1-k); columns dE_xj, dE_yj, dE_zj.
            let mut m = DMatrix::zeros(3, 3);
            let mut y = DVector::zeros(3);
            for (row, r) in runs[..3].iter().enumerate() {
                let s = r.signs;
                // The move of axis j covering interval k.
                let kk = interval(&s, j, k, n);
                for i in 0..3 {
                    m[(row, i)] = s[j] * s[i];
                }
                y[row] = inc[row][3 * kk + j];
            }
            // Three equations, three unknowns: least squares is the exact solve.
            let fit = lsq(&m, &y);
            if fit.rank < 3 {
                return Err(SolveError::Singular);
            }
            let sol = fit.beta;
            for (row, v) in de.iter_mut().zip(sol.iter()) {
                row[j][k] = *v;
            }
        }
    }
    let mut est = profiles(&de, a, n, None);
    if let Some((rate, sigma)) = drift {
        est.drift_um_per_min = Some(rate);
        est.drift_sigma_um_per_min = Some(sigma);
    }
    Ok(est)
}

/// Turns increments `de[i][j][k]` into the estimate's profiles and squareness.
fn profiles(de: &[[Vec<f64>; 3]; 3], a: f64, n: usize, sigma: Option<[f64; 3]>) -> Estimate {
    let range = a * n as f64;
    let slope = |v: &[f64]| v.iter().sum::<f64>() / (range * 1e-3); // urad
    let detrend = |v: &[f64]| {
        let c = cumulative(v);
        let end = c.last().copied().unwrap_or(0.0);
        c.iter()
            .enumerate()
            .map(|(k, x)| x - end * (k + 1) as f64 / n as f64)
            .collect::<Vec<_>>()
    };
    let order = [(1, 0), (2, 0), (0, 1), (2, 1), (0, 2), (1, 2)];
    Estimate {
        positioning_um: std::array::from_fn(|j| cumulative(&de[j][j])),
        straightness_um: order.map(|(i, j)| detrend(&de[i][j])),
        // The angle between two axes' mean lines, X the reference: Y's x slope plus X's y
        // slope, and so on.
        squareness_urad: [
            slope(&de[0][1]) + slope(&de[1][0]),
            slope(&de[0][2]) + slope(&de[2][0]),
            slope(&de[1][2]) + slope(&de[2][1]),
        ],
        squareness_sigma_urad: sigma.unwrap_or([f64::NAN; 3]),
        straightness_sigma_um: [f64::NAN; 6],
        drift_um_per_min: None,
        drift_sigma_um_per_min: None,
    }
}

/// The set-up-robust formulation: the nine increments of every step (the positioning ones
/// observed by the direct measurement as well) and each diagonal's set-up offsets, estimated
/// by weighted least squares on the readings themselves (each reading the sum of the moves
/// before it, its own noise), in the gauge of `LinearErrors`. Out-and-back runs add one
/// unknown per diagonal, its drift rate along the beam (`reading = geometry + rate t`, `t`
/// from the reading's index and `step_time_s`): the two legs read the same geometry at
/// different times, so a linear drift separates from it. One-way runs estimate no drift.
pub fn robust(
    runs: &[DiagonalRun; 4],
    positioning: &Positioning,
    setup: &Setup,
) -> Result<Estimate, SolveError> {
    let (a, n) = (setup.step_mm, setup.steps);
    for (j, p) in positioning.iter().enumerate() {
        if p.len() != n {
            return Err(SolveError::Readings(["x", "y", "z"][j].into(), p.len(), n));
        }
    }
    let oab = out_and_back(runs, n)?;
    // Unknowns: dE_ij of interval k at (3 i + j) n + k, then per diagonal c_x, c_y
    // (c_z = -c_x - c_y), then, out and back, per diagonal its drift rate along the beam.
    let nd = 9 * n;
    let nu = nd + 8 + if oab { 4 } else { 0 };
    let at = |i: usize, j: usize, k: usize| (3 * i + j) * n + k;
    let per_run = if oab { 6 * n } else { 3 * n };
    let rows = 4 * per_run + 3 * n;
    let mut m = DMatrix::zeros(rows, nu);
    let mut y = DVector::zeros(rows);
    let w = 1.0 / (3f64.sqrt() * setup.noise_um.max(1e-6));
    let step_min = setup.step_time_s / 60.0;
    let mut r = 0;
    for (d, run) in runs.iter().enumerate() {
        let s = run.signs;
        // sqrt3 R at staircase point p = the sum of the moves to it: a + sum_i s_j s_i dE_ij
        // + c_j each (`geometry[p]`), plus sqrt3 times the drift since the start.
        let mut geometry = vec![DVector::<f64>::zeros(nu)];
        for k in 0..n {
            for j in 0..3 {
                let mut row = geometry[geometry.len() - 1].clone();
                let kk = interval(&s, j, k, n);
                for i in 0..3 {
                    row[at(i, j, kk)] += s[j] * s[i];
                }
                match j {
                    0 => row[nd + 2 * d] += 1.0,
                    1 => row[nd + 2 * d + 1] += 1.0,
                    _ => {
                        row[nd + 2 * d] -= 1.0;
                        row[nd + 2 * d + 1] -= 1.0;
                    }
                }
                geometry.push(row);
            }
        }
        for (q, v) in run.readings_um.iter().enumerate() {
            let p = position(q, n);
            let mut row = geometry[p].clone();
            if oab {
                row[nd + 8 + d] = 3f64.sqrt() * (q + 1) as f64 * step_min;
            }
            m.set_row(r, &(row.transpose() * w));
            y[r] = (3f64.sqrt() * v - p as f64 * a * 1e3) * w;
            r += 1;
        }
    }
    // The direct positioning readings: each the sum of its axis' increments so far.
    let wp = 1.0 / setup.positioning_noise_um.max(1e-6);
    for (j, p) in positioning.iter().enumerate() {
        for (k, v) in p.iter().enumerate() {
            for kk in 0..=k {
                m[(r, at(j, j, kk))] = wp;
            }
            y[r] = v * wp;
            r += 1;
        }
    }
    // Gauge: X's straightness in y and z, and Y's in z, have no end-point slope (the sum of
    // their increments is zero). Exact constraints, not heavy rows: the readings do not fix
    // these three sums (they set the frame), and a heavy row only approaches the constraint
    // as its weight grows, at the price of rounding in everything else.
    let mut gauge = DMatrix::zeros(3, nu);
    for (g, (i, j)) in [(1, 0), (2, 0), (2, 1)].into_iter().enumerate() {
        for k in 0..n {
            gauge[(g, at(i, j, k))] = 1.0;
        }
    }
    let fit = constrained(&m, &y, &gauge);
    if fit.rank < nu {
        return Err(SolveError::Singular);
    }
    let (x, cov) = (fit.beta, fit.cov);
    let de: [[Vec<f64>; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| (0..n).map(|k| x[at(i, j, k)]).collect()));
    // A squareness is the sum of one profile's increments over the range (the other's is
    // held at zero by the gauge).
    let range = a * n as f64 * 1e-3;
    let sig = |i: usize, j: usize| {
        let idx: Vec<usize> = (0..n).map(|k| at(i, j, k)).collect();
        let v: f64 = idx
            .iter()
            .flat_map(|&p| idx.iter().map(move |&q| (p, q)))
            .map(|(p, q)| cov[(p, q)])
            .sum();
        v.max(0.0).sqrt() / range
    };
    let mut est = profiles(&de, a, n, Some([sig(0, 1), sig(0, 2), sig(1, 2)]));
    // A straightness point p is sum_{k<=p} dE_k - (p+1)/n sum_k dE_k: its variance g' C g.
    let order = [(1, 0), (2, 0), (0, 1), (2, 1), (0, 2), (1, 2)];
    for (t, (i, j)) in order.iter().enumerate() {
        let mut worst: f64 = 0.0;
        for p in 0..n {
            let g: Vec<f64> = (0..n)
                .map(|k| f64::from(u8::from(k <= p)) - (p + 1) as f64 / n as f64)
                .collect();
            let mut v = 0.0;
            for (k1, g1) in g.iter().enumerate() {
                for (k2, g2) in g.iter().enumerate() {
                    v += g1 * g2 * cov[(at(*i, *j, k1), at(*i, *j, k2))];
                }
            }
            worst = worst.max(v.max(0.0).sqrt());
        }
        est.straightness_sigma_um[t] = worst;
    }
    if oab {
        est.drift_um_per_min = Some(std::array::from_fn(|d| x[nd + 8 + d]));
        est.drift_sigma_um_per_min = Some(std::array::from_fn(|d| {
            cov[(nd + 8 + d, nd + 8 + d)].max(0.0).sqrt()
        }));
    }
    Ok(est)
}

/// The log's `step` and `axis` of a diagonal's reading `m` (0-based) in a run of `n` steps.
fn csv_row(m: usize, n: usize) -> (usize, &'static str) {
    if m < 3 * n {
        (m / 3 + 1, ["x", "y", "z"][m % 3])
    } else {
        let b = m - 3 * n;
        (n + b / 3 + 1, ["z", "y", "x"][b % 3])
    }
}

/// An interferometer log as CSV: `diagonal,step,axis,reading_um`, one row per move; `diagonal`
/// is `ppp`, `npp`, `pnp` or `ppn` (the moves of a diagonal in the order X, Y, Z of each step,
/// the reading after the move, from the start corner) or `line` for the direct positioning
/// measurement along `axis` (the reading at each step's end from the axis' start).
///
/// Out and back, the return leg continues the step numbers: step `n + k` is the `k`-th step
/// back from the far corner, its moves in the order Z, Y, X, so that step `2 n`'s `x` row is
/// the reading back at the start corner. A one-way log is the same layout as before the
/// return leg existed. `n` is the positioning's length.
pub fn to_csv(runs: &[DiagonalRun; 4], positioning: &Positioning) -> String {
    let n = positioning[0].len();
    let mut s = String::from("diagonal,step,axis,reading_um\n");
    for r in runs {
        let name = diagonal_name(&r.signs);
        for (m, v) in r.readings_um.iter().enumerate() {
            let (step, axis) = csv_row(m, n);
            s += &format!("{name},{step},{axis},{v:.4}\n");
        }
    }
    for (j, p) in positioning.iter().enumerate() {
        for (k, v) in p.iter().enumerate() {
            s += &format!("line,{},{},{v:.4}\n", k + 1, ["x", "y", "z"][j]);
        }
    }
    s
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParseError {
    #[error("line {line}: {detail}")]
    Line { line: usize, detail: String },
    #[error("{0}")]
    Missing(String),
}

/// Reads an interferometer log (`to_csv`'s layout; rows in any order) of `n` steps: one-way
/// when no diagonal has a step past `n`, else out and back (every diagonal's return leg
/// complete).
pub fn from_csv(text: &str, n: usize) -> Result<([DiagonalRun; 4], Positioning), ParseError> {
    let mut runs: [Vec<Option<f64>>; 4] = std::array::from_fn(|_| vec![None; 6 * n]);
    let mut pos: [Vec<Option<f64>>; 3] = std::array::from_fn(|_| vec![None; n]);
    for (i, raw) in text.lines().enumerate().skip(1) {
        let line = i + 1;
        if raw.trim().is_empty() {
            continue;
        }
        let bad = |detail: String| ParseError::Line { line, detail };
        let cells: Vec<&str> = raw.split(',').map(str::trim).collect();
        let [diag, step, axis, value] = cells[..] else {
            return Err(bad(format!("{} cells, expected 4", cells.len())));
        };
        let line_row = diag.eq_ignore_ascii_case("line");
        let last = if line_row { n } else { 2 * n };
        let step: usize = step
            .parse()
            .ok()
            .filter(|s| (1..=last).contains(s))
            .ok_or_else(|| bad(format!("step '{step}' is not 1..{last}")))?;
        let j = ["x", "y", "z"]
            .iter()
            .position(|a| a.eq_ignore_ascii_case(axis))
            .ok_or_else(|| bad(format!("axis '{axis}' is not x, y or z")))?;
        let v: f64 = value
            .parse()
            .ok()
            .filter(|v: &f64| v.is_finite())
            .ok_or_else(|| bad(format!("reading '{value}' is not a finite number")))?;
        let slot = if line_row {
            &mut pos[j][step - 1]
        } else {
            let d = DIAGONALS
                .iter()
                .position(|s| diagonal_name(s).eq_ignore_ascii_case(diag))
                .ok_or_else(|| {
                    bad(format!(
                        "diagonal '{diag}' is not ppp, npp, pnp, ppn or line"
                    ))
                })?;
            if step <= n {
                &mut runs[d][3 * (step - 1) + j]
            } else {
                // The return: Z, Y, X back in each step.
                &mut runs[d][3 * n + 3 * (step - n - 1) + 2 - j]
            }
        };
        if slot.replace(v).is_some() {
            return Err(bad(format!("{diag} step {step} {axis} is given twice")));
        }
    }
    let complete = |v: &[Option<f64>], what: String| -> Result<Vec<f64>, ParseError> {
        v.iter()
            .enumerate()
            .map(|(k, x)| {
                x.ok_or_else(|| {
                    let at = if what.starts_with("line") {
                        format!("step {}", k + 1)
                    } else {
                        let (step, axis) = csv_row(k, n);
                        format!("step {step} {axis}")
                    };
                    ParseError::Missing(format!("{what} {at}: the reading is missing"))
                })
            })
            .collect()
    };
    let back = runs.iter().any(|r| r[3 * n..].iter().any(Option::is_some));
    let len = if back { 6 * n } else { 3 * n };
    let mut out = Vec::new();
    for (d, r) in runs.iter().enumerate() {
        out.push(DiagonalRun {
            signs: DIAGONALS[d],
            readings_um: complete(&r[..len], diagonal_name(&DIAGONALS[d]))?,
        });
    }
    let positioning = [
        complete(&pos[0], "line x".into())?,
        complete(&pos[1], "line y".into())?,
        complete(&pos[2], "line z".into())?,
    ];
    let runs: [DiagonalRun; 4] = out
        .try_into()
        .map_err(|_| ParseError::Missing("diagonals".into()))?;
    Ok((runs, positioning))
}
