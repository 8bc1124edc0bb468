//! Identification of the location errors from the detections of one cycle: Gauss-Newton
//! weighted least squares on the exact measurement model, with the nuisance parameters the
//! plan can support, standard uncertainties from the covariance, per-detection residuals, the
//! redundancy residuals and their chi-square, optional Huber weighting, and a structural
//! identifiability check that names what a plan cannot separate.
//!
//! Parameters are in um, urad and um/min; the model works in mm and rad.

use crate::units;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;
use thiserror::Error;

use crate::geometry::{Vec3, wrap_deg};
use crate::kinematics::PoseGeometry;
use crate::kinematics::{ErrorId, Kinematics, MAX_ROTARY, MachineState};
use crate::least_squares::{lsq, lsq_with_tol, redundant_part};
use crate::measurement::{Approach, Axis, NoTrip, latched_at};

/// One detection as the solver sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    pub label: String,
    pub angles: [f64; MAX_ROTARY],
    pub approach: Approach,
    /// The latched commanded position, mm; the moving coordinate is the reading.
    pub position: Vec3,
    pub t_ns: i64,
}

impl Observation {
    pub fn reading(&self) -> f64 {
        self.position[self.approach.axis.index()]
    }
}

/// What the solver may estimate besides the identified location errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Nuisance {
    /// Beam height above its configured place (table frame), um.
    SetterHeight,
    /// Beam shift across the beam, horizontally (along table Z x beam direction), um.
    SetterLateral,
    /// Effective radius minus feed x latency of lateral approaches, against its calibration, um.
    Radius,
    /// Tool-tip drift rate along a machine axis during the cycle, um/min.
    DriftRate(Axis),
}

impl Nuisance {
    pub fn name(&self) -> String {
        match self {
            Nuisance::SetterHeight => "setter_height_um".into(),
            Nuisance::SetterLateral => "setter_lateral_um".into(),
            Nuisance::Radius => "radius_minus_latency_um".into(),
            Nuisance::DriftRate(a) => format!("tool_drift_{}_um_per_min", a.name()),
        }
    }
    fn unit(&self) -> &'static str {
        match self {
            Nuisance::DriftRate(_) => "um/min",
            _ => "um",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Param {
    Location(ErrorId),
    Nuisance(Nuisance),
}

#[derive(Debug, Clone, PartialEq)]
pub struct SolveOptions {
    /// One-reading standard uncertainty, um.
    pub sigma_um: f64,
    /// Huber threshold in units of sigma (1.5 is usual); `None` for plain LS.
    pub huber_k: Option<f64>,
    /// Nuisance parameters to estimate where the plan supports them, in priority order.
    pub nuisance: Vec<Nuisance>,
    /// Tool-tip drift rates within the cycle (event-level use of the timestamps).
    pub drift_rates: DriftRates,
    pub max_iterations: usize,
}

/// When to estimate the tool-tip drift rates of a cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DriftRates {
    /// Where the plan separates them from the location errors: no identified error's
    /// uncertainty grows by more than 10 % (a time-symmetric plan).
    Auto,
    /// Wherever the plan can determine them at all.
    Always,
    Never,
}

/// Largest growth of an identified error's uncertainty that `DriftRates::Auto` accepts.
const MAX_INFLATION: f64 = 0.10;

impl SolveOptions {
    pub fn new(sigma_um: f64) -> Self {
        SolveOptions {
            sigma_um,
            huber_k: None,
            nuisance: vec![
                Nuisance::SetterHeight,
                Nuisance::SetterLateral,
                Nuisance::Radius,
            ],
            drift_rates: DriftRates::Auto,
            max_iterations: 30,
        }
    }

    /// Estimate the tool-tip drift rates wherever the plan determines them.
    pub fn with_drift_rates(mut self) -> Self {
        self.drift_rates = DriftRates::Always;
        self
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum SolveError {
    #[error("{n} detections cannot determine {p} parameters")]
    TooFew { n: usize, p: usize },
    #[error("the plan cannot separate {}{}", .combinations.join("; "), hint_text(.hint))]
    NotIdentifiable {
        combinations: Vec<String>,
        hint: Option<String>,
    },
    #[error("detection '{label}': the model finds no trip ({reason})")]
    NoTrip { label: String, reason: NoTrip },
    #[error("detection '{label}': {what} is not a finite number")]
    NonFinite { label: String, what: String },
    #[error("the solution did not converge in {iterations} iterations (last step {step:.3e})")]
    NotConverged { iterations: usize, step: f64 },
    #[error("sigma_um must be a positive number")]
    BadSigma,
}

fn hint_text(h: &Option<String>) -> String {
    h.as_ref().map(|h| format!(" ({h})")).unwrap_or_default()
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Estimate {
    pub name: String,
    pub unit: String,
    pub value: f64,
    pub sigma: f64,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Held {
    pub name: String,
    pub reason: String,
}

#[derive(Debug, Clone, Serialize)]
pub struct Solution {
    /// The identified location errors, in the machine's report order.
    pub errors: Vec<Estimate>,
    pub nuisance: Vec<Estimate>,
    /// Nuisance parameters held at their configured value, with why.
    pub held: Vec<Held>,
    /// Measured minus model, per detection in input order, um.
    pub residuals_um: Vec<f64>,
    /// Huber weight factor per detection (1 = full weight).
    pub weights: Vec<f64>,
    /// Residuals projected on an orthonormal basis of the left null space of the
    /// sensitivity matrix: free of every estimated parameter, um.
    pub redundancy_um: Vec<f64>,
    pub chi2: f64,
    pub dof: usize,
    pub iterations: usize,
    /// Reference time: mean of the detection timestamps, ns.
    pub t_ref_ns: i64,
    #[serde(skip)]
    pub covariance: DMatrix<f64>,
}

impl Solution {
    pub fn error(&self, name: &str) -> Option<&Estimate> {
        self.errors.iter().find(|e| e.name == name)
    }
    pub fn residual_rms_um(&self) -> f64 {
        let n = self.residuals_um.len().max(1) as f64;
        (self.residuals_um.iter().map(|r| r * r).sum::<f64>() / n).sqrt()
    }
}

/// Mean of timestamps without overflow.
pub fn mean_time_ns(ts: impl Iterator<Item = i64> + Clone) -> i64 {
    let Some(t0) = ts.clone().next() else {
        return 0;
    };
    let (sum, n) = ts.fold((0.0f64, 0usize), |(s, n), t| (s + (t - t0) as f64, n + 1));
    t0 + (sum / n as f64).round() as i64
}

/// The linear measurement model of a set of observations around the nominal state.
#[derive(Debug, Clone, PartialEq)]
pub struct Design {
    /// Parameter names, in column order (errors in um or urad, nuisances in their units).
    pub params: Vec<String>,
    /// Each reading at the nominal state, mm.
    pub nominal_mm: Vec<f64>,
    /// Reading change per parameter unit, um: one row per observation.
    pub sensitivity_um: DMatrix<f64>,
}

/// A solver prepared for one set of observation geometries (a plan): the parameters it
/// estimates and the sensitivity matrix at the nominal state.
pub struct Identifier<'a> {
    k: &'a Kinematics,
    base: MachineState,
    params: Vec<Param>,
    held: Vec<Held>,
    opts: SolveOptions,
    lateral_normal: Vec3,
    /// Step sizes for finite differences, per parameter.
    steps: Vec<f64>,
    /// Sensitivities at the nominal state for the template geometry, and that geometry.
    j0: DMatrix<f64>,
    geometry: Vec<([f64; MAX_ROTARY], Approach)>,
}

const RANK_TOL: f64 = 1e-6;

impl<'a> Identifier<'a> {
    pub fn new(
        k: &'a Kinematics,
        template: &[Observation],
        opts: &SolveOptions,
    ) -> Result<Self, SolveError> {
        if !(opts.sigma_um > 0.0 && opts.sigma_um.is_finite()) {
            return Err(SolveError::BadSigma);
        }
        check_finite(template)?;
        let base = k.nominal_state();
        let mut lateral_normal = Vec3::z().cross(&base.beam_dir);
        if lateral_normal.norm() < 1e-9 {
            lateral_normal = Vec3::x();
        }
        lateral_normal /= lateral_normal.norm();
        let mut me = Identifier {
            k,
            base,
            params: k.identify.iter().map(|id| Param::Location(*id)).collect(),
            held: Vec::new(),
            opts: opts.clone(),
            lateral_normal,
            steps: Vec::new(),
            j0: DMatrix::zeros(0, 0),
            geometry: template.iter().map(|o| (o.angles, o.approach)).collect(),
        };
        me.steps = me.params.iter().map(|_| 1e-3).collect();
        let t_ref = mean_time_ns(template.iter().map(|o| o.t_ns));
        let n = template.len();
        if n < me.params.len() {
            return Err(SolveError::TooFew {
                n,
                p: me.params.len(),
            });
        }
        // A column at the nominal state depends on its own parameter only (every other one is
        // zero, and a zero adds nothing): each is computed once as parameters are tried, and
        // the matrices below are put together from them.
        let mut cols = (0..me.params.len())
            .map(|c| me.central_column(template, &vec![0.0; me.params.len()], c, t_ref))
            .collect::<Result<Vec<_>, _>>()?;
        let matrix = |cols: &[Vec<f64>]| DMatrix::from_fn(n, cols.len(), |r, c| cols[c][r]);
        let j = matrix(&cols);
        let null = null_combinations(&j, &me.param_names());
        if !null.is_empty() {
            return Err(SolveError::NotIdentifiable {
                combinations: null,
                hint: identifiability_hint(k, template),
            });
        }
        let rates: Vec<Nuisance> = match opts.drift_rates {
            DriftRates::Never => Vec::new(),
            _ => [Axis::X, Axis::Y, Axis::Z]
                .into_iter()
                .filter(|a| template.iter().any(|o| o.approach.axis == *a))
                .map(Nuisance::DriftRate)
                .collect(),
        };
        let n_loc = me.params.len();
        let mut baseline: Option<Vec<f64>> = None;
        for nu in opts.nuisance.iter().chain(&rates) {
            let is_rate = matches!(nu, Nuisance::DriftRate(_));
            if is_rate && baseline.is_none() {
                baseline = Some(variances(&matrix(&cols), n_loc));
            }
            me.params.push(Param::Nuisance(*nu));
            me.steps.push(1e-3);
            let last = me.params.len() - 1;
            cols.push(me.central_column(template, &vec![0.0; me.params.len()], last, t_ref)?);
            let j = matrix(&cols);
            let null = if me.params.len() > n {
                vec!["more parameters than detections".to_string()]
            } else {
                null_combinations(&j, &me.param_names())
            };
            let mut reason = (!null.is_empty()).then(|| {
                format!(
                    "held at its configured value: the plan cannot separate {}",
                    null.join("; ")
                )
            });
            if reason.is_none()
                && is_rate
                && opts.drift_rates == DriftRates::Auto
                && let Some(base) = &baseline
            {
                let now = variances(&j, n_loc);
                let (worst, growth) = now
                    .iter()
                    .zip(base)
                    .enumerate()
                    .map(|(i, (a, b))| (i, (a / b).sqrt() - 1.0))
                    .fold((0, 0.0), |acc, x| if x.1 > acc.1 { x } else { acc });
                if growth > MAX_INFLATION {
                    reason = Some(format!(
                        "not estimated: with this plan's timing it would raise the uncertainty of {} by {:.0} % (a time-symmetric plan separates drift from the errors)",
                        me.param_names()[worst],
                        growth * 100.0
                    ));
                }
            }
            if let Some(reason) = reason {
                me.params.pop();
                me.steps.pop();
                cols.pop();
                me.held.push(Held {
                    name: nu.name(),
                    reason,
                });
            }
        }
        me.j0 = matrix(&cols);
        Ok(me)
    }

    /// Sensitivities at the nominal state: cached for the template geometry, with the drift
    /// columns (which depend on the times) written for these observations.
    fn initial_jacobian(
        &self,
        obs: &[Observation],
        t_ref: i64,
    ) -> Result<DMatrix<f64>, SolveError> {
        let same = obs.len() == self.geometry.len()
            && obs
                .iter()
                .zip(&self.geometry)
                .all(|(o, (a, ap))| same_angles(&o.angles, a) && o.approach == *ap);
        if !same {
            return self.jacobian_central(obs, &vec![0.0; self.params.len()], t_ref);
        }
        let mut j = self.j0.clone();
        for (c, param) in self.params.iter().enumerate() {
            if let Param::Nuisance(Nuisance::DriftRate(a)) = param {
                for (r, o) in obs.iter().enumerate() {
                    j[(r, c)] = if o.approach.axis == *a {
                        -units::ns_to_min(o.t_ns - t_ref)
                    } else {
                        0.0
                    };
                }
            }
        }
        Ok(j)
    }

    fn param_names(&self) -> Vec<String> {
        self.params
            .iter()
            .map(|p| match p {
                Param::Location(id) => self.k.error_name(*id).to_string(),
                Param::Nuisance(n) => n.name(),
            })
            .collect()
    }

    /// The model state for parameter values `p`.
    fn state(&self, p: &[f64]) -> MachineState {
        let mut s = self.base;
        for (param, v) in self.params.iter().zip(p) {
            match param {
                Param::Location(id) => s.loc[id.axis][id.slot] += v * id.scale(),
                Param::Nuisance(Nuisance::SetterHeight) => s.beam_point.z += v * 1e-3,
                Param::Nuisance(Nuisance::SetterLateral) => {
                    s.beam_point += self.lateral_normal * (v * 1e-3)
                }
                Param::Nuisance(Nuisance::Radius) => s.radius += v * 1e-3,
                Param::Nuisance(Nuisance::DriftRate(_)) => {}
            }
        }
        s
    }

    /// Model readings (mm) of all observations.
    fn predict(&self, obs: &[Observation], p: &[f64], t_ref: i64) -> Result<Vec<f64>, SolveError> {
        let s = self.state(p);
        let lines = self.k.lines(&s);
        let mut cache: Vec<([f64; MAX_ROTARY], PoseGeometry)> = Vec::with_capacity(8);
        let mut out = Vec::with_capacity(obs.len());
        for o in obs {
            let pose = match cache.iter().find(|(a, _)| same_angles(a, &o.angles)) {
                Some((_, g)) => *g,
                None => {
                    let g = self.k.pose_geometry_on(&lines, &s, &o.angles);
                    cache.push((o.angles, g));
                    g
                }
            };
            let mut v =
                latched_at(&s, &pose, &o.approach, &o.position, None).map_err(|reason| {
                    SolveError::NoTrip {
                        label: o.label.clone(),
                        reason,
                    }
                })?;
            let dt_min = units::ns_to_min(o.t_ns - t_ref);
            for (param, val) in self.params.iter().zip(p) {
                if let Param::Nuisance(Nuisance::DriftRate(a)) = param
                    && *a == o.approach.axis
                {
                    v -= val * 1e-3 * dt_min;
                }
            }
            out.push(v);
        }
        Ok(out)
    }

    /// Sensitivities, um (of reading) per parameter unit, by central differences.
    fn jacobian_central(
        &self,
        obs: &[Observation],
        p: &[f64],
        t_ref: i64,
    ) -> Result<DMatrix<f64>, SolveError> {
        let mut j = DMatrix::zeros(obs.len(), p.len());
        for c in 0..p.len() {
            for (r, v) in self
                .central_column(obs, p, c, t_ref)?
                .into_iter()
                .enumerate()
            {
                j[(r, c)] = v;
            }
        }
        Ok(j)
    }

    /// Column `c` of [`Self::jacobian_central`]: the readings' sensitivity to parameter `c`.
    fn central_column(
        &self,
        obs: &[Observation],
        p: &[f64],
        c: usize,
        t_ref: i64,
    ) -> Result<Vec<f64>, SolveError> {
        let h = self.steps[c];
        let mut q = p.to_vec();
        q[c] = p[c] + h;
        let up = self.predict(obs, &q, t_ref)?;
        q[c] = p[c] - h;
        let dn = self.predict(obs, &q, t_ref)?;
        Ok(up
            .iter()
            .zip(&dn)
            .map(|(u, d)| (u - d) * 1e3 / (2.0 * h))
            .collect())
    }

    /// Forward differences around known model readings `f0`.
    fn jacobian_forward(
        &self,
        obs: &[Observation],
        p: &[f64],
        f0: &[f64],
        t_ref: i64,
    ) -> Result<DMatrix<f64>, SolveError> {
        let mut j = DMatrix::zeros(obs.len(), p.len());
        let mut q = p.to_vec();
        for c in 0..p.len() {
            let h = self.steps[c];
            q[c] = p[c] + h;
            let up = self.predict(obs, &q, t_ref)?;
            q[c] = p[c];
            for r in 0..obs.len() {
                j[(r, c)] = (up[r] - f0[r]) * 1e3 / h;
            }
        }
        Ok(j)
    }

    /// The linear measurement model around the nominal state for `obs`: each reading's
    /// nominal value and its sensitivity to every parameter this identifier estimates. The
    /// diagnosis fits time-varying parameters through it, one detection at a time. Lateral
    /// readings are linear in the errors; a z approach under a beam tilted across it trips at
    /// the edge of the tool's end face, `r |tilt|` higher, which no linear model has at zero
    /// (0.06 um for 12 urad under a 10-mm tool).
    pub fn nominal_design(&self, obs: &[Observation]) -> Result<Design, SolveError> {
        check_finite(obs)?;
        let t_ref = mean_time_ns(obs.iter().map(|o| o.t_ns));
        let zero = vec![0.0; self.params.len()];
        Ok(Design {
            params: self.param_names(),
            nominal_mm: self.predict(obs, &zero, t_ref)?,
            sensitivity_um: self.jacobian_central(obs, &zero, t_ref)?,
        })
    }

    /// Cramer-Rao standard deviations of the estimated parameters for this geometry, at the
    /// nominal state: `sigma * sqrt(diag((J^T J)^-1))`.
    pub fn cramer_rao(&self, template: &[Observation]) -> Result<Vec<Estimate>, SolveError> {
        let t_ref = mean_time_ns(template.iter().map(|o| o.t_ns));
        let zero = vec![0.0; self.params.len()];
        let j = self.jacobian_central(template, &zero, t_ref)?;
        let cov = covariance(&j, self.opts.sigma_um);
        Ok(self.estimates(&zero, &cov).into_iter().flatten().collect())
    }

    fn estimates(&self, p: &[f64], cov: &DMatrix<f64>) -> [Vec<Estimate>; 2] {
        let mut errors = Vec::new();
        let mut nuisance = Vec::new();
        for (i, param) in self.params.iter().enumerate() {
            let sigma = cov[(i, i)].max(0.0).sqrt();
            match param {
                Param::Location(id) => errors.push(Estimate {
                    name: self.k.error_name(*id).to_string(),
                    unit: id.unit().into(),
                    value: p[i],
                    sigma,
                }),
                Param::Nuisance(n) => nuisance.push(Estimate {
                    name: n.name(),
                    unit: n.unit().into(),
                    value: p[i],
                    sigma,
                }),
            }
        }
        [errors, nuisance]
    }

    /// Solve one cycle. The observations must have the geometry of the template (same poses
    /// and approaches); values and times are free.
    pub fn solve(&self, obs: &[Observation]) -> Result<Solution, SolveError> {
        check_finite(obs)?;
        let n = obs.len();
        let np = self.params.len();
        if n < np {
            return Err(SolveError::TooFew { n, p: np });
        }
        let t_ref = mean_time_ns(obs.iter().map(|o| o.t_ns));
        let sigma = self.opts.sigma_um;
        let m: Vec<f64> = obs.iter().map(|o| o.reading()).collect();
        let mut p = vec![0.0; np];
        let mut weights = vec![1.0; n];
        let mut iterations = 0;
        // Chord iterations on the sensitivities at the nominal state while far from the
        // solution; fresh sensitivities near it, so that the fixed point is the least-squares
        // solution of the exact model.
        let mut j = self.initial_jacobian(obs, t_ref)?;
        let mut j_at = p.clone();
        let mut f = self.predict(obs, &p, t_ref)?;
        let cost = |f: &[f64], w: &[f64]| -> f64 {
            m.iter()
                .zip(f)
                .zip(w)
                .map(|((mi, fi), wi)| wi * ((mi - fi) * 1e3 / sigma).powi(2))
                .sum()
        };
        let distance = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max)
        };
        loop {
            let mut last_step = f64::INFINITY;
            let mut converged = false;
            let mut c = cost(&f, &weights);
            for _ in 0..self.opts.max_iterations {
                iterations += 1;
                // Sensitivities taken within 0.1 (um, urad) of the solution change by well
                // under 1 %, so the fixed point moves by under 1 % of the residual-driven
                // displacement: negligible against sigma, and nothing without noise.
                let fresh = distance(&p, &j_at) < 0.1;
                let step = gn_step(&j, &m, &f, &weights, sigma);
                last_step = step.amax();
                if last_step < 1e-6 && fresh {
                    converged = true;
                    break;
                }
                // Halve the step while the cost rises.
                let mut scale = 1.0;
                let mut accepted = None;
                while scale >= 1e-4 {
                    let p_new: Vec<f64> = p
                        .iter()
                        .zip(step.iter())
                        .map(|(a, d)| a + scale * d)
                        .collect();
                    let f_new = self.predict(obs, &p_new, t_ref)?;
                    let c_new = cost(&f_new, &weights);
                    if c_new <= c {
                        accepted = Some((p_new, f_new, c_new));
                        break;
                    }
                    scale *= 0.5;
                }
                let refresh = match accepted {
                    Some((p_new, f_new, c_new)) => {
                        let gain = c - c_new;
                        p = p_new;
                        f = f_new;
                        c = c_new;
                        if fresh && scale * last_step < 1e-3 && gain <= 1e-10 * c.max(1.0) {
                            // Stalled on the rounded corner of a beam slope through zero.
                            converged = true;
                            break;
                        }
                        scale * last_step < 0.1
                    }
                    None if fresh => {
                        converged = last_step < 1e-3;
                        break;
                    }
                    None => {
                        j_at = vec![f64::INFINITY; np];
                        true
                    }
                };
                if refresh && distance(&p, &j_at) >= 0.1 {
                    j = self.jacobian_forward(obs, &p, &f, t_ref)?;
                    j_at = p.clone();
                }
            }
            if !converged {
                return Err(SolveError::NotConverged {
                    iterations,
                    step: last_step,
                });
            }
            let Some(k) = self.opts.huber_k else { break };
            let new_w: Vec<f64> = m
                .iter()
                .zip(&f)
                .map(|(mi, fi)| {
                    let a = ((mi - fi) * 1e3 / sigma).abs();
                    if a <= k { 1.0 } else { k / a }
                })
                .collect();
            let change = new_w
                .iter()
                .zip(&weights)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            weights = new_w;
            if change < 1e-6 || iterations > 20 * self.opts.max_iterations {
                break;
            }
        }
        let residuals_um: Vec<f64> = m.iter().zip(&f).map(|(a, b)| (a - b) * 1e3).collect();
        let wj = weighted(&j, &weights, sigma);
        let cov = covariance_from_weighted(&wj);
        let chi2 = residuals_um.iter().map(|r| (r / sigma).powi(2)).sum();
        let redundancy_um = redundancy(&weighted(&j, &vec![1.0; n], sigma), &residuals_um, sigma);
        let [errors, nuisance] = self.estimates(&p, &cov);
        Ok(Solution {
            errors,
            nuisance,
            held: self.held.clone(),
            residuals_um,
            weights,
            redundancy_um,
            chi2,
            dof: n - np,
            iterations,
            t_ref_ns: t_ref,
            covariance: cov,
        })
    }
}

/// Solve one cycle from scratch.
pub fn identify(
    k: &Kinematics,
    obs: &[Observation],
    opts: &SolveOptions,
) -> Result<Solution, SolveError> {
    Identifier::new(k, obs, opts)?.solve(obs)
}

fn same_angles(a: &[f64; MAX_ROTARY], b: &[f64; MAX_ROTARY]) -> bool {
    a == b || a.iter().zip(b).all(|(x, y)| wrap_deg(x - y).abs() < 1e-12)
}

fn check_finite(obs: &[Observation]) -> Result<(), SolveError> {
    for o in obs {
        let bad = |what: &str| SolveError::NonFinite {
            label: o.label.clone(),
            what: what.to_string(),
        };
        if o.angles.iter().any(|a| !a.is_finite()) {
            return Err(bad("an axis angle"));
        }
        for (i, c) in ["x_mm", "y_mm", "z_mm"].iter().enumerate() {
            if !o.position[i].is_finite() {
                return Err(bad(c));
            }
        }
        if !o.approach.feed_mm_min.is_finite() {
            return Err(bad("feed_mm_min"));
        }
    }
    Ok(())
}

fn weighted(j: &DMatrix<f64>, w: &[f64], sigma: f64) -> DMatrix<f64> {
    let mut wj = j.clone();
    for (r, wr) in w.iter().enumerate() {
        let s = wr.sqrt() / sigma;
        wj.row_mut(r).scale_mut(s);
    }
    wj
}

/// The Gauss-Newton step: the weighted least-squares solution of `J d = m - f`.
fn gn_step(j: &DMatrix<f64>, m: &[f64], f: &[f64], w: &[f64], sigma: f64) -> DVector<f64> {
    let wj = weighted(j, w, sigma);
    let rw = DVector::from_iterator(
        m.len(),
        m.iter()
            .zip(f)
            .zip(w)
            .map(|((mi, fi), wi)| (mi - fi) * 1e3 * wi.sqrt() / sigma),
    );
    lsq(&wj, &rw).beta
}

/// `(J^T W J)^-1` from the weighted sensitivities; NaN where the design is rank deficient
/// (the constructor has already refused such a plan).
fn covariance_from_weighted(wj: &DMatrix<f64>) -> DMatrix<f64> {
    let (n, p) = (wj.nrows(), wj.ncols());
    let f = lsq(wj, &DVector::zeros(n));
    if f.rank < p {
        return DMatrix::from_element(p, p, f64::NAN);
    }
    f.cov
}

fn covariance(j: &DMatrix<f64>, sigma: f64) -> DMatrix<f64> {
    covariance_from_weighted(&weighted(j, &vec![1.0; j.nrows()], sigma))
}

/// Variances (up to sigma^2) of the first `k` parameters for sensitivities `j`.
fn variances(j: &DMatrix<f64>, k: usize) -> Vec<f64> {
    let f = lsq(j, &DVector::zeros(j.nrows()));
    if f.rank < j.ncols() {
        return vec![f64::INFINITY; k];
    }
    (0..k).map(|i| f.cov[(i, i)]).collect()
}

/// Components of the residuals in the left null space of the (weighted) sensitivity matrix.
fn redundancy(wj: &DMatrix<f64>, residuals_um: &[f64], sigma: f64) -> Vec<f64> {
    let v = DVector::from_iterator(wj.nrows(), residuals_um.iter().map(|r| r / sigma));
    redundant_part(wj, &v).iter().map(|x| x * sigma).collect()
}

/// The parameter combinations the sensitivity matrix cannot see, in words.
fn null_combinations(j: &DMatrix<f64>, names: &[String]) -> Vec<String> {
    let norms: Vec<f64> = (0..j.ncols()).map(|c| j.column(c).norm()).collect();
    let mut out = Vec::new();
    let live: Vec<usize> = (0..j.ncols()).filter(|c| norms[*c] >= 1e-12).collect();
    for (c, nrm) in norms.iter().enumerate() {
        if *nrm < 1e-12 {
            out.push(format!("{} (no reading depends on it)", names[c]));
        }
    }
    if live.is_empty() {
        return out;
    }
    let names: Vec<String> = live.iter().map(|c| names[*c].clone()).collect();
    let jl = j.select_columns(&live);
    let fit = lsq_with_tol(&jl, &DVector::zeros(j.nrows()), RANK_TOL);
    for tie in &fit.ties {
        // In physical units, largest component 1.
        let big = tie.amax();
        let terms: Vec<String> = tie
            .iter()
            .zip(&names)
            .filter(|(x, _)| x.abs() > 1e-3 * big)
            .map(|(x, n)| format!("{:+.3} {}", x / big, n))
            .collect();
        out.push(format!(
            "the readings do not change along ({})",
            terms.join(" ")
        ));
    }
    out
}

fn identifiability_hint(k: &Kinematics, obs: &[Observation]) -> Option<String> {
    let tilting = k.tilting_axes();
    if !tilting.is_empty() && !obs.iter().any(|o| k.is_tilted(&o.angles)) {
        return Some(format!(
            "no tilted pose: the position of the {} axis shows only when it turns; add a pose with {} != 0",
            tilting.join("/"),
            tilting.join("/")
        ));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::{Plan, PlanConfig};

    pub(crate) fn observations(
        k: &Kinematics,
        plan: &Plan,
        truth: &MachineState,
    ) -> Vec<Observation> {
        plan.steps
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let v =
                    crate::measurement::latched(k, truth, &s.angles, &s.approach, &s.start, None)
                        .unwrap();
                let mut position = s.start;
                position[s.approach.axis.index()] = v;
                Observation {
                    label: s.label.clone(),
                    angles: s.angles,
                    approach: s.approach,
                    position,
                    t_ns: i as i64 * 1_000_000_000,
                }
            })
            .collect()
    }

    #[test]
    fn recovers_errors_noise_free() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let mut truth = k.nominal_state();
        let vals = [40.0, -70.0, 25.0, -15.0, 120.0, -250.0];
        for (id, v) in k.identify.iter().zip(vals) {
            truth.loc[id.axis][id.slot] = v * id.scale();
        }
        truth.beam_point += Vec3::new(0.3, -0.4, 0.25);
        let obs = observations(&k, &plan, &truth);
        let sol = identify(&k, &obs, &SolveOptions::new(0.5)).unwrap();
        for (e, v) in sol.errors.iter().zip(vals) {
            assert!(
                (e.value - v).abs() < 1e-3,
                "{} {} vs {}",
                e.name,
                e.value,
                v
            );
        }
        assert!(sol.chi2 < 1e-6);
    }

    /// The sensitivities put together from columns computed one at a time, as parameters were
    /// tried, are those of the whole parameter set at once, to the last bit: a zero parameter
    /// adds nothing to another's column.
    #[test]
    fn the_columns_tried_one_at_a_time_are_the_whole_jacobian() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
        let obs = observations(&k, &plan, &k.nominal_state());
        let opts = SolveOptions::new(0.5).with_drift_rates();
        let id = Identifier::new(&k, &obs, &opts).unwrap();
        // More than the locations: the nuisances and at least one drift rate were tried.
        assert!(id.params.len() > k.identify.len() + 2, "{:?}", id.params);
        let t_ref = mean_time_ns(obs.iter().map(|o| o.t_ns));
        let whole = id
            .jacobian_central(&obs, &vec![0.0; id.params.len()], t_ref)
            .unwrap();
        assert_eq!(id.j0, whole);
    }
}
