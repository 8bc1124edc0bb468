//! Identification of location errors from processed R-test runs: weighted least squares on
//! the exact kinematic model.
//!
//! Each reading gives the deviation `d` (table frame, um) of the spindle-side object's centre
//! from the table-side object's:
//! `d = R_t^T (tip - T(P) + R_h h) - t`, where `T`, `R_t`, `R_h` are the actual table and
//! head transforms at the pose under the location errors `p`, `tip` the actual tool reference
//! point under the NC's nominal command, `t` the table-side object's set-up offset (free: no
//! one knows where the nest or ball sits to a micrometre) and `h` the spindle-side object's
//! offset from the tool reference point (calibrated: a prior of mean 0 and the calibration's
//! standard uncertainty). On a table-only machine `R_t^T h` is exactly the signature of the
//! axis lines' positions, which is why the errors found are *apparent* (relative to the
//! spindle-side object, as the tool setter's are relative to the tool tip) and why the head
//! calibration's uncertainty enters theirs.
//!
//! The design matrix is the model's Jacobian at the nominal (central differences of 1 um or
//! 1 urad: the model is linear to far below the noise at micrometre errors), the weights the
//! inverse of each deviation's covariance (whitened by its Cholesky factor). A parameter is
//! estimated only if it raises the rank of the design; one that does not is named with the
//! parameters it cannot be told from. Standard uncertainties come from the covariance, scaled
//! by the Birge ratio `sqrt(chi2/dof)` when that exceeds 1 (the model then misses something,
//! and the scatter, not the a-priori noise, says how well the errors are known).

use std::collections::BTreeMap;

use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::{ErrorId, Kinematics, MachineState};
use driftwatch_core::least_squares::{lsq, lsq_with_tol};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::kinematic_test::{Setup, deviation_table_um};
use crate::process::Processed;

/// The parameters a solve may estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Param {
    Error(ErrorId),
    Table(usize),
    Head(usize),
    /// The spindle-side object's drift, head frame, um/min (thermal growth during the run),
    /// and its change, um/min^2 (the growth's lag bends it within minutes of a start or stop).
    HeadRate(usize),
    HeadCurve(usize),
    /// A location error's drift during the runs, its unit per minute.
    ErrorRate(ErrorId),
    /// A linear-axis error of the tool side: scale X, Y, Z (ppm), squareness XY, XZ, YZ
    /// (urad), as `kinematics::LinearErrors`.
    Linear(usize),
    /// A rotary axis' angular positioning error, one harmonic of its commanded angle (urad):
    /// `value * cos(n theta)` or `value * sin(n theta)`.
    Index {
        axis: usize,
        harmonic: u32,
        sine: bool,
    },
}

/// The angular positioning harmonics `all_errors` asks for, per axis.
const INDEX_HARMONICS: u32 = 2;

/// The name of an angular positioning harmonic, e.g. `C_index_cos2_urad`.
pub fn index_name(axis: &str, harmonic: u32, sine: bool) -> String {
    format!(
        "{axis}_index_{}{harmonic}_urad",
        if sine { "sin" } else { "cos" }
    )
}

fn parse_index(k: &Kinematics, name: &str) -> Option<Param> {
    let (axis, rest) = name.split_once("_index_")?;
    let rest = rest.strip_suffix("_urad")?;
    let (sine, n) = if let Some(n) = rest.strip_prefix("sin") {
        (true, n)
    } else {
        (false, rest.strip_prefix("cos")?)
    };
    let harmonic: u32 = n.parse().ok().filter(|h| *h >= 1)?;
    let axis = k.rotary.iter().position(|a| a.name == axis)?;
    Some(Param::Index {
        axis,
        harmonic,
        sine,
    })
}

/// The linear-axis errors the R-test can be asked for, by name.
pub const LINEAR_ERRORS: [&str; 6] = [
    "scale_x_ppm",
    "scale_y_ppm",
    "scale_z_ppm",
    "squareness_xy_urad",
    "squareness_xz_urad",
    "squareness_yz_urad",
];

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Estimate {
    pub value: f64,
    pub sigma: f64,
    pub unit: &'static str,
}

/// What a solve found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Identification {
    pub machine: String,
    /// Reference time: mean time of the readings, ns.
    pub t_ns: i64,
    pub tests: Vec<String>,
    /// The location errors (um, urad), apparent: relative to the spindle-side object.
    pub errors: BTreeMap<String, Estimate>,
    /// The table-side object's offset from its programmed centre, table frame, um.
    pub table_object_um: [Estimate; 3],
    /// The spindle-side object's offset from the tool reference point (prior and data), um.
    pub head_object_um: [Estimate; 3],
    /// The spindle-side object's drift during the runs (when asked for), um/min.
    pub drift: BTreeMap<String, Estimate>,
    /// Parameters asked for that these tests cannot separate, with what they are tied to.
    pub not_identifiable: Vec<String>,
    pub n_readings: usize,
    pub chi2: f64,
    pub dof: usize,
    /// The factor the a-priori uncertainties were scaled by (>= 1).
    pub birge: f64,
    pub residual_rms_um: f64,
    /// Correlation of the estimated errors, in `errors`' order.
    pub correlation: Vec<Vec<f64>>,
}

impl Identification {
    /// The result as a reference measurement for the service's verification
    /// (`POST /api/v1/machines/{id}/verifications`): errors and standard uncertainties by
    /// name at the reference time, only those of `names` (the errors the tool setter
    /// identifies: the others have nothing to be compared with).
    pub fn reference_json(&self, names: &[String]) -> serde_json::Value {
        let kept = self.errors.iter().filter(|(n, _)| names.contains(n));
        let errors: BTreeMap<&String, f64> = kept.clone().map(|(n, e)| (n, e.value)).collect();
        let sigma: BTreeMap<&String, f64> = kept.map(|(n, e)| (n, e.sigma)).collect();
        serde_json::json!({
            "instrument": "rtest",
            "t_ns": self.t_ns,
            "errors": errors,
            "sigma": sigma,
            "frame_note": "apparent location errors relative to the spindle-side object (ball or nest), its calibration's uncertainty included",
            "source": self.tests.join(", "),
        })
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IdentifyError {
    #[error("{0} is not a location error of this machine")]
    UnknownError(String),
    #[error("no processed readings to identify from")]
    Empty,
    #[error("a reading's covariance is not positive definite")]
    Covariance,
    #[error("the least-squares system is singular")]
    Singular,
}

/// What to estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// Location errors by name; empty: the machine's own `identify` list.
    pub errors: Vec<String>,
    /// Standard uncertainty of the spindle-side object's calibration, um (per component).
    pub head_sigma_um: f64,
    /// Estimate drifts while the tests run, so that the errors refer to the readings' mean
    /// time: the spindle-side object's, linear and quadratic in time (the spindle's growth),
    /// and each estimated location error's, linear (the structure's).
    pub drift_rates: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            errors: Vec::new(),
            head_sigma_um: 0.5,
            drift_rates: false,
        }
    }
}

/// Every location error of the machine that the model can carry (positions, orientations and
/// zero angles of every axis), by name.
/// The machine's identified errors come first: when two cannot be told apart, the one the
/// tool setter also reports is kept and the other named. The linear axes' scale and
/// squareness errors come next, then each rotary axis' angular positioning error as the
/// first two harmonics of its angle.
pub fn all_errors(k: &Kinematics) -> Vec<String> {
    let mut out = k.identify_names();
    for n in k
        .rotary
        .iter()
        .flat_map(|ax| ax.error_names.iter().map(|n| n.to_string()))
    {
        if !out.contains(&n) {
            out.push(n);
        }
    }
    out.extend(LINEAR_ERRORS.iter().map(|s| s.to_string()));
    for ax in &k.rotary {
        for n in 1..=INDEX_HARMONICS {
            for sine in [false, true] {
                out.push(index_name(&ax.name, n, sine));
            }
        }
    }
    out
}

/// The parameter values in the model's terms.
struct Values {
    state: MachineState,
    setup: Setup,
    /// The spindle-side object's drift, mm/min and mm/min^2.
    rate: Vec3,
    curve: Vec3,
    /// The location errors' drift per minute, in the state's own slots.
    loc_rate: [[f64; 5]; driftwatch_core::kinematics::MAX_ROTARY],
    /// Angular positioning harmonics: axis, harmonic, sine, rad.
    index: Vec<(usize, u32, bool, f64)>,
}

fn state_with(k: &Kinematics, params: &[Param], x: &[f64]) -> Values {
    let mut s = k.nominal_state();
    let mut setup = Setup::default();
    let mut rate = Vec3::zeros();
    let mut curve = Vec3::zeros();
    let mut loc_rate = [[0.0; 5]; driftwatch_core::kinematics::MAX_ROTARY];
    let mut index = Vec::new();
    for (p, v) in params.iter().zip(x) {
        match p {
            Param::Error(id) => s.loc[id.axis][id.slot] += v * id.scale(),
            Param::Table(j) => setup.table_object_mm[*j] += v * 1e-3,
            Param::Head(j) => setup.head_object_mm[*j] += v * 1e-3,
            Param::HeadRate(j) => rate[*j] += v * 1e-3,
            Param::HeadCurve(j) => curve[*j] += v * 1e-3,
            Param::ErrorRate(id) => loc_rate[id.axis][id.slot] += v * id.scale(),
            Param::Linear(i) => match i {
                0..=2 => s.linear.k[*i] += v * 1e-6,
                3 => s.linear.sxy += v * 1e-6,
                4 => s.linear.sxz += v * 1e-6,
                _ => s.linear.syz += v * 1e-6,
            },
            Param::Index {
                axis,
                harmonic,
                sine,
            } => index.push((*axis, *harmonic, *sine, v * 1e-6)),
        }
    }
    Values {
        state: s,
        setup,
        rate,
        curve,
        loc_rate,
        index,
    }
}

/// The model's deviations (um, table frame), the drift referred to `t_ref_ns`.
fn model(
    k: &Kinematics,
    runs: &[Processed],
    params: &[Param],
    x: &[f64],
    t_ref_ns: i64,
) -> Vec<Vec3> {
    let Values {
        state: s,
        setup,
        rate,
        curve,
        loc_rate,
        index,
    } = state_with(k, params, x);
    runs.iter()
        .flat_map(|r| {
            r.points
                .iter()
                .map(|d| {
                    let mut at = setup;
                    let dt_min = (d.t_ns - t_ref_ns) as f64 / 60e9;
                    at.head_object_mm += rate * dt_min + curve * (dt_min * dt_min);
                    let mut now = s;
                    for (a, r) in now.loc.iter_mut().zip(&loc_rate) {
                        for (v, dv) in a.iter_mut().zip(r) {
                            *v += dv * dt_min;
                        }
                    }
                    for (axis, n, sine, v) in &index {
                        let t = d.angles_deg[*axis].to_radians() * f64::from(*n);
                        now.angle_error[*axis] += v * if *sine { t.sin() } else { t.cos() };
                    }
                    deviation_table_um(k, &now, &d.angles_deg, &r.ball_mm, &at)
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

/// What a solve may estimate, in the order the rank test takes them (the table object
/// first, then the errors asked for, then the drifts).
fn candidates(k: &Kinematics, opts: &Options) -> Result<Vec<(Param, String)>, IdentifyError> {
    let names = if opts.errors.is_empty() {
        k.identify_names()
    } else {
        opts.errors.clone()
    };
    let mut candidates: Vec<(Param, String)> = (0..3)
        .map(|j| {
            (
                Param::Table(j),
                format!("table_object_{}", ["x", "y", "z"][j]),
            )
        })
        .collect();
    for n in &names {
        if let Some(i) = LINEAR_ERRORS.iter().position(|l| l == n) {
            candidates.push((Param::Linear(i), n.clone()));
            continue;
        }
        if let Some(p) = parse_index(k, n) {
            candidates.push((p, n.clone()));
            continue;
        }
        let id = k
            .error_id(n)
            .ok_or_else(|| IdentifyError::UnknownError(n.clone()))?;
        candidates.push((Param::Error(id), n.clone()));
    }
    if opts.drift_rates {
        for j in 0..3 {
            candidates.push((
                Param::HeadRate(j),
                format!("head_drift_{}_um_per_min", ["x", "y", "z"][j]),
            ));
        }
        for j in 0..3 {
            candidates.push((
                Param::HeadCurve(j),
                format!("head_drift_{}_um_per_min2", ["x", "y", "z"][j]),
            ));
        }
        for n in names
            .iter()
            .filter(|n| !LINEAR_ERRORS.contains(&n.as_str()) && parse_index(k, n).is_none())
        {
            if let Some(id) = k.error_id(n) {
                candidates.push((Param::ErrorRate(id), format!("{n}_per_min")));
            }
        }
    }
    Ok(candidates)
}

/// The whitened design (the model's Jacobian at the nominal, central differences) and the
/// whitened residual of the measurements from the nominal model.
fn whitened_design(
    k: &Kinematics,
    runs: &[Processed],
    all: &[Param],
    whiten: &[driftwatch_core::geometry::Mat3],
    t_ref_ns: i64,
) -> (DMatrix<f64>, DVector<f64>) {
    let zero = vec![0.0; all.len()];
    let base = model(k, runs, all, &zero, t_ref_ns);
    let n = base.len() * 3;
    let mut jac = DMatrix::zeros(n, all.len());
    for c in 0..all.len() {
        let mut xp = zero.clone();
        let mut xm = zero.clone();
        xp[c] = 1.0;
        xm[c] = -1.0;
        let (mp, mm) = (
            model(k, runs, all, &xp, t_ref_ns),
            model(k, runs, all, &xm, t_ref_ns),
        );
        for (i, w) in whiten.iter().enumerate() {
            let col = w * (mp[i] - mm[i]) / 2.0;
            for r in 0..3 {
                jac[(3 * i + r, c)] = col[r];
            }
        }
    }
    let meas = runs
        .iter()
        .flat_map(|r| r.points.iter().map(|d| d.table_um));
    let mut y = DVector::zeros(n);
    for (i, (m, w)) in meas.zip(whiten).enumerate() {
        let r = w * (m - base[i]);
        for j in 0..3 {
            y[3 * i + j] = r[j];
        }
    }
    (jac, y)
}

/// Keeps a candidate only if it raises the rank of the free part; names the others.
fn select(jac: &DMatrix<f64>, candidates: &[(Param, String)]) -> (Vec<usize>, Vec<String>) {
    let mut kept: Vec<usize> = Vec::new();
    let mut not_identifiable = Vec::new();
    for c in 0..candidates.len() {
        let mut trial = kept.clone();
        trial.push(c);
        if rank(jac, &trial) == trial.len() {
            kept = trial;
        } else {
            not_identifiable.push(tie_message(jac, &kept, c, candidates));
        }
    }
    (kept, not_identifiable)
}

/// The estimates by kind: errors (and their columns, for the correlation), the table
/// object's columns, the drifts.
struct Sorted {
    errors: BTreeMap<String, Estimate>,
    order: Vec<usize>,
    table: [usize; 3],
    drift: BTreeMap<String, Estimate>,
}

fn sort(
    cols: &[usize],
    all: &[Param],
    candidates: &[(Param, String)],
    est: &dyn Fn(usize, &'static str) -> Estimate,
) -> Sorted {
    let mut out = Sorted {
        errors: BTreeMap::new(),
        order: Vec::new(),
        table: [0; 3],
        drift: BTreeMap::new(),
    };
    for (j, &c) in cols.iter().enumerate() {
        let name = || candidates[c].1.clone();
        match all[c] {
            Param::Error(id) => {
                out.errors.insert(name(), est(j, id.unit()));
                out.order.push(j);
            }
            Param::Linear(i) => {
                out.errors
                    .insert(name(), est(j, if i < 3 { "ppm" } else { "urad" }));
                out.order.push(j);
            }
            Param::Index { .. } => {
                out.errors.insert(name(), est(j, "urad"));
                out.order.push(j);
            }
            Param::Table(t) => out.table[t] = j,
            Param::HeadRate(_) => {
                out.drift.insert(name(), est(j, "um/min"));
            }
            Param::HeadCurve(_) => {
                out.drift.insert(name(), est(j, "um/min^2"));
            }
            Param::ErrorRate(id) => {
                let unit = if id.is_position() {
                    "um/min"
                } else {
                    "urad/min"
                };
                out.drift.insert(name(), est(j, unit));
            }
            Param::Head(_) => {}
        }
    }
    out
}

/// Identifies location errors from one or more processed runs of one set-up (the same
/// table-side object for all).
pub fn identify(
    k: &Kinematics,
    runs: &[Processed],
    opts: &Options,
) -> Result<Identification, IdentifyError> {
    let candidates = candidates(k, opts)?;
    let heads: Vec<Param> = (0..3).map(Param::Head).collect();
    let obs: Vec<(&crate::process::Deviation, Vec3)> = runs
        .iter()
        .flat_map(|r| r.points.iter().map(|d| (d, d.table_um)))
        .collect();
    if obs.is_empty() {
        return Err(IdentifyError::Empty);
    }
    // Whitening: each deviation's covariance L L^T; rows L^-1.
    let mut whiten = Vec::with_capacity(obs.len());
    for (d, _) in &obs {
        let l = d.cov_table.cholesky().ok_or(IdentifyError::Covariance)?.l();
        whiten.push(l.try_inverse().ok_or(IdentifyError::Covariance)?);
    }
    let all: Vec<Param> = candidates
        .iter()
        .map(|c| c.0)
        .chain(heads.iter().copied())
        .collect();
    let t_ref_ns = {
        let ts: Vec<i64> = obs.iter().map(|(d, _)| d.t_ns).collect();
        driftwatch_core::identify::mean_time_ns(ts.iter().copied())
    };
    let (jac, y) = whitened_design(k, runs, &all, &whiten, t_ref_ns);
    let n = y.len();
    let (kept, not_identifiable) = select(&jac, &candidates);
    // The head object: three more columns, each with its prior as one more row.
    let head_cols: Vec<usize> = (candidates.len()..all.len()).collect();
    let cols: Vec<usize> = kept.iter().copied().chain(head_cols.clone()).collect();
    let m = cols.len();
    let mut a = DMatrix::zeros(n + 3, m);
    let mut b = DVector::zeros(n + 3);
    for (j, &c) in cols.iter().enumerate() {
        a.view_mut((0, j), (n, 1)).copy_from(&jac.column(c));
    }
    b.rows_mut(0, n).copy_from(&y);
    let prior = opts.head_sigma_um.max(1e-6);
    for (r, &hc) in head_cols.iter().enumerate() {
        let j = cols.iter().position(|&c| c == hc).unwrap_or(0);
        a[(n + r, j)] = 1.0 / prior;
    }
    // The kept columns have full rank (`select`) and the head's columns their priors' rows, so
    // the design has full rank; one that does not is refused, as the inverse refused it.
    let fit = lsq(&a, &b);
    if fit.rank < m {
        return Err(IdentifyError::Singular);
    }
    let (x, cov_random) = (fit.beta, fit.cov);
    let (cal_cov, cal_chi2) = calibration_cov(runs, &whiten, &cov_random, &a, n);
    let (form_cov, form_chi2) = form_cov(runs, &whiten, &cov_random, &a);
    let systematic = cal_cov + form_cov;
    let resid = &b - &a * &x;
    let chi2_data = resid.rows(0, n).norm_squared();
    let dof = n.saturating_sub(kept.len()).max(1);
    // What chi-square the noise and the propagated systematics explain together.
    let expected_chi2 = dof as f64 + cal_chi2 + form_chi2;
    let birge = (chi2_data / expected_chi2).sqrt().max(1.0);
    // The scatter scales the readings' noise; the systematic parts are what they are.
    let cov = cov_random * (birge * birge) + systematic;
    // Residuals in um: the exact model at the solution.
    let mut xfull = vec![0.0; all.len()];
    for (j, &c) in cols.iter().enumerate() {
        xfull[c] = x[j];
    }
    let fitted = model(k, runs, &all, &xfull, t_ref_ns);
    let rms = (obs
        .iter()
        .zip(&fitted)
        .map(|((_, m), f)| (m - f).norm_squared())
        .sum::<f64>()
        / n as f64)
        .sqrt();
    let est = |j: usize, unit: &'static str| Estimate {
        value: x[j],
        sigma: cov[(j, j)].sqrt(),
        unit,
    };
    let sorted = sort(&cols, &all, &candidates, &est);
    let (errors, order, table, drift) = (sorted.errors, sorted.order, sorted.table, sorted.drift);
    let head_j = |h: usize| cols.len() - 3 + h;
    let correlation = order
        .iter()
        .map(|&i| {
            order
                .iter()
                .map(|&j| cov[(i, j)] / (cov[(i, i)] * cov[(j, j)]).sqrt())
                .collect()
        })
        .collect();
    let all_table_kept = (0..3).all(|t| kept.contains(&t));
    Ok(Identification {
        machine: k.name.clone(),
        t_ns: t_ref_ns,
        drift,
        tests: runs
            .iter()
            .map(|r| format!("{} ({})", r.test, r.setting.name()))
            .collect(),
        errors,
        table_object_um: [0, 1, 2].map(|t| {
            if all_table_kept {
                est(table[t], "um")
            } else {
                Estimate {
                    value: f64::NAN,
                    sigma: f64::NAN,
                    unit: "um",
                }
            }
        }),
        head_object_um: [0, 1, 2].map(|h| est(head_j(h), "um")),
        not_identifiable,
        n_readings: obs.len(),
        chi2: chi2_data,
        dof,
        birge,
        residual_rms_um: rms,
        correlation,
    })
}

/// The calibration's systematic part: a change `dG` of the sensitivity matrix moves every
/// displacement read with it by `-G^-1 dG d`; its effect on the estimates through the
/// least-squares operator, over each row's covariance (one `G` per set-up: runs of the same
/// setting share it).
fn calibration_cov(
    runs: &[Processed],
    whiten: &[driftwatch_core::geometry::Mat3],
    cov: &DMatrix<f64>,
    a: &DMatrix<f64>,
    n: usize,
) -> (DMatrix<f64>, f64) {
    let m = cov.nrows();
    let mut out = DMatrix::zeros(m, m);
    let mut chi2 = 0.0;
    let op = cov * a.transpose();
    let mut groups: Vec<crate::instrument::Setting> = runs.iter().map(|r| r.setting).collect();
    groups.dedup();
    for setting in groups {
        for row in 0..3 {
            // Sensitivity of the estimates to the three elements of this row of G, and what
            // the fit leaves of their effect on the readings.
            let mut s = DMatrix::zeros(m, 3);
            let mut residual = DMatrix::zeros(a.nrows(), 3);
            for col in 0..3 {
                let mut dy = DVector::zeros(a.nrows());
                let mut i = 0;
                for r in runs {
                    for d in &r.points {
                        if r.setting == setting {
                            let mut e = driftwatch_core::geometry::Mat3::zeros();
                            e[(row, col)] = 1.0;
                            let moved = d.nest_to_table * (-(r.g_inv * e * d.nest_um));
                            let w = whiten[i] * moved;
                            for j in 0..3 {
                                dy[3 * i + j] = w[j];
                            }
                        }
                        i += 1;
                    }
                }
                debug_assert!(i * 3 == n);
                let shift = &op * &dy;
                residual.set_column(col, &(&dy - a * &shift));
                s.set_column(col, &shift);
            }
            let row_cov = runs
                .iter()
                .find(|r| r.setting == setting)
                .map(|r| r.g_row_cov)
                .unwrap_or_default();
            let rc = DMatrix::from_fn(3, 3, |i, j| row_cov[(i, j)]);
            out += &s * &rc * s.transpose();
            chi2 += (residual.transpose() * &residual * rc).trace();
        }
    }
    (out, chi2)
}

/// The ball's form, systematic: one ball for every run, its radius deviation spanned by
/// [`crate::instrument::form_basis`] with independent coefficients of the spread its
/// sphericity implies; each coefficient moves every reading by its value at the contact now
/// minus at the zero.
fn form_cov(
    runs: &[Processed],
    whiten: &[driftwatch_core::geometry::Mat3],
    cov: &DMatrix<f64>,
    a: &DMatrix<f64>,
) -> (DMatrix<f64>, f64) {
    let m = cov.nrows();
    let sphericity = runs.iter().map(|r| r.sphericity_um).fold(0.0, f64::max);
    let sd = crate::instrument::form_coefficient_sd(sphericity);
    if sd == 0.0 {
        return (DMatrix::zeros(m, m), 0.0);
    }
    let op = cov * a.transpose();
    let mut s = DMatrix::zeros(m, 16);
    let mut dy = DMatrix::zeros(a.nrows(), 16);
    let mut i = 0;
    for r in runs {
        for d in &r.points {
            let mut dr = [[0.0; 16]; 3];
            for (k, (now, zero)) in d.contacts.iter().enumerate() {
                let (bn, bz) = (
                    crate::instrument::form_basis(now),
                    crate::instrument::form_basis(zero),
                );
                for f in 0..16 {
                    dr[k][f] = bn[f] - bz[f];
                }
            }
            for f in 0..16 {
                let moved = d.nest_to_table
                    * (r.g_inv
                        * driftwatch_core::geometry::Vec3::new(dr[0][f], dr[1][f], dr[2][f]));
                let w = whiten[i] * moved;
                for j in 0..3 {
                    dy[(3 * i + j, f)] = w[j];
                }
            }
            i += 1;
        }
    }
    s.copy_from(&(&op * &dy));
    let residual = &dy - a * &s;
    (
        &s * s.transpose() * (sd * sd),
        residual.norm_squared() * sd * sd,
    )
}

/// The rank of the columns `cols` of `jac`, scaled to unit norm (so that the rank test does
/// not depend on units): singular values above 1e-6 of the largest.
fn rank(jac: &DMatrix<f64>, cols: &[usize]) -> usize {
    if cols.is_empty() {
        return 0;
    }
    lsq_with_tol(
        &jac.select_columns(cols),
        &DVector::zeros(jac.nrows()),
        1e-6,
    )
    .rank
}

/// "EC0C: not separable from table_object_x (-1.00), ..." from the least-squares fit of the
/// dropped column on the kept ones.
fn tie_message(
    jac: &DMatrix<f64>,
    kept: &[usize],
    c: usize,
    candidates: &[(Param, String)],
) -> String {
    let name = &candidates[c].1;
    let col = jac.column(c).into_owned();
    if col.norm() < 1e-12 || kept.is_empty() {
        return format!("{name}: these tests do not see it at all");
    }
    let sub = DMatrix::from_columns(&kept.iter().map(|&k| jac.column(k)).collect::<Vec<_>>());
    // The kept columns have full rank (`select`), so the fit is unique.
    let coef = lsq(&sub, &col).beta;
    let ties: Vec<String> = kept
        .iter()
        .zip(coef.iter())
        .filter(|(_, v)| v.abs() > 0.05)
        .map(|(&k, v)| format!("{} ({v:+.2})", candidates[k].1))
        .collect();
    format!(
        "{name}: not separable from {} (its signature is their combination)",
        ties.join(", ")
    )
}
