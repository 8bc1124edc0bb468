//! The fitted thermal model (physics.md 2.1): every channel (an apparent location error or a
//! displacement sensor) is
//!
//! `y(t) = offset + sum_j K_j lag(u; tau_j) + sum_s sum_k G_sk lag(T_s - T_s,ref; tau_sk)
//!         + c (n / n_ref)^2`,
//!
//! with `u = (n / n_ref)^gamma` from the whole spindle log (measurement spins included) and a
//! fixed, log-spaced pole basis, so that every parameter enters linearly: the fit has no local
//! minima. Lags advance by exact zero-order-hold steps between events.
//!
//! The batch fit is the posterior of a Gaussian prior (weak, plus ridge where the held-out
//! data prefer it) and the observations; the online [`Predictor`] is a Kalman filter over the
//! same parameters, starting from that posterior, with a random walk on the offset between
//! observations. With no random walk, the filter run over the fit's data from the fit's prior
//! gives the fit's posterior. Pure code.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::recording::{Recording, ResultStatus};

#[derive(Debug, Error, PartialEq)]
pub enum ModelError {
    #[error("model configuration: {0}")]
    Config(String),
    #[error("channel {channel}: {message}")]
    Channel { channel: String, message: String },
    #[error("no observations to fit{0}")]
    NoData(String),
}

/// A temperature input and its lags.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureInput {
    pub sensor: String,
    /// Time constants, min; 0 is the temperature itself without lag.
    #[serde(default = "default_temperature_taus")]
    pub taus_min: Vec<f64>,
}

/// What an accepted diagnosis term adds to the thermal model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ModelInput {
    SpindleLag {
        tau_min: f64,
    },
    Temperature {
        sensor: String,
        taus_min: Vec<f64>,
    },
    InstantSpeed,
    /// Nothing the thermal model can carry (a clock term, or a measurement-model effect).
    None,
}

/// The default lags of a temperature input, min: the temperature itself, 1 h and 4 h.
pub fn default_temperature_taus() -> Vec<f64> {
    vec![0.0, 60.0, 240.0]
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// Pole basis of the spindle heat input, min.
    pub taus_min: Vec<f64>,
    /// Reference speed of the heat input, min^-1.
    pub n_ref_rpm: f64,
    /// Exponent of the heat input.
    pub gamma: f64,
    pub temperatures: Vec<TemperatureInput>,
    /// An instantaneous speed term `c (n / n_ref)^2` (centrifugal and bearing-contact shift).
    pub instant_speed: bool,
    /// Ridge factors tried by blocked cross-validation (times each column's mean square);
    /// the smallest held-out error wins, 0 unless a larger one does better.
    pub ridge_grid: Vec<f64>,
    /// Random walk of the offset between observations, um^2 per hour: how fast the model's
    /// prediction loses credit without a measurement.
    pub offset_walk_um2_per_h: f64,
    /// Prior standard deviation of every gain (um per unit input): what the data must
    /// overrule. Thermal errors of tens of um make 100 um a weak but physical bound.
    pub prior_gain_sd: f64,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            taus_min: vec![6.0, 15.0, 40.0, 100.0, 250.0, 600.0],
            n_ref_rpm: 20000.0,
            gamma: 1.5,
            temperatures: Vec::new(),
            instant_speed: false,
            ridge_grid: vec![0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0],
            offset_walk_um2_per_h: 1.0,
            prior_gain_sd: 100.0,
        }
    }
}

/// The shipped default (`config/thermal.toml`).
pub const DEFAULT_MODEL_CONFIG: &str = include_str!("../config/thermal.toml");

impl ModelConfig {
    /// Parse and check a model configuration TOML.
    pub fn from_toml(text: &str) -> Result<Self, ModelError> {
        let c: ModelConfig = toml::from_str(text).map_err(|e| ModelError::Config(e.to_string()))?;
        c.validate()?;
        Ok(c)
    }

    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::Config(m));
        if self.taus_min.iter().any(|t| !crate::positive(*t)) {
            return bad(format!("spindle taus_min must be > 0: {:?}", self.taus_min));
        }
        if !crate::positive(self.n_ref_rpm) || !crate::positive(self.gamma) {
            return bad("n_ref_rpm and gamma must be > 0".into());
        }
        for t in &self.temperatures {
            if t.taus_min.is_empty() || t.taus_min.iter().any(|x| !crate::non_negative(*x)) {
                return bad(format!("sensor {}: taus_min must be >= 0", t.sensor));
            }
        }
        if self.ridge_grid.is_empty() || self.ridge_grid.iter().any(|x| !crate::non_negative(*x)) {
            return bad("ridge_grid needs values >= 0".into());
        }
        if !crate::positive(self.prior_gain_sd) {
            return bad("prior_gain_sd must be > 0".into());
        }
        if !crate::non_negative(self.offset_walk_um2_per_h) {
            return bad("offset_walk_um2_per_h must be >= 0".into());
        }
        Ok(())
    }

    /// This configuration with what accepted diagnosis terms add (time constants and
    /// lags kept sorted and unique).
    pub fn with_inputs(&self, inputs: &[ModelInput]) -> ModelConfig {
        let mut m = self.clone();
        for i in inputs {
            match i {
                ModelInput::SpindleLag { tau_min } => m.taus_min.push(*tau_min),
                ModelInput::Temperature { sensor, taus_min } => {
                    match m.temperatures.iter_mut().find(|t| &t.sensor == sensor) {
                        Some(t) => t.taus_min.extend(taus_min),
                        None => m.temperatures.push(TemperatureInput {
                            sensor: sensor.clone(),
                            taus_min: taus_min.clone(),
                        }),
                    }
                }
                ModelInput::InstantSpeed => m.instant_speed = true,
                ModelInput::None => {}
            }
        }
        let tidy = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.dedup();
        };
        tidy(&mut m.taus_min);
        for t in &mut m.temperatures {
            tidy(&mut t.taus_min);
        }
        m
    }

    /// Column names: `offset`, `spindle_lag_<tau>`, `<sensor>_lag_<tau>`, `speed_squared`.
    pub fn columns(&self) -> Vec<String> {
        let mut c = vec!["offset".to_string()];
        c.extend(self.taus_min.iter().map(|t| format!("spindle_lag_{t}min")));
        for s in &self.temperatures {
            c.extend(
                s.taus_min
                    .iter()
                    .map(|t| format!("{}_lag_{t}min", s.sensor)),
            );
        }
        if self.instant_speed {
            c.push("speed_squared".into());
        }
        c
    }
}

/// What happens on the machine's timeline, in time order.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    Spindle {
        t_ns: i64,
        rpm: f64,
    },
    Temperature {
        t_ns: i64,
        sensor: String,
        celsius: f64,
    },
    /// A measured value of a channel; `sigma` its standard uncertainty when known.
    Observation {
        t_ns: i64,
        channel: String,
        value: f64,
        sigma: Option<f64>,
    },
}

impl Event {
    pub fn t_ns(&self) -> i64 {
        match self {
            Event::Spindle { t_ns, .. }
            | Event::Temperature { t_ns, .. }
            | Event::Observation { t_ns, .. } => *t_ns,
        }
    }
}

/// The temperature sensors the events name, sorted and unique.
pub fn sensors_of(events: &[Event]) -> Vec<String> {
    let mut v: Vec<String> = events
        .iter()
        .filter_map(|e| match e {
            Event::Temperature { sensor, .. } => Some(sensor.clone()),
            _ => None,
        })
        .collect();
    v.sort();
    v.dedup();
    v
}

/// The timeline of recordings: spindle, temperatures, displacement readings and the errors of
/// every validated (`ok`) cycle result at its reference time. Inputs sort before observations
/// at the same time.
pub fn events_from(recordings: &[Recording]) -> Vec<Event> {
    let mut ev = Vec::new();
    for r in recordings {
        ev.extend(r.spindle.iter().map(|m| Event::Spindle {
            t_ns: m.t_ns,
            rpm: m.msg.rpm,
        }));
        ev.extend(r.temperatures.iter().map(|m| Event::Temperature {
            t_ns: m.t_ns,
            sensor: m.msg.sensor.clone(),
            celsius: m.msg.celsius,
        }));
        ev.extend(r.displacements.iter().map(|m| Event::Observation {
            t_ns: m.t_ns,
            channel: m.msg.sensor.clone(),
            value: m.msg.um,
            sigma: None,
        }));
        for res in &r.results {
            let m = &res.msg;
            if m.status != ResultStatus::Ok {
                continue;
            }
            let (Some(errors), sigma) = (&m.errors, &m.sigma) else {
                continue;
            };
            for (name, v) in errors {
                ev.push(Event::Observation {
                    t_ns: m.t_ns,
                    channel: name.clone(),
                    value: *v,
                    sigma: sigma.as_ref().and_then(|s| s.get(name)).copied(),
                });
            }
        }
    }
    ev.sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
    ev
}

/// The lag states of every input, advanced along the timeline.
#[derive(Debug, Clone)]
pub struct Features {
    cfg: ModelConfig,
    /// Reference of each configured sensor (in `cfg.temperatures` order): given, or its
    /// first reading.
    t_ref: Vec<Option<f64>>,
    t_ns: i64,
    rpm: f64,
    /// The spindle heat input `(|n| / n_ref)^gamma`, kept with `rpm`.
    heat: f64,
    /// Last reading of each configured sensor.
    temps: Vec<Option<f64>>,
    /// One per column after the offset, in column order (the speed term last, if any).
    x: Vec<f64>,
}

impl Features {
    /// States at `t0_ns` of a machine that has stood cold: spindle lags at zero, temperature
    /// lags at their reference. A sensor without a given reference takes its first reading.
    pub fn new(cfg: &ModelConfig, t_ref_c: &BTreeMap<String, f64>, t0_ns: i64) -> Self {
        let n = cfg.columns().len() - 1;
        Features {
            cfg: cfg.clone(),
            t_ref: cfg
                .temperatures
                .iter()
                .map(|s| t_ref_c.get(&s.sensor).copied())
                .collect(),
            t_ns: t0_ns,
            rpm: 0.0,
            heat: 0.0,
            temps: vec![None; cfg.temperatures.len()],
            x: vec![0.0; n],
        }
    }

    pub fn t_ns(&self) -> i64 {
        self.t_ns
    }

    /// The reference temperature of every configured sensor seen so far.
    pub fn t_ref_c(&self) -> BTreeMap<String, f64> {
        self.cfg
            .temperatures
            .iter()
            .zip(&self.t_ref)
            .filter_map(|(s, r)| r.map(|r| (s.sensor.clone(), r)))
            .collect()
    }

    /// Configured sensors that have had no reading yet.
    pub fn unseen_sensors(&self) -> Vec<String> {
        self.cfg
            .temperatures
            .iter()
            .zip(&self.temps)
            .filter(|(_, t)| t.is_none())
            .map(|(s, _)| s.sensor.clone())
            .collect()
    }

    /// Visit every state with the input it follows and its time constant in seconds (0: no
    /// lag), in column order, without allocating (this runs for every event).
    fn for_each_state(&mut self, mut f: impl FnMut(&mut f64, f64, f64)) {
        let mut i = 0;
        for t in &self.cfg.taus_min {
            f(&mut self.x[i], self.heat, t * 60.0);
            i += 1;
        }
        for (k, s) in self.cfg.temperatures.iter().enumerate() {
            let d = match (self.temps[k], self.t_ref[k]) {
                (Some(t), Some(r)) => t - r,
                _ => 0.0,
            };
            for t in &s.taus_min {
                f(&mut self.x[i], d, t * 60.0);
                i += 1;
            }
        }
        if self.cfg.instant_speed {
            f(&mut self.x[i], (self.rpm / self.cfg.n_ref_rpm).powi(2), 0.0);
        }
    }

    /// Advance to `t_ns` with the inputs held (exact zero-order hold). Time never runs back.
    pub fn advance_to(&mut self, t_ns: i64) {
        if t_ns <= self.t_ns {
            return;
        }
        let dt = (t_ns - self.t_ns) as f64 / 1e9;
        self.for_each_state(|x, u, tau| {
            if tau <= 0.0 {
                *x = u;
            } else {
                let a = (-dt / tau).exp();
                *x = a * *x + (1.0 - a) * u;
            }
        });
        self.t_ns = t_ns;
    }

    fn refresh_instant(&mut self) {
        self.for_each_state(|x, u, tau| {
            if tau <= 0.0 {
                *x = u;
            }
        });
    }

    pub fn set_rpm(&mut self, t_ns: i64, rpm: f64) {
        self.advance_to(t_ns);
        if rpm.is_finite() && rpm != self.rpm {
            self.rpm = rpm;
            self.heat = (rpm.abs() / self.cfg.n_ref_rpm).powf(self.cfg.gamma);
            self.refresh_instant();
        }
    }

    pub fn set_temperature(&mut self, t_ns: i64, sensor: &str, celsius: f64) {
        self.advance_to(t_ns);
        let Some(k) = self
            .cfg
            .temperatures
            .iter()
            .position(|s| s.sensor == sensor)
        else {
            return;
        };
        if celsius.is_finite() {
            self.temps[k] = Some(celsius);
            self.t_ref[k].get_or_insert(celsius);
            self.refresh_instant();
        }
    }

    /// Apply an input event (observations do not change the inputs).
    pub fn apply(&mut self, e: &Event) {
        match e {
            Event::Spindle { t_ns, rpm } => self.set_rpm(*t_ns, *rpm),
            Event::Temperature {
                t_ns,
                sensor,
                celsius,
            } => self.set_temperature(*t_ns, sensor, *celsius),
            Event::Observation { t_ns, .. } => self.advance_to(*t_ns),
        }
    }

    /// The design row at the current time: `[1, states...]`.
    pub fn row(&self) -> DVector<f64> {
        let mut r = Vec::with_capacity(self.x.len() + 1);
        r.push(1.0);
        r.extend_from_slice(&self.x);
        DVector::from_vec(r)
    }
}

/// One channel's fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelFit {
    pub name: String,
    /// Posterior mean of the parameters, in the model's column order.
    pub coef: Vec<f64>,
    /// Posterior covariance, row-major.
    pub cov: Vec<f64>,
    /// Prior precision of each parameter (weak prior plus ridge); the prior mean is zero.
    pub prior_precision: Vec<f64>,
    /// Ridge factor chosen by blocked cross-validation.
    pub ridge: f64,
    /// Model scatter beyond the observations' own uncertainty, um (added in quadrature).
    pub discrepancy_um: f64,
    pub n_obs: usize,
    pub rms_um: f64,
    /// Weighted chi-square per degree of freedom with the discrepancy included (1 when the
    /// discrepancy is positive).
    pub chi2_dof: f64,
    /// Held-out RMS of the chosen ridge factor (blocked cross-validation), um.
    pub cv_rmse_um: f64,
}

impl ChannelFit {
    fn n(&self) -> usize {
        self.coef.len()
    }
    pub fn cov_matrix(&self) -> DMatrix<f64> {
        DMatrix::from_row_slice(self.n(), self.n(), &self.cov)
    }
    /// The time constant and gain of each spindle lag (um per unit heat input).
    pub fn spindle_gains(&self, cfg: &ModelConfig) -> Vec<(f64, f64)> {
        cfg.taus_min
            .iter()
            .zip(self.coef.iter().skip(1))
            .map(|(t, k)| (*t, *k))
            .collect()
    }
}

/// A fitted model: what `driftwatch fit` writes as JSON.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ThermalModel {
    pub format: String,
    pub config: ModelConfig,
    pub columns: Vec<String>,
    /// Temperature reference of each sensor (its first reading in the fit data), deg C.
    pub t_ref_c: BTreeMap<String, f64>,
    /// First and last event time of the fit data, ns.
    pub from_ns: i64,
    pub to_ns: i64,
    pub channels: Vec<ChannelFit>,
}

pub const MODEL_FORMAT: &str = "driftwatch.thermal_model.v1";

impl ThermalModel {
    /// Read a model file written by `driftwatch fit`, checking its format and configuration.
    pub fn from_json(text: &str) -> Result<Self, ModelError> {
        let m: ThermalModel = serde_json::from_str(text)
            .map_err(|e| ModelError::Config(format!("not a driftwatch model: {e}")))?;
        if m.format != MODEL_FORMAT {
            return Err(ModelError::Config(format!(
                "model format '{}', expected '{MODEL_FORMAT}'",
                m.format
            )));
        }
        m.config.validate()?;
        let n = m.config.columns().len();
        if m.columns != m.config.columns()
            || m.channels
                .iter()
                .any(|c| c.coef.len() != n || c.cov.len() != n * n)
        {
            return Err(ModelError::Config(
                "the model's parameters do not match its configuration's columns".into(),
            ));
        }
        Ok(m)
    }
}

/// Weak prior of the offset, um (the gains' is configured): wide against any machine.
const PRIOR_SD_OFFSET: f64 = 1e4;
/// Blocks of the time-ordered data for cross-validation.
const CV_BLOCKS: usize = 5;

/// One observation of a channel with its design row (the lag states at its time).
#[derive(Debug, Clone, PartialEq)]
pub struct Obs {
    pub t_ns: i64,
    pub row: DVector<f64>,
    pub y: f64,
    pub sigma: Option<f64>,
}

/// Fit every observed channel on the events up to `until_ns`.
pub fn fit(
    cfg: &ModelConfig,
    events: &[Event],
    until_ns: Option<i64>,
) -> Result<ThermalModel, ModelError> {
    cfg.validate()?;
    let events: Vec<&Event> = events
        .iter()
        .filter(|e| until_ns.is_none_or(|u| e.t_ns() <= u))
        .collect();
    let (Some(first), Some(last)) = (events.first(), events.last()) else {
        return Err(ModelError::NoData(String::new()));
    };
    let mut t_ref_c = BTreeMap::new();
    for e in &events {
        if let Event::Temperature {
            sensor, celsius, ..
        } = e
            && celsius.is_finite()
        {
            t_ref_c.entry(sensor.clone()).or_insert(*celsius);
        }
    }
    for s in &cfg.temperatures {
        if !t_ref_c.contains_key(&s.sensor) {
            return Err(ModelError::Config(format!(
                "temperature input '{}' has no reading in the data (sensors: {:?})",
                s.sensor,
                t_ref_c.keys().collect::<Vec<_>>()
            )));
        }
    }
    let mut f = Features::new(cfg, &t_ref_c, first.t_ns());
    let mut per: BTreeMap<String, Vec<Obs>> = BTreeMap::new();
    for e in &events {
        f.apply(e);
        if let Event::Observation {
            t_ns,
            channel,
            value,
            sigma,
        } = e
            && value.is_finite()
        {
            per.entry(channel.clone()).or_default().push(Obs {
                t_ns: *t_ns,
                row: f.row(),
                y: *value,
                sigma: sigma.filter(|s| crate::positive(*s)),
            });
        }
    }
    fit_rows(cfg, t_ref_c, (first.t_ns(), last.t_ns()), &per)
}

/// Fit every channel from its observation rows (time-ordered), made by [`Features`] with the
/// reference temperatures `t_ref_c` over the data span `span_ns`.
pub fn fit_rows(
    cfg: &ModelConfig,
    t_ref_c: BTreeMap<String, f64>,
    span_ns: (i64, i64),
    per: &BTreeMap<String, Vec<Obs>>,
) -> Result<ThermalModel, ModelError> {
    cfg.validate()?;
    if per.is_empty() {
        return Err(ModelError::NoData(
            " (no displacement readings or validated cycle results)".into(),
        ));
    }
    let columns = cfg.columns();
    if let Some((name, _)) = per
        .iter()
        .find(|(_, o)| o.iter().any(|o| o.row.len() != columns.len()))
    {
        return Err(ModelError::Config(format!(
            "channel {name}: rows do not have the configuration's {} columns",
            columns.len()
        )));
    }
    let channels = per
        .iter()
        .map(|(name, obs)| fit_channel(cfg, name, obs, columns.len()))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(ThermalModel {
        format: MODEL_FORMAT.into(),
        config: cfg.clone(),
        columns,
        t_ref_c,
        from_ns: span_ns.0,
        to_ns: span_ns.1,
        channels,
    })
}

/// Posterior mean and precision matrix for weights `w` and prior precision `lambda`.
fn solve(obs: &[&Obs], w: &[f64], lambda: &[f64]) -> Option<(DVector<f64>, DMatrix<f64>)> {
    let n = lambda.len();
    let mut a = DMatrix::from_diagonal(&DVector::from_column_slice(lambda));
    let mut b = DVector::zeros(n);
    for (o, wi) in obs.iter().zip(w) {
        a.ger(*wi, &o.row, &o.row, 1.0);
        b.axpy(wi * o.y, &o.row, 1.0);
    }
    let a = (a.clone() + a.transpose()) * 0.5;
    let chol = a.clone().cholesky()?;
    Some((chol.solve(&b), a))
}

fn fit_channel(
    cfg: &ModelConfig,
    name: &str,
    obs: &[Obs],
    n: usize,
) -> Result<ChannelFit, ModelError> {
    let err = |m: String| ModelError::Channel {
        channel: name.to_string(),
        message: m,
    };
    if obs.len() < 2 {
        return Err(err(format!(
            "{} observation(s); at least 2 needed",
            obs.len()
        )));
    }
    // Scale of each column over the data, so that a ridge factor means the same for all.
    let mut ms = vec![0.0; n];
    for o in obs {
        for (m, x) in ms.iter_mut().zip(o.row.iter()) {
            *m += x * x / obs.len() as f64;
        }
    }
    let base: Vec<f64> = (0..n)
        .map(|j| {
            let sd = if j == 0 {
                PRIOR_SD_OFFSET
            } else {
                cfg.prior_gain_sd
            };
            1.0 / (sd * sd)
        })
        .collect();
    let with_ridge = |k: f64| -> Vec<f64> {
        base.iter()
            .zip(&ms)
            .enumerate()
            .map(|(j, (b, m))| if j == 0 { *b } else { b + k * m.max(1e-12) })
            .collect()
    };
    let all: Vec<&Obs> = obs.iter().collect();
    // Discrepancy so that chi2/dof = 1 (0 when the stated uncertainties already explain the
    // scatter): two passes are enough, the weights change little after the first.
    let weights = |d2: f64| -> Vec<f64> {
        obs.iter()
            .map(|o| {
                let v = o.sigma.map_or(0.0, |s| s * s) + d2;
                if v > 0.0 { 1.0 / v } else { 1.0 }
            })
            .collect()
    };
    // Parameters the data determine (the rest stay at their prior): at most the observations.
    let dof = obs.len() as f64 - n as f64;
    let determined = dof >= 1.0;
    let dof = dof.max(1.0);
    // The discrepancy that makes chi2/dof = 1 for a given ridge (0 when the stated
    // uncertainties already explain the scatter); a few passes settle the weights.
    let discrepancy = |k: f64| -> Result<f64, ModelError> {
        let mut d2 = 0.0;
        for _ in 0..3 {
            let (beta, _) = solve(&all, &weights(d2), &with_ridge(k))
                .ok_or_else(|| err("singular fit".into()))?;
            let r2: Vec<(f64, f64)> = obs
                .iter()
                .map(|o| {
                    (
                        (o.y - o.row.dot(&beta)).powi(2),
                        o.sigma.map_or(0.0, |s| s * s),
                    )
                })
                .collect();
            let chi = |d2: f64| -> f64 {
                r2.iter()
                    .map(|(r, s)| if s + d2 > 0.0 { r / (s + d2) } else { 0.0 })
                    .sum()
            };
            if !determined {
                // Fewer observations than parameters: the residuals say nothing about the
                // model's scatter; the posterior covariance carries the uncertainty.
                d2 = if obs.iter().all(|o| o.sigma.is_none()) {
                    1.0
                } else {
                    0.0
                };
            } else if obs.iter().all(|o| o.sigma.is_none()) {
                d2 = r2.iter().map(|x| x.0).sum::<f64>() / dof;
            } else if chi(0.0) <= dof {
                d2 = 0.0;
            } else {
                // chi(d2) falls as d2 grows: bisect for chi = dof.
                let (mut lo, mut hi) = (0.0, r2.iter().map(|x| x.0).fold(1e-12, f64::max));
                for _ in 0..80 {
                    let mid = 0.5 * (lo + hi);
                    if chi(mid) > dof { lo = mid } else { hi = mid }
                }
                d2 = hi;
            }
        }
        Ok(d2)
    };
    let d2 = discrepancy(0.0)?;
    let w = weights(d2);
    // Blocked cross-validation over contiguous stretches of time, when there are enough
    // observations for each held-out block to say something (two per block); else the prior
    // alone regularises.
    let blocks = CV_BLOCKS.min(obs.len());
    let mut best = (f64::INFINITY, 0.0);
    let grid: &[f64] = if obs.len() >= 2 * CV_BLOCKS {
        &cfg.ridge_grid
    } else {
        &[0.0]
    };
    for &k in grid {
        let mut sse = 0.0;
        let mut count = 0usize;
        for b in 0..blocks {
            let lo = b * obs.len() / blocks;
            let hi = (b + 1) * obs.len() / blocks;
            let train: Vec<&Obs> = obs[..lo].iter().chain(&obs[hi..]).collect();
            let wt: Vec<f64> = w[..lo].iter().chain(&w[hi..]).copied().collect();
            let Some((beta, _)) = solve(&train, &wt, &with_ridge(k)) else {
                continue;
            };
            for o in &obs[lo..hi] {
                sse += (o.y - o.row.dot(&beta)).powi(2);
                count += 1;
            }
        }
        let rmse = (sse / count.max(1) as f64).sqrt();
        // A larger ridge must do better, not merely as well.
        if rmse < best.0 * (1.0 - 1e-9) {
            best = (rmse, k);
        }
    }
    let d2 = discrepancy(best.1)?;
    let w = weights(d2);
    let lambda = with_ridge(best.1);
    let (beta, a) = solve(&all, &w, &lambda).ok_or_else(|| err("singular fit".into()))?;
    let cov = a
        .try_inverse()
        .ok_or_else(|| err("singular posterior".into()))?;
    let resid: Vec<f64> = obs.iter().map(|o| o.y - o.row.dot(&beta)).collect();
    let rms = (resid.iter().map(|r| r * r).sum::<f64>() / resid.len() as f64).sqrt();
    let chi2: f64 = resid.iter().zip(&w).map(|(r, wi)| r * r * wi).sum();
    let mut cov_rows = Vec::with_capacity(n * n);
    for i in 0..n {
        for j in 0..n {
            cov_rows.push(cov[(i, j)]);
        }
    }
    Ok(ChannelFit {
        name: name.to_string(),
        coef: beta.iter().copied().collect(),
        cov: cov_rows,
        prior_precision: lambda,
        ridge: best.1,
        discrepancy_um: d2.sqrt(),
        n_obs: obs.len(),
        rms_um: rms,
        chi2_dof: chi2 / dof,
        cv_rmse_um: best.0,
    })
}

/// A prediction of one channel.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Prediction {
    pub channel: String,
    pub value: f64,
    /// Standard uncertainty of the channel's true value (parameters, offset walk since the
    /// last observation, model discrepancy), um.
    pub sigma: f64,
}

#[derive(Debug, Clone)]
struct ChannelState {
    beta: DVector<f64>,
    p: DMatrix<f64>,
    /// Time of the last observation (or of the start).
    t_ns: i64,
    discrepancy2: f64,
}

/// The model run forward in time, corrected by every observation (Kalman filter).
#[derive(Debug, Clone)]
pub struct Predictor {
    pub model: std::sync::Arc<ThermalModel>,
    features: Features,
    channels: BTreeMap<String, ChannelState>,
    walk_per_s: f64,
}

impl Predictor {
    /// Start from the fitted posterior at `t0_ns` with the inputs of a cold machine.
    pub fn new(model: &ThermalModel, t0_ns: i64) -> Self {
        let features = Features::new(&model.config, &model.t_ref_c, t0_ns);
        Self::resume(std::sync::Arc::new(model.clone()), features, t0_ns)
    }

    /// Continue from the fitted posterior with lag states already run up to now (the
    /// model's configuration and references must be the ones the states were made with);
    /// `last_obs_ns` is when the fit last saw an observation, where the offset walk starts.
    pub fn resume(
        model: std::sync::Arc<ThermalModel>,
        features: Features,
        last_obs_ns: i64,
    ) -> Self {
        let channels = model
            .channels
            .iter()
            .map(|c| {
                (
                    c.name.clone(),
                    ChannelState {
                        beta: DVector::from_column_slice(&c.coef),
                        p: c.cov_matrix(),
                        t_ns: last_obs_ns,
                        discrepancy2: c.discrepancy_um.powi(2),
                    },
                )
            })
            .collect();
        Predictor {
            features,
            channels,
            walk_per_s: model.config.offset_walk_um2_per_h / 3600.0,
            model,
        }
    }

    /// Start from the fit's prior instead (zero mean, its prior precision), with no offset
    /// walk: run over the fit's own data it reproduces the fit (the batch-online check).
    pub fn from_prior(model: &ThermalModel, t0_ns: i64) -> Self {
        let mut p = Predictor::new(model, t0_ns);
        for c in &model.channels {
            if let Some(s) = p.channels.get_mut(&c.name) {
                s.beta = DVector::zeros(c.coef.len());
                s.p = DMatrix::from_diagonal(&DVector::from_iterator(
                    c.prior_precision.len(),
                    c.prior_precision.iter().map(|l| 1.0 / l),
                ));
            }
        }
        p.walk_per_s = 0.0;
        p
    }

    pub fn t_ns(&self) -> i64 {
        self.features.t_ns()
    }

    /// Take an event in time order: inputs move the lags, observations correct their
    /// channel. An observation of a channel the model does not have is ignored (returns false).
    pub fn apply(&mut self, e: &Event) -> bool {
        self.features.apply(e);
        let Event::Observation {
            t_ns,
            channel,
            value,
            sigma,
        } = e
        else {
            return true;
        };
        let h = self.features.row();
        self.observe_row(channel, *t_ns, *value, *sigma, &h)
    }

    /// Correct a channel with an observation made at `t_ns` whose design row `h` is known
    /// (the lag states at that time, when the filter has already run past it).
    pub fn observe_row(
        &mut self,
        channel: &str,
        t_ns: i64,
        value: f64,
        sigma: Option<f64>,
        h: &DVector<f64>,
    ) -> bool {
        let Some(s) = self.channels.get_mut(channel) else {
            return false;
        };
        if !value.is_finite() || h.len() != s.beta.len() {
            return false;
        }
        s.p[(0, 0)] += self.walk_per_s * (t_ns - s.t_ns).max(0) as f64 / 1e9;
        s.t_ns = s.t_ns.max(t_ns);
        let r = sigma.filter(|x| crate::positive(*x)).map_or(0.0, |x| x * x) + s.discrepancy2;
        let r = if r > 0.0 { r } else { 1e-12 };
        let ph = &s.p * h;
        let innovation_var = h.dot(&ph) + r;
        let k = &ph / innovation_var;
        let innovation = value - h.dot(&s.beta);
        s.beta += &k * innovation;
        // Joseph form keeps P symmetric and positive.
        let n = h.len();
        let i_kh = DMatrix::identity(n, n) - &k * h.transpose();
        s.p = &i_kh * &s.p * i_kh.transpose() + &k * k.transpose() * r;
        true
    }

    /// Every channel at `t_ns` (not before the last event), inputs held since the last one.
    pub fn predict(&mut self, t_ns: i64) -> Vec<Prediction> {
        self.features.advance_to(t_ns);
        let h = self.features.row();
        self.channels
            .iter()
            .map(|(name, s)| {
                let walk = self.walk_per_s * (t_ns - s.t_ns).max(0) as f64 / 1e9;
                let var = h.dot(&(&s.p * &h)) + walk + s.discrepancy2;
                Prediction {
                    channel: name.clone(),
                    value: h.dot(&s.beta),
                    sigma: var.max(0.0).sqrt(),
                }
            })
            .collect()
    }

    /// Current parameter mean of a channel (for reports and the batch-online check).
    pub fn coef(&self, channel: &str) -> Option<Vec<f64>> {
        self.channels
            .get(channel)
            .map(|s| s.beta.iter().copied().collect())
    }
}

/// One step of a causal replay.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplayStep {
    pub t_ns: i64,
    pub predictions: Vec<Prediction>,
    /// Observations used in the step (since the previous one), by channel: their last value.
    pub measured: BTreeMap<String, f64>,
}

/// Predictions against the observations after the last update.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HoldoutScore {
    pub channel: String,
    pub n: usize,
    pub rmse_um: f64,
    /// Holding the last used observation instead.
    pub persistence_rmse_um: f64,
}

/// Replay `events` through the model as the daemon would live: every `step_ns` from the first
/// event, each prediction from what came before it. Observations up to `update_until_ns`
/// correct the model; later ones are only scored.
pub fn replay(
    model: &ThermalModel,
    events: &[Event],
    step_ns: i64,
    update_until_ns: i64,
) -> (Vec<ReplayStep>, Vec<HoldoutScore>) {
    let (Some(first), Some(last)) = (events.first(), events.last()) else {
        return (Vec::new(), Vec::new());
    };
    let step_ns = step_ns.max(1);
    let mut p = Predictor::new(model, first.t_ns());
    let mut last_used: BTreeMap<String, f64> = BTreeMap::new();
    let mut sums: BTreeMap<String, (usize, f64, f64)> = BTreeMap::new();
    let mut steps = Vec::new();
    let mut measured = BTreeMap::new();
    let mut k = 0;
    let mut t = first.t_ns();
    while t <= last.t_ns() {
        while k < events.len() && events[k].t_ns() <= t {
            let e = &events[k];
            k += 1;
            match e {
                Event::Observation { channel, value, .. } if e.t_ns() > update_until_ns => {
                    let pred = p
                        .predict(e.t_ns())
                        .into_iter()
                        .find(|x| &x.channel == channel);
                    if let (Some(pr), Some(prev)) = (pred, last_used.get(channel)) {
                        let s = sums.entry(channel.clone()).or_default();
                        s.0 += 1;
                        s.1 += (pr.value - value).powi(2);
                        s.2 += (prev - value).powi(2);
                    }
                }
                Event::Observation { channel, value, .. } => {
                    if p.apply(e) {
                        last_used.insert(channel.clone(), *value);
                        measured.insert(channel.clone(), *value);
                    }
                }
                _ => {
                    p.apply(e);
                }
            }
        }
        steps.push(ReplayStep {
            t_ns: t,
            predictions: p.predict(t),
            measured: std::mem::take(&mut measured),
        });
        t += step_ns;
    }
    let scores = sums
        .into_iter()
        .map(|(channel, (n, sse, ssp))| HoldoutScore {
            channel,
            n,
            rmse_um: (sse / n as f64).sqrt(),
            persistence_rmse_um: (ssp / n as f64).sqrt(),
        })
        .collect();
    (steps, scores)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const MIN: i64 = 60_000_000_000;

    /// A patent-like day: 20000 min^-1 for 210 min, 30 min stop, restart; observations of a
    /// two-lag channel every `every` min with noise `sd`.
    fn day(every: i64, sd: f64, seed: u64) -> (Vec<Event>, Vec<(i64, f64)>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut ev = vec![
            Event::Spindle {
                t_ns: 0,
                rpm: 20000.0,
            },
            Event::Spindle {
                t_ns: 210 * MIN,
                rpm: 0.0,
            },
            Event::Spindle {
                t_ns: 240 * MIN,
                rpm: 20000.0,
            },
            Event::Spindle {
                t_ns: 400 * MIN,
                rpm: 10000.0,
            },
            Event::Spindle {
                t_ns: 500 * MIN,
                rpm: 0.0,
            },
        ];
        let truth = |t: f64, lags: &mut (f64, f64), u: f64, dt: f64| {
            let a1 = (-dt / 12.0).exp();
            let a2 = (-dt / 120.0).exp();
            lags.0 = a1 * lags.0 + (1.0 - a1) * u;
            lags.1 = a2 * lags.1 + (1.0 - a2) * u;
            let _ = t;
            5.0 + 39.0 * lags.0 + 49.0 * lags.1
        };
        let mut lags = (0.0, 0.0);
        let mut truth_at = Vec::new();
        let speed = |m: i64| match m {
            0..210 => 20000.0,
            240..400 => 20000.0,
            400..500 => 10000.0,
            _ => 0.0,
        };
        let mut y = 5.0;
        for m in 0..=700 {
            if m > 0 {
                let u = (speed(m - 1) / 20000.0f64).powf(1.5);
                y = truth(m as f64, &mut lags, u, 1.0);
            }
            truth_at.push((m * MIN, y));
            if m % every == 0 {
                ev.push(Event::Observation {
                    t_ns: m * MIN,
                    channel: "EZ0B".into(),
                    value: y + sd * rng.random_range(-1.0..1.0) * 3f64.sqrt(),
                    sigma: Some(sd),
                });
            }
        }
        ev.sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
        (ev, truth_at)
    }

    #[test]
    fn zero_order_hold_is_exact_for_any_step() {
        let cfg = ModelConfig::default();
        let mut a = Features::new(&cfg, &BTreeMap::new(), 0);
        let mut b = a.clone();
        a.set_rpm(0, 20000.0);
        b.set_rpm(0, 20000.0);
        a.advance_to(100 * MIN);
        for m in 1..=100 {
            b.advance_to(m * MIN);
        }
        for (x, y) in a.row().iter().zip(b.row().iter()) {
            assert!((x - y).abs() < 1e-12);
        }
        // The 6-min lag after 100 min at full heat: 1 - e^(-100/6).
        assert!((a.row()[1] - (1.0 - (-100.0f64 / 6.0).exp())).abs() < 1e-12);
    }

    #[test]
    fn a_two_lag_channel_is_recovered_and_predicted() {
        let (ev, truth) = day(5, 0.3, 7);
        let m = fit(&ModelConfig::default(), &ev, None).unwrap();
        let c = &m.channels[0];
        assert_eq!(c.name, "EZ0B");
        assert!(c.rms_um < 0.5, "rms {}", c.rms_um);
        assert!(c.chi2_dof < 1.5, "{}", c.chi2_dof);
        // The basis represents the 12/120-min lags: steady-state gain (sum) near 88 um.
        let total: f64 = c.spindle_gains(&m.config).iter().map(|g| g.1).sum();
        assert!((total - 88.0).abs() < 3.0, "total gain {total}");
        // Predicting the day again without observations follows the truth within 1.5 um.
        let mut p = Predictor::new(&m, 0);
        let inputs: Vec<&Event> = ev
            .iter()
            .filter(|e| !matches!(e, Event::Observation { .. }))
            .collect();
        let mut worst: f64 = 0.0;
        let mut k = 0;
        for (t, y) in &truth {
            while k < inputs.len() && inputs[k].t_ns() <= *t {
                p.apply(inputs[k]);
                k += 1;
            }
            let pr = &p.predict(*t)[0];
            worst = worst.max((pr.value - y).abs());
        }
        assert!(worst < 1.5, "worst {worst}");
    }

    #[test]
    fn the_online_filter_from_the_prior_reproduces_the_batch_fit() {
        let (ev, _) = day(10, 0.5, 3);
        let m = fit(&ModelConfig::default(), &ev, None).unwrap();
        let mut p = Predictor::from_prior(&m, 0);
        for e in &ev {
            p.apply(e);
        }
        let online = p.coef("EZ0B").unwrap();
        let batch = &m.channels[0].coef;
        // Compared where it matters: the predicted values over the day.
        let mut f = Features::new(&m.config, &m.t_ref_c, 0);
        let mut worst: f64 = 0.0;
        for e in &ev {
            f.apply(e);
            let r = f.row();
            let a: f64 = r.iter().zip(&online).map(|(x, b)| x * b).sum();
            let b: f64 = r.iter().zip(batch).map(|(x, b)| x * b).sum();
            worst = worst.max((a - b).abs());
        }
        assert!(worst < 1e-6, "online and batch differ by {worst} um");
    }

    #[test]
    fn uncertainty_grows_without_observations_and_shrinks_with_one() {
        let (ev, _) = day(10, 0.5, 4);
        let m = fit(&ModelConfig::default(), &ev, None).unwrap();
        let mut p = Predictor::new(&m, 0);
        let s0 = p.predict(0)[0].sigma;
        let s1 = p.predict(600 * MIN)[0].sigma;
        assert!(s1 > s0, "{s0} -> {s1}");
        // 10 h of offset walk at 1 um^2/h: at least sqrt(10) um.
        assert!(s1 >= 10f64.sqrt(), "{s1}");
        p.apply(&Event::Observation {
            t_ns: 600 * MIN,
            channel: "EZ0B".into(),
            value: 20.0,
            sigma: Some(0.5),
        });
        let s2 = p.predict(600 * MIN)[0].sigma;
        assert!(s2 < 1.0, "{s2}");
        assert!(!p.apply(&Event::Observation {
            t_ns: 600 * MIN,
            channel: "nope".into(),
            value: 1.0,
            sigma: None,
        }));
    }

    #[test]
    fn the_shipped_configuration_is_the_default() {
        let c = ModelConfig::from_toml(DEFAULT_MODEL_CONFIG).unwrap();
        assert_eq!(c, ModelConfig::default());
        let with = format!("{DEFAULT_MODEL_CONFIG}\n[[temperatures]]\nsensor = \"ambient\"\n");
        let c = ModelConfig::from_toml(&with).unwrap();
        assert_eq!(c.temperatures[0].taus_min, [0.0, 60.0, 240.0]);
        assert!(ModelConfig::from_toml("gamma = -1.0").is_err());
        assert!(ModelConfig::from_toml("tau = 3").is_err());
    }

    #[test]
    fn bad_configurations_and_empty_data_are_named() {
        let cfg = ModelConfig {
            taus_min: vec![0.0],
            ..Default::default()
        };
        assert!(matches!(fit(&cfg, &[], None), Err(ModelError::Config(_))));
        assert!(matches!(
            fit(&ModelConfig::default(), &[], None),
            Err(ModelError::NoData(_))
        ));
        let cfg = ModelConfig {
            temperatures: vec![TemperatureInput {
                sensor: "head".into(),
                taus_min: vec![0.0],
            }],
            ..Default::default()
        };
        let (ev, _) = day(10, 0.5, 5);
        let e = fit(&cfg, &ev, None).unwrap_err().to_string();
        assert!(e.contains("head"), "{e}");
    }

    #[test]
    fn a_model_file_reads_back_and_a_damaged_one_is_refused() {
        let (ev, _) = day(10, 0.5, 5);
        let m = fit(&ModelConfig::default(), &ev, None).unwrap();
        let text = serde_json::to_string(&m).unwrap();
        assert_eq!(ThermalModel::from_json(&text).unwrap(), m);
        let e = ThermalModel::from_json("{}").unwrap_err().to_string();
        assert!(e.contains("not a driftwatch model"), "{e}");
        let mut other = m.clone();
        other.format = "driftwatch.thermal_model.v0".into();
        let e = ThermalModel::from_json(&serde_json::to_string(&other).unwrap())
            .unwrap_err()
            .to_string();
        assert!(e.contains("v0"), "{e}");
        let mut short = m.clone();
        short.channels[0].coef.pop();
        let e = ThermalModel::from_json(&serde_json::to_string(&short).unwrap())
            .unwrap_err()
            .to_string();
        assert!(e.contains("do not match"), "{e}");
    }
}
