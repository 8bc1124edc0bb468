//! Model families that compete for one displacement channel, judged the same way on the
//! same points: the pole-basis grey box of [`crate::thermal_model`] and the textbook
//! baselines a thermal engineer would try first, persistence (the last training value held),
//! multiple linear regression on every temperature, regression on a few key temperatures
//! chosen by forward selection, and an ARX model run in simulation (free-run, multi-step)
//! mode; and the inverse-MSE combination of all but persistence. Every family is scored by
//! rolling-origin (forward-chaining) cross-validation on the training span only: at each
//! origin it is fitted on what came before (its own choices, the key sensors or the ARX
//! orders, made again inside) and predicts freely to the end of the span, with no reading
//! after the origin. The chosen family has the lowest CV error; persistence and regression
//! are among the candidates, so the choice never loses to them in CV. Its band is the CV
//! errors' quantiles by horizon ([`Bands`]), judged on each fold against the others.
//!
//! Pure: plain data in and out, no I/O.

use crate::units;
use nalgebra::{DMatrix, DVector};

use crate::least_squares::least_squares;
use crate::thermal_model::{self, Event, ModelConfig};

/// One channel on a regular grid: the latest reading and the latest value of every input
/// at each grid time (held between readings).
#[derive(Debug, Clone)]
pub struct Grid {
    pub channel: String,
    pub t_ns: Vec<i64>,
    pub y: Vec<f64>,
    /// Input names: the temperature sensors, then `spindle_rpm` when the spindle turned.
    pub names: Vec<String>,
    /// `inputs[j][k]`: input j at grid time k.
    pub inputs: Vec<Vec<f64>>,
    /// `fresh[k]`: a reading of the channel arrived since the grid time before (else `y[k]`
    /// is the last reading held). Fits and scores use fresh points only: a sensor that holds
    /// its value while the machine stands says nothing then.
    pub fresh: Vec<bool>,
}

impl Grid {
    pub fn len(&self) -> usize {
        self.t_ns.len()
    }
    pub fn is_empty(&self) -> bool {
        self.t_ns.is_empty()
    }
    /// The first grid index at or after `t_ns`.
    pub fn index_at(&self, t_ns: i64) -> usize {
        self.t_ns.partition_point(|&t| t < t_ns)
    }
}

/// Sample `channel` and the inputs every `step_ns`, from the first time the channel and
/// every input have a value. A spindle that never turned is no input (a column of zeros
/// says nothing and makes every design singular).
pub fn grid(events: &[Event], channel: &str, step_ns: i64) -> Option<Grid> {
    let sensors = thermal_model::sensors_of(events);
    let spins = events
        .iter()
        .any(|e| matches!(e, Event::Spindle { rpm, .. } if *rpm != 0.0));
    let mut names = sensors.clone();
    if spins {
        names.push("spindle_rpm".into());
    }
    let mut now: Vec<Option<f64>> = vec![None; names.len()];
    if spins {
        // The spindle is off until told otherwise.
        if let Some(last) = now.last_mut() {
            *last = Some(0.0);
        }
    }
    let mut y: Option<f64> = None;
    let step_ns = step_ns.max(1);
    let mut g = Grid {
        channel: channel.to_string(),
        t_ns: Vec::new(),
        y: Vec::new(),
        names: names.clone(),
        inputs: vec![Vec::new(); names.len()],
        fresh: Vec::new(),
    };
    let mut fresh = false;
    let mut next: Option<i64> = None;
    let mut k = 0;
    let last_t = events.last()?.t_ns();
    loop {
        // Take every event up to the next grid time (or the first event).
        let until = next.unwrap_or(events.first()?.t_ns());
        while k < events.len() && events[k].t_ns() <= until {
            match &events[k] {
                Event::Spindle { rpm, .. } if spins => {
                    if let Some(last) = now.last_mut() {
                        *last = Some(*rpm);
                    }
                }
                Event::Temperature {
                    sensor, celsius, ..
                } => {
                    if let Ok(i) = sensors.binary_search(sensor) {
                        now[i] = Some(*celsius);
                    }
                }
                Event::Observation {
                    channel: c, value, ..
                } if c == channel => {
                    y = Some(*value);
                    fresh = true;
                }
                _ => {}
            }
            k += 1;
        }
        if let (Some(v), true) = (y, now.iter().all(Option::is_some)) {
            g.t_ns.push(until);
            g.y.push(v);
            g.fresh.push(std::mem::take(&mut fresh));
            for (j, x) in now.iter().enumerate() {
                g.inputs[j].push(x.unwrap_or(0.0));
            }
        }
        let t = until.checked_add(step_ns)?;
        if t > last_t {
            break;
        }
        next = Some(t);
    }
    (!g.is_empty()).then_some(g)
}

/// The grid step for runs of a thermal test when none is given: the temperatures' median
/// sample spacing, but at least a 400th of the shortest run (a fine grid on a long test only
/// costs time; a coarse one on a short run leaves least squares on two dozen inputs with too
/// few rows to fit).
pub fn default_step_ns(runs: &[&[Event]]) -> i64 {
    let mut spacing = Vec::new();
    let mut shortest = i64::MAX;
    for r in runs {
        let t: Vec<i64> = r
            .iter()
            .filter(|e| matches!(e, Event::Temperature { .. }))
            .map(Event::t_ns)
            .collect();
        spacing.extend(t.windows(2).map(|w| w[1] - w[0]).filter(|d| *d > 0));
        if let (Some(a), Some(b)) = (t.first(), t.last()) {
            shortest = shortest.min(b - a);
        }
    }
    spacing.sort_unstable();
    let median = spacing
        .get(spacing.len() / 2)
        .copied()
        .unwrap_or(units::NS_PER_MIN);
    median.max(shortest / 400).max(1)
}

/// The families that compete.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    /// The last training reading, held.
    Persistence,
    /// Least squares on every input at the same time.
    Regression,
    /// Least squares on the inputs forward selection keeps (at most [`MAX_KEY`]).
    KeyRegression,
    /// `y_k = sum a_i y_(k-i) + sum b_jl u_j,(k-l) + c`, fitted one step ahead, run freely.
    Arx,
    /// The pole-basis grey box with its filter (`thermal_model`), as `fit` and `predict` run it.
    GreyBox,
    /// The other families but persistence, averaged with weights inversely proportional to
    /// their CV mean square error (Bates and Granger, 1969): a combination of forecasts
    /// often beats the single model a noisy CV picks, and it competes in the same CV.
    Combination,
}

impl Family {
    pub const ALL: [Family; 6] = [
        Family::Persistence,
        Family::Regression,
        Family::KeyRegression,
        Family::Arx,
        Family::GreyBox,
        Family::Combination,
    ];
    pub fn as_str(self) -> &'static str {
        match self {
            Family::Persistence => "persistence",
            Family::Regression => "regression",
            Family::KeyRegression => "key_regression",
            Family::Arx => "arx",
            Family::GreyBox => "grey_box",
            Family::Combination => "combination",
        }
    }
    pub fn parse(s: &str) -> Option<Family> {
        Family::ALL.into_iter().find(|f| f.as_str() == s)
    }
}

/// Most inputs key-temperature regression keeps.
pub const MAX_KEY: usize = 5;

/// A fitted family: what it needs to predict forward from an origin.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Fitted {
    Persistence,
    Linear {
        inputs: Vec<usize>,
        /// Intercept first, then one gain per input (on the inputs' own scale).
        coef: Vec<f64>,
    },
    Arx {
        na: usize,
        nb: usize,
        inputs: Vec<usize>,
        /// a_1..a_na, then b_j0..b_j(nb-1) per input, then c.
        theta: Vec<f64>,
    },
    /// The grey box is fitted and run on the events themselves.
    GreyBox,
    /// Each part with its weight (the weights sum to one).
    Combination {
        parts: Vec<(Fitted, f64)>,
    },
}

impl Fitted {
    /// The inputs the fit uses, by name.
    fn input_names(&self, g: &Grid) -> Vec<String> {
        match self {
            Fitted::Linear { inputs, .. } | Fitted::Arx { inputs, .. } => {
                inputs.iter().map(|&j| g.names[j].clone()).collect()
            }
            Fitted::Persistence => Vec::new(),
            Fitted::GreyBox => g.names.clone(),
            Fitted::Combination { .. } => self
                .empirical_inputs()
                .iter()
                .map(|&j| g.names[j].clone())
                .collect(),
        }
    }

    /// The grid inputs an empirical (regression or ARX) part uses: the ones whose range
    /// a combination's description names.
    fn empirical_inputs(&self) -> Vec<usize> {
        let mut out: Vec<usize> = match self {
            Fitted::Linear { inputs, .. } | Fitted::Arx { inputs, .. } => inputs.clone(),
            Fitted::Persistence | Fitted::GreyBox => Vec::new(),
            Fitted::Combination { parts } => parts
                .iter()
                .flat_map(|(f, _)| f.empirical_inputs())
                .collect(),
        };
        out.sort_unstable();
        out.dedup();
        out
    }
    pub fn describe(&self, g: &Grid) -> String {
        match self {
            Fitted::Persistence => "last value held".into(),
            Fitted::Linear { inputs, .. } => {
                format!(
                    "{} inputs: {}",
                    inputs.len(),
                    self.input_names(g).join(", ")
                )
            }
            Fitted::Arx { na, nb, inputs, .. } => format!(
                "na {na}, nb {nb}, {} inputs: {}",
                inputs.len(),
                self.input_names(g).join(", ")
            ),
            Fitted::GreyBox => "pole basis + every temperature".into(),
            Fitted::Combination { parts } => parts
                .iter()
                .map(|(f, w)| format!("{w:.2} x [{}]", f.describe(g)))
                .collect::<Vec<_>>()
                .join(" + "),
        }
    }
}

/// The inputs among `inputs` that vary over grid points `0..end`: one constant over the fit
/// data is the intercept again, and the vanishing ridge would split the intercept between
/// them, an arbitrary gain that moves the prediction when the input does.
fn varying(g: &Grid, inputs: &[usize], end: usize) -> Vec<usize> {
    let rows: Vec<usize> = (0..end.min(g.len())).collect();
    varying_on(g, inputs, &rows)
}

/// [`varying`] over the grid points `rows` (those a fit uses): a spindle that stood only
/// while the sensor held its value varies over the grid, but not over the fresh readings,
/// and there it is the intercept again.
fn varying_on(g: &Grid, inputs: &[usize], rows: &[usize]) -> Vec<usize> {
    inputs
        .iter()
        .copied()
        .filter(|&j| {
            let x = &g.inputs[j];
            rows.first().is_some_and(|&r0| {
                rows.iter()
                    .any(|&k| (x[k] - x[r0]).abs() > 1e-12 * x[r0].abs().max(1.0))
            })
        })
        .collect()
}

/// The grid points before `end` with a fresh reading: the rows a fit takes.
fn fresh_rows(g: &Grid, end: usize) -> Vec<usize> {
    (0..end.min(g.len())).filter(|&k| g.fresh[k]).collect()
}

fn fit_linear(g: &Grid, inputs: &[usize], end: usize) -> Option<Fitted> {
    let rows = fresh_rows(g, end);
    let inputs = &varying_on(g, inputs, &rows);
    let x = DMatrix::from_fn(rows.len(), inputs.len() + 1, |i, j| {
        if j == 0 {
            1.0
        } else {
            g.inputs[inputs[j - 1]][rows[i]]
        }
    });
    let y = DVector::from_iterator(rows.len(), rows.iter().map(|&k| g.y[k]));
    let coef = least_squares(&x, &y).ok()?;
    Some(Fitted::Linear {
        inputs: inputs.to_vec(),
        coef: coef.iter().copied().collect(),
    })
}

fn fit_arx(g: &Grid, na: usize, nb: usize, inputs: &[usize], end: usize) -> Option<Fitted> {
    let inputs = &varying(g, inputs, end);
    let lag = na.max(nb.saturating_sub(1));
    if end <= lag + 1 {
        return None;
    }
    let rows = end - lag;
    let p = na + nb * inputs.len() + 1;
    let x = DMatrix::from_fn(rows, p, |r, c| {
        let k = r + lag;
        if c < na {
            g.y[k - 1 - c]
        } else if c < na + nb * inputs.len() {
            let (j, l) = ((c - na) / nb, (c - na) % nb);
            g.inputs[inputs[j]][k - l]
        } else {
            1.0
        }
    });
    let y = DVector::from_fn(rows, |r, _| g.y[r + lag]);
    let theta = least_squares(&x, &y).ok()?;
    let a: Vec<f64> = theta.iter().take(na).copied().collect();
    // Run freely, the model must be stable: every root of z^na - a1 z^(na-1) - ... inside
    // the unit circle (checked for the orders used here, 1 and 2).
    let stable = match a.as_slice() {
        [a1] => a1.abs() < 1.0,
        // Jury's conditions for z^2 - a1 z - a2.
        [a1, a2] => a2.abs() < 1.0 && (1.0 - a1 - a2) > 0.0 && (1.0 + a1 - a2) > 0.0,
        _ => false,
    };
    stable.then(|| Fitted::Arx {
        na,
        nb,
        inputs: inputs.to_vec(),
        theta: theta.iter().copied().collect(),
    })
}

/// Predictions for grid indices `origin..end`, from readings before `origin` only (and the
/// inputs, which are measured as they happen).
pub fn simulate(f: &Fitted, g: &Grid, origin: usize, end: usize) -> Vec<f64> {
    let end = end.min(g.len());
    if origin == 0 || origin >= end {
        return Vec::new();
    }
    match f {
        Fitted::Persistence => vec![g.y[origin - 1]; end - origin],
        Fitted::Linear { inputs, coef } => {
            let at = |k: usize| {
                coef[0]
                    + inputs
                        .iter()
                        .enumerate()
                        .map(|(i, &j)| coef[i + 1] * g.inputs[j][k])
                        .sum::<f64>()
            };
            (origin..end).map(at).collect()
        }
        Fitted::Arx {
            na,
            nb,
            inputs,
            theta,
        } => {
            // The past outputs: measured before the origin, simulated after it.
            let mut y: Vec<f64> = g.y[..origin].to_vec();
            for k in origin..end {
                let mut v = theta[theta.len() - 1];
                for i in 0..*na {
                    v += theta[i] * y[k - 1 - i];
                }
                for (ji, &j) in inputs.iter().enumerate() {
                    for l in 0..*nb {
                        if k >= l {
                            v += theta[na + ji * nb + l] * g.inputs[j][k - l];
                        }
                    }
                }
                y.push(v);
            }
            y.split_off(origin)
        }
        Fitted::GreyBox | Fitted::Combination { .. } => Vec::new(),
    }
}

/// [`simulate`] with the grey box's own predictions for `origin..end` (`grey`, which only
/// the events can give): the grey box and a combination that holds it run too. Empty when a
/// part cannot run.
pub fn simulate_with(f: &Fitted, g: &Grid, origin: usize, end: usize, grey: &[f64]) -> Vec<f64> {
    match f {
        Fitted::GreyBox => grey.to_vec(),
        Fitted::Combination { parts } => {
            let n = end.min(g.len()).saturating_sub(origin);
            let mut sum = vec![0.0; n];
            for (part, w) in parts {
                let p = simulate_with(part, g, origin, end, grey);
                if p.len() != n {
                    return Vec::new();
                }
                sum.iter_mut().zip(&p).for_each(|(s, p)| *s += w * p);
            }
            sum
        }
        _ => simulate(f, g, origin, end),
    }
}

/// Rolling origins of the CV: this many, spread evenly (fewer on a short span).
pub const N_FOLDS: usize = 8;

/// Rolling origins over the first `end` grid points for a model used `horizon` grid steps
/// ahead of its last reading: [`N_FOLDS`] origins, each fold fitted on what comes before it
/// and predicting freely up to `horizon` steps, never past `end`. The CV judges a model at
/// the horizon it is used for, as far as the data allow: the origins run from half the span
/// to where a fold still has its whole horizon, or to three quarters of it when the horizon
/// is longer than a quarter. No fold is fitted on less than half the span: a fold fitted on
/// far less data than the model it judges misjudges it (on short warm-up runs, least squares
/// on two dozen temperatures fitted on a third of the fit lost to persistence in CV and beat
/// it on the hold-out). What the folds test is [`tested_horizon`]; a longer horizon of use is
/// beyond what the CV saw, and the choice says so.
pub fn folds(end: usize, horizon: usize) -> Vec<(usize, usize)> {
    if end < 2 {
        return Vec::new();
    }
    let horizon = horizon.max(1);
    let first = (end / 2).max(1);
    let last = end
        .saturating_sub(horizon.min((end - first) / 2).max(1))
        .max(first);
    let mut o: Vec<usize> = (0..N_FOLDS)
        .map(|i| first + (last - first) * i / (N_FOLDS - 1))
        .collect();
    o.dedup();
    o.into_iter()
        .map(|a| (a, a.saturating_add(horizon).min(end)))
        .filter(|(a, b)| a < b && *a > 0)
        .collect()
}

/// The longest horizon, in grid steps, the folds of [`folds`] test.
pub fn tested_horizon(end: usize, horizon: usize) -> usize {
    folds(end, horizon)
        .iter()
        .map(|(a, b)| b - a)
        .max()
        .unwrap_or(0)
}

/// One CV error: its fold, its horizon in grid steps after the fold's origin, its value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CvError {
    pub fold: usize,
    pub horizon: usize,
    pub e: f64,
}

/// A fold's errors on the fresh readings (`fresh` and `y` from the fold's origin).
fn fold_errors<'a>(
    fold: usize,
    p: &'a [f64],
    y: &'a [f64],
    fresh: &'a [bool],
) -> impl Iterator<Item = CvError> + 'a {
    p.iter()
        .zip(y)
        .enumerate()
        .filter(|(h, _)| fresh[*h])
        .map(move |(horizon, (p, y))| CvError {
            fold,
            horizon,
            e: p - y,
        })
}

/// The errors of a fit procedure over the folds of `0..end`; `None` when a fold could not
/// be fitted.
fn cv_errors(
    g: &Grid,
    end: usize,
    horizon: usize,
    fit: &dyn Fn(usize) -> Option<Fitted>,
) -> Option<Vec<CvError>> {
    cv_run(g, end, horizon, fit).map(|r| r.0)
}

/// [`cv_errors`], and each fold's residual at its origin: the last reading before it less
/// the fold's model there.
fn cv_run(
    g: &Grid,
    end: usize,
    horizon: usize,
    fit: &dyn Fn(usize) -> Option<Fitted>,
) -> Option<(Vec<CvError>, Vec<f64>)> {
    let mut e = Vec::new();
    let mut r0 = Vec::new();
    for (i, (o, stop)) in folds(end, horizon).into_iter().enumerate() {
        let f = fit(o)?;
        let p = simulate(&f, g, o, stop);
        e.extend(fold_errors(i, &p, &g.y[o..stop], &g.fresh[o..stop]));
        r0.push(origin_residual(&f, g, o, f64::NAN));
    }
    (!e.is_empty()).then_some((e, r0))
}

/// The residual at an origin: the last reading before grid point `origin` less what `f`
/// gives there (`grey_prev`: the grey box's value there, for a fit that holds it). 0 when it
/// cannot be had (the relaxation then adds nothing).
pub fn origin_residual(f: &Fitted, g: &Grid, origin: usize, grey_prev: f64) -> f64 {
    if origin == 0 || origin > g.len() {
        return 0.0;
    }
    let p = simulate_with(f, g, origin - 1, origin, &[grey_prev]);
    match p.first() {
        Some(v) if v.is_finite() => g.y[origin - 1] - v,
        _ => 0.0,
    }
}

/// Relaxation times the CV chooses among, hours: the residual at the origin decays
/// `exp(-t / tau)` into the prediction (none: the model's mean alone; 64 h: about holding it
/// over any horizon here).
pub const RELAX_H: [f64; 4] = [1.0, 4.0, 16.0, 64.0];

/// The weight of the origin's residual `horizon` grid points after the origin (the first
/// prediction is one step after the last reading).
pub fn relax_weight(relax_h: Option<f64>, horizon: usize, step_ns: i64) -> f64 {
    relax_h.map_or(0.0, |tau| {
        (-((horizon + 1) as f64) * step_ns as f64 / (tau * units::NS_PER_H as f64)).exp()
    })
}

fn cv_rms(e: &[CvError]) -> f64 {
    rms(&e.iter().map(|c| c.e).collect::<Vec<_>>())
}

/// Root mean square (0 for no values).
pub fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|v| v * v).sum::<f64>() / e.len().max(1) as f64).sqrt()
}

/// Forward selection of key inputs on `0..end`, by the inner rolling-origin CV of a
/// regression on them: add the input that lowers it most, stop when none lowers it by 1 %.
pub fn key_inputs(g: &Grid, end: usize, horizon: usize) -> Vec<usize> {
    let all: Vec<usize> = (0..g.names.len()).collect();
    forward_select(&all, f64::INFINITY, &|with| {
        cv_errors(g, end, horizon, &|o| fit_linear(g, with, o))
            .map_or(f64::INFINITY, |e| cv_rms(&e))
    })
}

/// Forward selection of at most [`MAX_KEY`] of `candidates`: add the one whose `score`
/// (lower is better; infinite where it cannot be had) is lowest, while it lowers the score
/// by 1 % from `start` (the score of none).
pub(crate) fn forward_select(
    candidates: &[usize],
    start: f64,
    score: &dyn Fn(&[usize]) -> f64,
) -> Vec<usize> {
    let mut chosen: Vec<usize> = Vec::new();
    let mut best = start;
    while chosen.len() < MAX_KEY {
        let step = candidates
            .iter()
            .filter(|j| !chosen.contains(j))
            .map(|&j| {
                let mut with = chosen.clone();
                with.push(j);
                (j, score(&with))
            })
            .filter(|(_, s)| s.is_finite())
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match step {
            Some((j, s)) if s < 0.99 * best => {
                chosen.push(j);
                best = s;
            }
            _ => break,
        }
    }
    chosen
}

/// Fit `family` on grid points `0..end` (its inner choices made there).
pub fn fit_family(family: Family, g: &Grid, end: usize, horizon: usize) -> Option<Fitted> {
    let all: Vec<usize> = (0..g.names.len()).collect();
    match family {
        Family::Persistence => Some(Fitted::Persistence),
        Family::Regression => fit_linear(g, &all, end),
        Family::KeyRegression => {
            let key = key_inputs(g, end, horizon);
            fit_linear(g, &key, end)
        }

        Family::Arx => {
            // Orders and inputs by the inner CV: first or second order, on the key inputs
            // or on every input.
            let key = key_inputs(g, end, horizon);
            let mut best: Option<(Fitted, f64)> = None;
            for inputs in [&key, &all] {
                if inputs.is_empty() {
                    continue;
                }
                for na in [1, 2] {
                    let nb = 2;
                    let Some(e) = cv_errors(g, end, horizon, &|o| fit_arx(g, na, nb, inputs, o))
                    else {
                        continue;
                    };
                    let s = cv_rms(&e);
                    if best.as_ref().is_none_or(|(_, b)| s < *b)
                        && let Some(f) = fit_arx(g, na, nb, inputs, end)
                    {
                        best = Some((f, s));
                    }
                }
            }
            best.map(|(f, _)| f)
        }
        Family::GreyBox => Some(Fitted::GreyBox),
        // Its weights come from the competition's CV: see `choose`.
        Family::Combination => None,
    }
}

/// The grey box's configuration for a grid's inputs: the spindle basis when the spindle
/// turned, and every temperature with the default lags.
pub fn grey_box_config(g: &Grid) -> ModelConfig {
    let spins = g.names.iter().any(|n| n == "spindle_rpm");
    let n_ref = g
        .names
        .iter()
        .position(|n| n == "spindle_rpm")
        .and_then(|j| g.inputs[j].iter().map(|v| v.abs()).reduce(f64::max))
        .filter(|m| *m > 0.0)
        .unwrap_or(1.0);
    let base = ModelConfig::default();
    ModelConfig {
        taus_min: if spins {
            base.taus_min.clone()
        } else {
            Vec::new()
        },
        n_ref_rpm: n_ref,
        temperatures: g
            .names
            .iter()
            .filter(|n| n.as_str() != "spindle_rpm")
            .map(|s| thermal_model::TemperatureInput {
                sensor: s.clone(),
                taus_min: thermal_model::default_temperature_taus(),
            })
            .collect(),
        ..base
    }
}

/// The grey box's free-run predictions for grid points `origin..stop`: fitted on the events
/// before the origin, replayed with no correction after it, the value `predict` serves.
pub fn grey_box(
    events: &[Event],
    cfg: &ModelConfig,
    g: &Grid,
    origin: usize,
    stop: usize,
) -> Option<Vec<f64>> {
    let t0 = *g.t_ns.get(origin)?;
    let t1 = *g.t_ns.get(stop.checked_sub(1)?)?;
    let until: Vec<Event> = events
        .iter()
        .filter(|e| e.t_ns() <= t1)
        .filter(|e| !matches!(e, Event::Observation { channel, .. } if *channel != g.channel))
        .cloned()
        .collect();
    let model = thermal_model::fit(cfg, &until, Some(t0 - 1)).ok()?;
    let step = g.t_ns.get(1).map_or(1, |t1| t1 - g.t_ns[0]);
    let (steps, _, _) = thermal_model::replay(&model, &until, step, t0 - 1, t0);
    // Replay steps run from the first event; take the step at or just before each grid time.
    let mut out = Vec::with_capacity(stop - origin);
    let mut s = 0;
    for &t in &g.t_ns[origin..stop] {
        while s + 1 < steps.len() && steps[s + 1].t_ns <= t {
            s += 1;
        }
        let v = steps
            .get(s)
            .and_then(|st| st.predictions.iter().find(|p| p.channel == g.channel))
            .map(|p| p.value)?;
        out.push(v);
    }
    Some(out)
}

/// Upper edges of the horizon bins of a band, hours after the last reading used: a free
/// run's error grows with the horizon, so one band for all horizons is too wide early and
/// too narrow late.
pub const BAND_EDGES_H: [f64; 4] = [1.0, 3.0, 8.0, 20.0];

/// Fewest CV errors a horizon bin needs for its own quantiles; a thinner bin takes the
/// previous bin's.
const MIN_BIN: usize = 20;

/// A band by horizon, from CV errors: in each bin the 68 % and 95 % quantiles of the
/// errors' size, never narrower than the bin before (the last bin holds every longer
/// horizon, beyond what the CV saw: there the band is extrapolated flat, and says so by
/// its hold-out coverage).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bands {
    /// Upper edge of each bin but the last, in grid steps.
    pub edges: Vec<usize>,
    pub b68: Vec<f64>,
    pub b95: Vec<f64>,
}

impl Bands {
    pub fn from_errors(errors: &[CvError], step_ns: i64) -> Bands {
        let edges: Vec<usize> = BAND_EDGES_H
            .iter()
            .map(|h| (h * units::NS_PER_H as f64 / step_ns.max(1) as f64).round() as usize)
            .collect();
        let pooled: Vec<f64> = errors.iter().map(|c| c.e).collect();
        let (mut b68, mut b95) = (Vec::new(), Vec::new());
        let mut prev = (quantile_abs(&pooled, 0.68), quantile_abs(&pooled, 0.95));
        let mut first = true;
        for i in 0..=edges.len() {
            let lo = if i == 0 { 0 } else { edges[i - 1] };
            let hi = edges.get(i).copied().unwrap_or(usize::MAX);
            let e: Vec<f64> = errors
                .iter()
                .filter(|c| c.horizon >= lo && c.horizon < hi)
                .map(|c| c.e)
                .collect();
            let here = if e.len() >= MIN_BIN {
                let q = (quantile_abs(&e, 0.68), quantile_abs(&e, 0.95));
                if first {
                    q
                } else {
                    (q.0.max(prev.0), q.1.max(prev.1))
                }
            } else {
                prev
            };
            first = false;
            b68.push(here.0);
            b95.push(here.1);
            prev = here;
        }
        Bands { edges, b68, b95 }
    }

    /// The 68 % and 95 % half-widths at `horizon` grid steps after the last reading.
    pub fn at(&self, horizon: usize) -> (f64, f64) {
        let i = self.edges.partition_point(|&e| e <= horizon);
        (
            self.b68.get(i).copied().unwrap_or(f64::NAN),
            self.b95.get(i).copied().unwrap_or(f64::NAN),
        )
    }

    /// The shares of `errors` (by horizon) within the 68 % and 95 % bands.
    pub fn coverage(&self, errors: &[(usize, f64)]) -> (f64, f64) {
        if errors.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let (mut c68, mut c95) = (0usize, 0usize);
        for &(h, e) in errors {
            let (b68, b95) = self.at(h);
            c68 += usize::from(e.abs() <= b68);
            c95 += usize::from(e.abs() <= b95);
        }
        let n = errors.len() as f64;
        (c68 as f64 / n, c95 as f64 / n)
    }
}

/// The calibration of CV bands on the CV folds themselves: each fold's errors against the
/// bands the other folds give, pooled. A band built and judged on the same errors would
/// cover its share by construction.
fn cv_coverage(errors: &[CvError], step_ns: i64) -> (f64, f64) {
    let n_folds = errors.iter().map(|c| c.fold + 1).max().unwrap_or(0);
    let (mut c68, mut c95, mut n) = (0.0, 0.0, 0usize);
    for f in 0..n_folds {
        let others: Vec<CvError> = errors.iter().filter(|c| c.fold != f).copied().collect();
        let mine: Vec<(usize, f64)> = errors
            .iter()
            .filter(|c| c.fold == f)
            .map(|c| (c.horizon, c.e))
            .collect();
        if others.is_empty() || mine.is_empty() {
            continue;
        }
        let (a, b) = Bands::from_errors(&others, step_ns).coverage(&mine);
        c68 += a * mine.len() as f64;
        c95 += b * mine.len() as f64;
        n += mine.len();
    }
    if n == 0 {
        (f64::NAN, f64::NAN)
    } else {
        (c68 / n as f64, c95 / n as f64)
    }
}

/// One family's figures on one channel.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FamilyScore {
    pub family: String,
    /// What the fit on the whole training span chose (inputs, orders).
    pub detail: String,
    /// Rolling-origin CV on the training span, RMSE.
    pub cv_rmse: f64,
    /// The 68 % and 95 % quantiles of the CV errors' size, all horizons pooled.
    pub band68: f64,
    pub band95: f64,
    /// The band by horizon the family claims (absent in model files written before it).
    #[serde(default)]
    pub bands: Option<Bands>,
    /// The bands' coverage on the CV folds, each fold against the others' bands.
    #[serde(default)]
    pub cv_cover68: Option<f64>,
    #[serde(default)]
    pub cv_cover95: Option<f64>,
    /// Hold-out (after the training span, no reading used): RMSE, largest error, and the
    /// shares within the 68 % and 95 % bands at their horizons.
    /// NaN where there is no hold-out: JSON writes it as null, and null reads back as NaN.
    #[serde(deserialize_with = "null_as_nan")]
    pub holdout_rmse: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub holdout_max: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub cover68: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub cover95: f64,
    pub chosen: bool,
    /// A combination's parts and weights.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub weights: Vec<(String, f64)>,
    /// The relaxation time the CV chose, h: the residual at the origin (the last reading
    /// less the model there) decays with it into the prediction. None: the model's mean
    /// alone.
    #[serde(default)]
    pub relax_h: Option<f64>,
}

/// A figure that may be NaN: serde_json writes NaN as null, so null reads back as NaN (a
/// model file written by `fit` without a hold-out must load again).
fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(<Option<f64> as serde::Deserialize>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// How a free run from `origin` did: `values[i]` was served at grid point `origin + i`, from the
/// readings before `origin` alone. Scored on the readings the sensor updated (a held value is
/// no reading), against holding the last reading before `origin` (persistence), with the
/// shares of errors within the bands at their horizons.
#[derive(Debug, Clone, PartialEq)]
pub struct FreeRunScore {
    /// Served minus measured, on the updated readings.
    pub errors: Vec<f64>,
    pub rmse: f64,
    pub persistence_rmse: f64,
    /// The largest |error|.
    pub max_abs: f64,
    pub within68: f64,
    pub within95: f64,
}

/// Score a free run (see [`FreeRunScore`]); `origin` must be at least 1 (a last reading).
pub fn score_free_run(g: &Grid, origin: usize, values: &[f64], bands: &Bands) -> FreeRunScore {
    let held = origin.checked_sub(1).and_then(|k| g.y.get(k)).copied();
    let mut by_horizon = Vec::new();
    let mut persistence = Vec::new();
    for (i, v) in values.iter().enumerate() {
        let k = origin + i;
        let (Some(&y), Some(true)) = (g.y.get(k), g.fresh.get(k).copied()) else {
            continue;
        };
        by_horizon.push((i, v - y));
        persistence.push(held.map_or(f64::NAN, |h| h - y));
    }
    let (within68, within95) = bands.coverage(&by_horizon);
    let errors: Vec<f64> = by_horizon.into_iter().map(|(_, e)| e).collect();
    FreeRunScore {
        rmse: rms(&errors),
        persistence_rmse: rms(&persistence),
        max_abs: errors.iter().fold(0.0f64, |m, e| m.max(e.abs())),
        errors,
        within68,
        within95,
    }
}

/// The share of errors within `band` (NaN without errors).
pub fn coverage(errors: &[f64], band: f64) -> f64 {
    if errors.is_empty() {
        return f64::NAN;
    }
    errors.iter().filter(|e| e.abs() <= band).count() as f64 / errors.len() as f64
}

fn quantile_abs(e: &[f64], q: f64) -> f64 {
    let mut a: Vec<f64> = e.iter().map(|v| v.abs()).collect();
    a.sort_by(f64::total_cmp);
    if a.is_empty() {
        return f64::NAN;
    }
    let i = ((a.len() as f64 * q).ceil() as usize).clamp(1, a.len()) - 1;
    a[i]
}

/// A family's CV errors and hold-out predictions, before scoring.
struct Run {
    family: Family,
    detail: String,
    cv: Vec<CvError>,
    hold: Vec<f64>,
    weights: Vec<(String, f64)>,
    /// Each fold's residual at its origin, and the hold-out's.
    r0: Vec<f64>,
    hold_r0: f64,
}

impl Run {
    /// The relaxation the CV prefers (none, or one of [`RELAX_H`]), applied to the CV errors
    /// and the hold-out predictions.
    fn relaxed(mut self, step_ns: i64) -> (Run, Option<f64>) {
        let with = |tau: Option<f64>| -> Vec<CvError> {
            self.cv
                .iter()
                .map(|c| CvError {
                    e: c.e
                        + self.r0.get(c.fold).copied().unwrap_or(0.0)
                            * relax_weight(tau, c.horizon, step_ns),
                    ..*c
                })
                .collect()
        };
        let best = std::iter::once(None)
            .chain(RELAX_H.iter().map(|h| Some(*h)))
            .map(|tau| (cv_rms(&with(tau)), tau))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .and_then(|b| b.1);
        self.cv = with(best);
        for (h, p) in self.hold.iter_mut().enumerate() {
            *p += self.hold_r0 * relax_weight(best, h, step_ns);
        }
        (self, best)
    }
}

/// The grey box's CV errors and hold-out predictions; `None` when a fold cannot be fitted.
fn grey_box_run(
    events: &[Event],
    cfg: &ModelConfig,
    g: &Grid,
    n_train: usize,
    horizon: usize,
) -> Option<GreyRun> {
    // Each run starts a step early: its first value, at the last reading before the origin,
    // gives the residual there.
    let mut e = Vec::new();
    let mut r0 = Vec::new();
    for (i, (o, stop)) in folds(n_train, horizon).into_iter().enumerate() {
        let p = grey_box(events, cfg, g, o - 1, stop)?;
        r0.push(g.y[o - 1] - p[0]);
        e.extend(fold_errors(i, &p[1..], &g.y[o..stop], &g.fresh[o..stop]));
    }
    if e.is_empty() {
        return None;
    }
    // No hold-out when the training span is the whole grid.
    let (hold, hold_r0) = if n_train < g.len() {
        let p = grey_box(events, cfg, g, n_train - 1, g.len())?;
        (p[1..].to_vec(), g.y[n_train - 1] - p[0])
    } else {
        (Vec::new(), 0.0)
    };
    Some(GreyRun {
        cv: e,
        hold,
        r0,
        hold_r0,
    })
}

/// The grey box's CV errors, hold-out predictions, and residuals at the origins.
struct GreyRun {
    cv: Vec<CvError>,
    hold: Vec<f64>,
    r0: Vec<f64>,
    hold_r0: f64,
}

/// The inverse-MSE combination of every run but persistence (at least two, with the same
/// folds and hold-out).
fn combine(runs: &[Run]) -> Option<Run> {
    let parts: Vec<&Run> = runs
        .iter()
        .filter(|r| r.family != Family::Persistence)
        .collect();
    let first = parts.first()?;
    if parts.len() < 2
        || parts
            .iter()
            .any(|r| r.cv.len() != first.cv.len() || r.hold.len() != first.hold.len())
    {
        return None;
    }
    let inv: Vec<f64> = parts
        .iter()
        .map(|r| 1.0 / cv_rms(&r.cv).powi(2).max(1e-12))
        .collect();
    let total: f64 = inv.iter().sum();
    let w: Vec<f64> = inv.iter().map(|v| v / total).collect();
    let mut cv = first.cv.clone();
    for (i, c) in cv.iter_mut().enumerate() {
        c.e = parts.iter().zip(&w).map(|(r, w)| w * r.cv[i].e).sum();
    }
    let hold = (0..first.hold.len())
        .map(|i| parts.iter().zip(&w).map(|(r, w)| w * r.hold[i]).sum())
        .collect();
    // Its prediction is the weighted sum, so is its residual at each origin.
    let r0 = (0..first.r0.len())
        .map(|i| {
            parts
                .iter()
                .zip(&w)
                .map(|(r, w)| w * r.r0.get(i).copied().unwrap_or(0.0))
                .sum()
        })
        .collect();
    let hold_r0 = parts.iter().zip(&w).map(|(r, w)| w * r.hold_r0).sum();
    let weights: Vec<(String, f64)> = parts
        .iter()
        .zip(&w)
        .map(|(r, w)| (r.family.as_str().to_string(), *w))
        .collect();
    Some(Run {
        family: Family::Combination,
        detail: weights
            .iter()
            .map(|(f, w)| format!("{w:.2} {f}"))
            .collect::<Vec<_>>()
            .join(" + "),
        cv,
        hold,
        weights,
        r0,
        hold_r0,
    })
}

fn score(r: Run, g: &Grid, n_train: usize) -> FamilyScore {
    let step_ns = g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]);
    let he: Vec<(usize, f64)> = r
        .hold
        .iter()
        .zip(&g.y[n_train..])
        .enumerate()
        .filter(|(h, _)| g.fresh[n_train + h])
        .map(|(h, (p, y))| (h, p - y))
        .collect();
    let bands = Bands::from_errors(&r.cv, step_ns);
    let (cover68, cover95) = bands.coverage(&he);
    let (cv68, cv95) = cv_coverage(&r.cv, step_ns);
    let pooled: Vec<f64> = r.cv.iter().map(|c| c.e).collect();
    let hold_e: Vec<f64> = he.iter().map(|x| x.1).collect();
    FamilyScore {
        family: r.family.as_str().to_string(),
        detail: r.detail,
        cv_rmse: rms(&pooled),
        band68: quantile_abs(&pooled, 0.68),
        band95: quantile_abs(&pooled, 0.95),
        bands: Some(bands),
        cv_cover68: Some(cv68),
        cv_cover95: Some(cv95),
        holdout_rmse: if he.is_empty() {
            f64::NAN
        } else {
            rms(&hold_e)
        },
        holdout_max: if he.is_empty() {
            f64::NAN
        } else {
            hold_e.iter().fold(0.0, |m: f64, e| m.max(e.abs()))
        },
        cover68,
        cover95,
        chosen: false,
        weights: r.weights,
        relax_h: None,
    }
}

/// Every family on one channel: CV on grid points before `train_end_ns` at `horizon` grid
/// steps (the horizon the model is used for), hold-out on the rest. The choice is [`Choice`].
pub fn compete(
    events: &[Event],
    g: &Grid,
    train_end_ns: i64,
    families: &[Family],
    grey: &ModelConfig,
    horizon: usize,
) -> (Vec<FamilyScore>, Choice) {
    let n_train = g.index_at(train_end_ns);
    let n = g.len();
    let mut runs = Vec::new();
    for &family in families {
        let run = match family {
            Family::Combination => continue,
            Family::GreyBox => grey_box_run(events, grey, g, n_train, horizon).map(|r| Run {
                family,
                detail: Fitted::GreyBox.describe(g),
                cv: r.cv,
                hold: r.hold,
                weights: Vec::new(),
                r0: r.r0,
                hold_r0: r.hold_r0,
            }),
            _ => cv_run(g, n_train, horizon, &|o| fit_family(family, g, o, horizon)).and_then(
                |(cv, r0)| {
                    let f = fit_family(family, g, n_train, horizon)?;
                    Some(Run {
                        family,
                        detail: f.describe(g),
                        cv,
                        hold: simulate(&f, g, n_train, n),
                        weights: Vec::new(),
                        r0,
                        hold_r0: origin_residual(&f, g, n_train, f64::NAN),
                    })
                },
            ),
        };
        runs.extend(run);
    }
    if families.contains(&Family::Combination)
        && let Some(c) = combine(&runs)
    {
        runs.push(c);
    }
    // The combination as served: with the relaxation its CV prefers. The textbook baselines
    // stay as the textbook has them; the grey box has its own offset walk, learned from the
    // data by its filter.
    let step_ns = g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]);
    let runs: Vec<(Run, Option<f64>)> = runs
        .into_iter()
        .map(|r| {
            if r.family == Family::Combination {
                r.relaxed(step_ns)
            } else {
                (r, None)
            }
        })
        .collect();
    let excursions = fold_excursions(g, n_train, horizon);
    let independent = independent_folds(&folds(n_train, horizon));
    let all: Vec<usize> = (0..g.names.len()).collect();
    let choice = Choice::of(
        &runs,
        &excursions,
        &independent,
        (tested_horizon(n_train, horizon), horizon),
        !varying_on(g, &all, &fresh_rows(g, n_train)).is_empty(),
    );
    let out = runs
        .into_iter()
        .map(|(r, relax_h)| {
            let chosen = r.family == choice.family;
            let mut s = score(r, g, n_train);
            s.relax_h = relax_h;
            s.chosen = chosen;
            if let Some(h) = relax_h {
                s.detail
                    .push_str(&format!("; the residual at the origin relaxes over {h} h"));
            }
            s
        })
        .collect();
    (out, choice)
}

/// The one-sided sign test at 5 %: the fewest wins of `n` paired comparisons (folds, or
/// later runs) that chance alone gives with probability at most 0.05; `None` when not even
/// `n` of `n` would (`n` < 5). A challenger replaces the textbook baseline only with that
/// many wins (7 of the 8 CV folds: P = 9/256 = 0.035; the folds overlap, so the true level
/// is somewhat higher, which errs towards the baseline).
pub fn sign_test_wins(n: usize) -> Option<usize> {
    // P(W >= w) for W ~ Binomial(n, 1/2), from the top down.
    let mut tail = 0.0;
    let mut c = 1.0; // C(n, k), k from n down
    let total = 2f64.powi(n as i32);
    let mut best = None;
    for k in (0..=n).rev() {
        tail += c / total;
        if tail > 0.05 {
            break;
        }
        best = Some(k);
        c = c * k as f64 / (n - k + 1) as f64;
    }
    best
}

/// How the served family was chosen for one regime of the inputs.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegimeChoice {
    pub family: Family,
    /// The family with the lowest CV error on the regime's points, and on how many folds
    /// (of those with such points) it beat the baseline.
    pub best_cv: Family,
    pub fold_wins: usize,
    pub folds: usize,
    /// CV points in the regime, and the RMSE there of the chosen family and the baseline.
    pub points: usize,
    /// NaN where a family has no CV points here (null in JSON, read back as NaN).
    #[serde(deserialize_with = "null_as_nan")]
    pub rmse: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub baseline_rmse: f64,
    pub why: String,
}

/// How the served prediction of a channel was chosen. Warm-up data leave the fit's input
/// range by design, and a model that predicts well inside what it was fitted on may not
/// outside it, so each regime has its own choice, judged on the CV points of that regime:
/// **inside** (every input within its fold's fit range, widened by [`RANGE_SLACK`] of it)
/// and **beyond** (from the first point in a fold where some input is not). At prediction
/// time the inputs are measured as they happen, so which regime a point is in is known
/// causally. A challenger replaces the textbook baseline in a regime only where it wins
/// beyond chance on folds with separate prediction windows ([`independent_folds`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Choice {
    /// The inside choice's family (the one the channel is named by).
    pub family: Family,
    /// The textbook baseline every choice starts from: least squares on every input, or
    /// persistence where that could not be fitted. A challenger replaces it only where it
    /// wins beyond chance ([`sign_test_wins`]).
    pub baseline: Family,
    pub inside: RegimeChoice,
    /// `None` where the CV folds never left their fit range.
    pub beyond: Option<RegimeChoice>,
    /// The largest excursion beyond the fit range the CV folds tested (a share of each
    /// input's range, [`excursion`]; infinite, written as null, where a forced family serves
    /// everywhere).
    #[serde(deserialize_with = "null_as_nan")]
    pub tested_excursion: f64,
    /// The horizon of use and the longest the CV folds tested, grid steps.
    pub horizon: usize,
    pub tested_horizon: usize,
    pub why: String,
}

impl RegimeChoice {
    /// The choice among `runs` on the CV points where `mask` holds.
    fn of(
        runs: &[(Run, Option<f64>)],
        baseline: Family,
        mask: &[bool],
        independent: &[usize],
        regime: &str,
    ) -> Self {
        let pick = |r: &Run| -> Vec<CvError> {
            r.cv.iter()
                .zip(mask)
                .filter(|(_, m)| **m)
                .map(|(c, _)| *c)
                .collect()
        };
        let usable: Vec<(Family, Vec<CvError>)> = runs
            .iter()
            .filter(|(r, _)| r.cv.len() == mask.len())
            .map(|(r, _)| (r.family, pick(r)))
            .filter(|(_, e)| !e.is_empty() && cv_rms(e).is_finite())
            .collect();
        let base = usable.iter().find(|(f, _)| *f == baseline);
        let best = usable
            .iter()
            .min_by(|a, b| cv_rms(&a.1).total_cmp(&cv_rms(&b.1)));
        let points = base.map_or(0, |b| b.1.len());
        let (best_cv, wins, folds) = match (best, base) {
            (Some(b), Some(base)) => {
                let (w, n) = fold_wins(&b.1, &base.1, independent);
                (b.0, w, n)
            }
            (Some(b), None) => (b.0, 0, 0),
            _ => (baseline, 0, 0),
        };
        let replaced = best_cv != baseline && sign_test_wins(folds).is_some_and(|w| wins >= w);
        let family = if replaced { best_cv } else { baseline };
        let rmse_of = |f: Family| {
            usable
                .iter()
                .find(|(g, _)| *g == f)
                .map_or(f64::NAN, |(_, e)| cv_rms(e))
        };
        let why = if best_cv == baseline {
            format!("{regime}: {} has the lowest CV error", baseline.as_str())
        } else if replaced {
            format!(
                "{regime}: {} beat the textbook baseline ({}) on {wins} of {folds} CV folds with separate prediction windows",
                best_cv.as_str(),
                baseline.as_str()
            )
        } else {
            format!(
                "{regime}: {} served; {} had the lowest CV error but beat it on {wins} of {folds} folds with separate prediction windows ({}), not beyond chance",
                baseline.as_str(),
                best_cv.as_str(),
                sign_test_wins(folds).map_or("too few folds for the test".into(), |w| format!(
                    "the bar is {w}"
                ))
            )
        };
        RegimeChoice {
            family,
            best_cv,
            fold_wins: wins,
            folds,
            points,
            rmse: rmse_of(family),
            baseline_rmse: rmse_of(baseline),
            why,
        }
    }
}

impl Choice {
    /// `regression_has_inputs`: some input varied over the fit data (else least squares is
    /// a constant, the fit data's mean, and holding the last reading is the baseline).
    fn of(
        runs: &[(Run, Option<f64>)],
        excursions: &[f64],
        independent: &[usize],
        (tested, horizon): (usize, usize),
        regression_has_inputs: bool,
    ) -> Self {
        let find = |f: Family| runs.iter().find(|(r, _)| r.family == f).map(|(r, _)| r);
        let baseline = [Family::Regression, Family::Persistence]
            .into_iter()
            .find(|f| {
                find(*f).is_some_and(|r| {
                    cv_rms(&r.cv).is_finite()
                        && (*f == Family::Persistence || regression_has_inputs)
                })
            })
            .unwrap_or(Family::Persistence);
        let inside_mask: Vec<bool> = excursions.iter().map(|x| *x <= RANGE_SLACK).collect();
        let beyond_mask: Vec<bool> = inside_mask.iter().map(|m| !m).collect();
        let inside = RegimeChoice::of(
            runs,
            baseline,
            &inside_mask,
            independent,
            "inside the fit range",
        );
        let beyond = (beyond_mask.iter().filter(|m| **m).count() >= MIN_BEYOND).then(|| {
            RegimeChoice::of(
                runs,
                baseline,
                &beyond_mask,
                independent,
                "beyond the fit range",
            )
        });
        let tested_excursion = if beyond.is_some() {
            excursions.iter().copied().fold(0.0, f64::max)
        } else {
            RANGE_SLACK
        };
        let mut why = inside.why.clone();
        match &beyond {
            Some(b) => why.push_str(&format!(
                "; {} (excursions up to {:.2} of an input's fit range tested)",
                b.why, tested_excursion
            )),
            None => why.push_str(&format!(
                "; the CV folds never left their fit range by more than {:.0} % of it: beyond that untested",
                100.0 * RANGE_SLACK
            )),
        }
        if tested < horizon && horizon < usize::MAX / 2 {
            why.push_str(&format!(
                "; the CV tested horizons up to {tested} grid steps, the model is used {horizon} ahead: beyond what the CV saw"
            ));
        }
        Choice {
            family: inside.family,
            baseline,
            inside,
            beyond,
            tested_excursion,
            horizon,
            tested_horizon: tested,
            why,
        }
    }
}

/// Fewest CV points beyond the folds' fit range for a choice there.
pub const MIN_BEYOND: usize = 10;

/// The folds whose prediction windows do not overlap, taken from the last (the one fitted
/// on the most data) backwards: overlapping folds predict the same readings from nearly the
/// same fit, so they are not separate trials for the sign test.
pub fn independent_folds(folds: &[(usize, usize)]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut before = usize::MAX;
    for (i, &(a, b)) in folds.iter().enumerate().rev() {
        if b <= before {
            out.push(i);
            before = a;
        }
    }
    out.reverse();
    out
}

/// On how many folds `a`'s mean square error is below `b`'s, of the `independent` folds
/// both have.
fn fold_wins(a: &[CvError], b: &[CvError], independent: &[usize]) -> (usize, usize) {
    let per_fold = |e: &[CvError]| {
        let mut m: std::collections::BTreeMap<usize, (f64, usize)> = Default::default();
        for c in e {
            let x = m.entry(c.fold).or_default();
            x.0 += c.e * c.e;
            x.1 += 1;
        }
        m
    };
    let (pa, pb) = (per_fold(a), per_fold(b));
    let mut wins = 0;
    let mut n = 0;
    for (f, (sa, na)) in pa.iter().filter(|(f, _)| independent.contains(f)) {
        if let Some((sb, nb)) = pb.get(f) {
            n += 1;
            wins += usize::from(sa / (*na as f64) < sb / (*nb as f64));
        }
    }
    (wins, n)
}

/// How far grid point `k` lies beyond `ranges`: the largest of each input's distance
/// outside its range, as a share of the range (0 inside; an input constant over the fit
/// data that moves counts as far beyond anything, `f64::INFINITY`).
pub fn excursion(g: &Grid, ranges: &[[f64; 2]], k: usize) -> f64 {
    excursion_by_input(g, ranges, k).0
}

/// [`excursion`] and the input that makes it (the first of equals).
pub fn excursion_by_input(g: &Grid, ranges: &[[f64; 2]], k: usize) -> (f64, usize) {
    g.inputs
        .iter()
        .zip(ranges)
        .map(|(x, &[lo, hi])| {
            let v = x[k];
            let out = (lo - v).max(v - hi).max(0.0);
            if out <= 1e-9 * lo.abs().max(hi.abs()).max(1.0) {
                0.0
            } else if hi - lo <= 0.0 {
                f64::INFINITY
            } else {
                out / (hi - lo)
            }
        })
        .enumerate()
        .fold(
            (0.0, 0),
            |best, (j, x)| if x > best.0 { (x, j) } else { best },
        )
}

/// For each CV error of [`cv_run`]'s order: the running largest [`excursion`] in its fold
/// from the origin to the point (a fold that has left its fit range counts as beyond from
/// then on, as the served prediction does). An input constant over a fold's fit data is left
/// out there: the fold's models have no gain on it, and the model served has one wherever
/// it varied in the fit data, so such a fold says nothing of how it extrapolates (it would
/// judge the regime by a never-seen input, as a spindle stage that starts after a fold's
/// origin is).
fn fold_excursions(g: &Grid, n_train: usize, horizon: usize) -> Vec<f64> {
    let mut out = Vec::new();
    for (o, stop) in folds(n_train, horizon) {
        let ranges: Vec<[f64; 2]> = input_ranges(g, o)
            .into_iter()
            .map(|[lo, hi]| {
                if hi > lo {
                    [lo, hi]
                } else {
                    [f64::NEG_INFINITY, f64::INFINITY]
                }
            })
            .collect();
        let mut run = 0.0f64;
        for k in o..stop {
            run = run.max(excursion(g, &ranges, k));
            if g.fresh[k] {
                out.push(run);
            }
        }
    }
    out
}

/// How far beyond an input's fitted range, as a share of it, an empirical family still serves.
pub const RANGE_SLACK: f64 = 0.5;

/// Each input's range over grid points `0..n_train`.
pub fn input_ranges(g: &Grid, n_train: usize) -> Vec<[f64; 2]> {
    g.inputs
        .iter()
        .map(|x| {
            let seen = &x[..n_train.min(x.len())];
            [
                seen.iter().copied().fold(f64::INFINITY, f64::min),
                seen.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            ]
        })
        .collect()
}

/// What `fit` keeps of a channel's competition: the chosen family fitted on the whole
/// training span, its CV band, and every family's CV figures.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ChannelChoice {
    pub channel: String,
    pub family: String,
    pub fitted: Fitted,
    /// The grid the family was fitted on: step and input names (a recording to predict must
    /// have the same inputs).
    pub step_ns: i64,
    pub inputs: Vec<String>,
    /// Each input's range over the fit data (see [`excursion`]).
    pub ranges: Vec<[f64; 2]>,
    pub band68: f64,
    pub band95: f64,
    /// The band by horizon (absent in model files written before it: the pooled band
    /// serves).
    #[serde(default)]
    pub bands: Option<Bands>,
    /// The relaxation of the residual at the origin (see [`FamilyScore::relax_h`]).
    #[serde(default)]
    pub relax_h: Option<f64>,
    pub scores: Vec<FamilyScore>,
    /// How the family was chosen (absent in model files written before it: there the grey
    /// box takes over where an empirical family leaves its fit range).
    #[serde(default)]
    pub choice: Option<Choice>,
    /// The family that serves beyond the fit data's range, fitted, and its relaxation.
    #[serde(default)]
    pub beyond_fitted: Option<Fitted>,
    #[serde(default)]
    pub beyond_relax_h: Option<f64>,
}

impl ChannelChoice {
    /// The band by horizon, or the pooled band at every horizon in model files written
    /// before bands by horizon.
    pub fn bands_or_pooled(&self) -> Bands {
        self.bands.clone().unwrap_or_else(|| Bands {
            edges: Vec::new(),
            b68: vec![self.band68],
            b95: vec![self.band95],
        })
    }

    /// The 68 % and 95 % half-widths `horizon` grid steps after the last reading used.
    pub fn band_at(&self, horizon: usize) -> (f64, f64) {
        self.bands
            .as_ref()
            .map_or((self.band68, self.band95), |b| b.at(horizon))
    }

    /// Whether serving from `origin` needs the grey box's predictions.
    pub fn needs_grey(&self) -> bool {
        let uses = |f: &str| f == Family::GreyBox.as_str() || f == Family::Combination.as_str();
        match &self.choice {
            None => true,
            Some(c) => {
                uses(&self.family) || c.beyond.as_ref().is_some_and(|b| uses(b.family.as_str()))
            }
        }
    }

    /// The value the regime of excursion `x` serves at hold-out index `i`.
    fn regime_value(
        &self,
        x: f64,
        i: usize,
        inside: &[f64],
        beyond: Option<&Vec<f64>>,
        held: f64,
    ) -> (f64, Served) {
        let beyond_at = beyond.and_then(|p| p.get(i)).copied();
        match self.choice.as_ref().and_then(|c| c.beyond.as_ref()) {
            _ if x <= RANGE_SLACK => (inside[i], Served::Inside(self.family.clone())),
            // No beyond choice (the CV never went beyond): the inside family, said to serve
            // where the CV never tested it (warm-up runs leave the range by design).
            None => (inside[i], Served::BeyondUntested(self.family.clone())),
            Some(b) => match beyond_at {
                Some(v) => (v, Served::Beyond(b.family)),
                // A beyond family that could not be run holds the reading.
                None => (held, Served::Held),
            },
        }
    }

    /// What the channel serves at grid points `origin..end`, from the readings before
    /// `origin` and the inputs as they happen: each point's value and what gave it. `grey`:
    /// the grey box's free run over the same points and `grey_prev` its value at the last
    /// reading (NaN where [`ChannelChoice::needs_grey`] is false). Inside the fit data's
    /// range the inside choice serves, beyond it the beyond choice ([`Choice`]), or the
    /// inside choice, said to be untested there, where the CV folds never left their range;
    /// once a point has left a regime the rest of the run stays out of it (warm-up does not
    /// come back).
    pub fn serve(
        &self,
        g: &Grid,
        origin: usize,
        end: usize,
        grey: &[f64],
        grey_prev: f64,
    ) -> Vec<(f64, Served)> {
        let end = end.min(g.len());
        if origin == 0 || origin >= end {
            return Vec::new();
        }
        let run = |f: &Fitted, relax_h: Option<f64>| -> Vec<f64> {
            let mut p = simulate_with(f, g, origin, end, grey);
            let r0 = origin_residual(f, g, origin, grey_prev);
            for (h, v) in p.iter_mut().enumerate() {
                *v += r0 * relax_weight(relax_h, h, self.step_ns);
            }
            p
        };
        let inside = run(&self.fitted, self.relax_h);
        let beyond = self
            .beyond_fitted
            .as_ref()
            .map(|f| run(f, self.beyond_relax_h));
        let held = g.y[origin - 1];
        let mut x = 0.0f64;
        (origin..end)
            .enumerate()
            .map(|(i, k)| {
                x = x.max(excursion(g, &self.ranges, k));
                // An input constant over the fit data has moved: no family learnt what it
                // does (a spindle that never stopped teaches nothing of a stop). The regime's
                // family goes on serving, said to be untested there: handing over to the grey
                // box's pole basis (which models a stop) lost to least squares on the lathe's
                // warm-up runs where it happened (docs/physics.md 2.5).
                match &self.choice {
                    // A model file from before the regimes: the grey box beyond the range.
                    None if x > RANGE_SLACK => (
                        grey.get(i).copied().unwrap_or(held),
                        Served::Beyond(Family::GreyBox),
                    ),
                    None => (inside[i], Served::Inside(self.family.clone())),
                    Some(_) => {
                        let (v, s) = self.regime_value(x, i, &inside, beyond.as_ref(), held);
                        if x.is_infinite() {
                            let s = match s {
                                Served::BeyondUntested(f) => Served::Inside(f),
                                s => s,
                            };
                            (v, Served::Untested(Box::new(s)))
                        } else {
                            (v, s)
                        }
                    }
                }
            })
            .collect()
    }
}

/// The sources of a served run in words: the first, then each change with its time (h
/// after the run's first grid point).
pub fn describe_served(served: &[(f64, Served)], g: &Grid, origin: usize) -> String {
    let mut out: Vec<String> = Vec::new();
    let mut last: Option<&Served> = None;
    for (i, (_, s)) in served.iter().enumerate() {
        if last != Some(s) {
            let h = units::ns_to_h(g.t_ns[origin + i] - g.t_ns[0]);
            out.push(if last.is_none() {
                s.to_string()
            } else {
                format!("{s} from {h:.2} h")
            });
            last = Some(s);
        }
    }
    out.join(", then ")
}

/// What gave a served value.
#[derive(Debug, Clone, PartialEq)]
pub enum Served {
    /// The inside choice (the channel's family), inputs within the fit data's range.
    Inside(String),
    /// The beyond choice, some input beyond the fit data's range.
    Beyond(Family),
    /// The inside choice beyond the fit data's range, where the CV folds never went (no
    /// beyond choice could be made).
    BeyondUntested(String),
    /// What the regime serves, where an input constant over the fit data has moved.
    Untested(Box<Served>),
    /// The last reading held: the family for the regime could not be run.
    Held,
}

impl std::fmt::Display for Served {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Served::Inside(family) => write!(f, "{family}"),
            Served::Beyond(family) => write!(f, "{} (beyond the fit range)", family.as_str()),
            Served::BeyondUntested(family) => write!(
                f,
                "{family} (beyond the fit range, further than the CV folds went: untested)"
            ),
            Served::Untested(s) => write!(
                f,
                "{s} (untested: an input constant over the fit data moved)"
            ),
            Served::Held => write!(
                f,
                "last reading held (the family for the regime could not be run)"
            ),
        }
    }
}

/// A scored family fitted on grid points `0..end` (a combination with its CV weights), its
/// inner choices made by CV at `horizon`.
pub fn fit_scored(score: &FamilyScore, g: &Grid, end: usize, horizon: usize) -> Option<Fitted> {
    match Family::parse(&score.family)? {
        Family::Combination => {
            let mut parts = Vec::new();
            for (name, w) in &score.weights {
                parts.push((fit_family(Family::parse(name)?, g, end, horizon)?, *w));
            }
            Some(Fitted::Combination { parts })
        }
        family => fit_family(family, g, end, horizon),
    }
}

/// Run the competition on the training span (`train_end_ns`: all of the grid when it lies
/// beyond it) for a model used `horizon` grid steps ahead, and keep the chosen family, or
/// `force` it. `None` when nothing could be fitted.
pub fn choose(
    events: &[Event],
    g: &Grid,
    train_end_ns: i64,
    families: &[Family],
    grey: &ModelConfig,
    force: Option<Family>,
    horizon: usize,
) -> Option<ChannelChoice> {
    let (scores, mut choice) = compete(events, g, train_end_ns, families, grey, horizon);
    let pick = match force {
        Some(f) => {
            // A forced family serves in every regime.
            choice.why = format!(
                "{} forced (the CV would serve {})",
                f.as_str(),
                choice.family.as_str()
            );
            choice.family = f;
            choice.inside.family = f;
            choice.beyond = Some(RegimeChoice {
                family: f,
                ..choice.inside.clone()
            });
            choice.tested_excursion = f64::INFINITY;
            scores.iter().find(|s| s.family == f.as_str())?
        }
        None => scores.iter().find(|s| s.chosen)?,
    };
    let n_train = g.index_at(train_end_ns);
    let fitted = fit_scored(pick, g, n_train, horizon)?;
    let ranges = input_ranges(g, n_train);
    let beyond = choice
        .beyond
        .as_ref()
        .and_then(|b| scores.iter().find(|s| s.family == b.family.as_str()));
    let beyond_fitted = beyond.and_then(|s| fit_scored(s, g, n_train, horizon));
    Some(ChannelChoice {
        channel: g.channel.clone(),
        family: pick.family.clone(),
        fitted,
        step_ns: g.t_ns.get(1).map_or(1, |t| t - g.t_ns[0]),
        inputs: g.names.clone(),
        ranges,
        band68: pick.band68,
        band95: pick.band95,
        bands: pick.bands.clone(),
        relax_h: pick.relax_h,
        beyond_relax_h: beyond.and_then(|s| s.relax_h),
        scores,
        choice: Some(choice),
        beyond_fitted,
    })
}

#[cfg(test)]
mod tests {

    /// A spindle that stood only while the sensor held its value: over the fresh readings
    /// least squares fits on, it never moved, and it gets no gain (before, it took an
    /// arbitrary share of the intercept, and a later speed doubled that into the prediction).
    #[test]
    fn an_input_that_moved_only_between_fresh_readings_gets_no_gain() {
        let n = 40;
        let temp: Vec<f64> = (0..n).map(|k| 20.0 + 0.1 * k as f64).collect();
        let stood = |k: usize| (15..25).contains(&k);
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..n as i64).map(|k| k * MIN).collect(),
            y: temp.iter().map(|t| 5.0 + 2.0 * (t - 20.0)).collect(),
            names: vec!["t".into(), "spindle_rpm".into()],
            inputs: vec![
                temp.clone(),
                (0..n)
                    .map(|k| if stood(k) { 0.0 } else { 1000.0 })
                    .collect(),
            ],
            fresh: (0..n).map(|k| !stood(k)).collect(),
        };
        let f = fit_family(Family::Regression, &g, n, 10).unwrap();
        let Fitted::Linear { inputs, coef } = &f else {
            panic!("{f:?}")
        };
        assert_eq!(inputs, &vec![0], "{f:?}");
        assert!((coef[1] - 2.0).abs() < 1e-6, "{f:?}");
        // At twice the speed the prediction follows the temperature alone.
        let mut h = g.clone();
        h.inputs[1].iter_mut().for_each(|v| *v = 2000.0);
        let p = simulate(&f, &h, n - 1, n);
        assert!((p[0] - h.y[n - 1]).abs() < 1e-4, "{p:?}");
    }

    /// An input that leaves the fit data's range further than any CV fold went: the inside
    /// family goes on serving, and says it is untested there.
    #[test]
    fn beyond_what_the_cv_tested_the_served_value_says_untested() {
        let n = 300;
        let u: Vec<f64> = (0..n)
            .map(|k| {
                if k < 200 {
                    (k as f64 / 10.0).sin()
                } else {
                    1.0 + 0.05 * (k - 200) as f64
                }
            })
            .collect();
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..n as i64).map(|k| k * MIN).collect(),
            y: u.iter().map(|v| 2.0 * v).collect(),
            names: vec!["u".into()],
            inputs: vec![u.clone()],
            fresh: vec![true; n],
        };
        let ev: Vec<Event> = Vec::new();
        let fams = [Family::Persistence, Family::Regression];
        let c = choose(&ev, &g, 200 * MIN, &fams, &grey_box_config(&g), None, 100).unwrap();
        assert!(
            c.choice.as_ref().unwrap().beyond.is_none(),
            "{:?}",
            c.choice
        );
        let served = c.serve(&g, 200, n, &[f64::NAN; 100], f64::NAN);
        // The range is [-1, 1]: past u = 2 (k = 220) the excursion exceeds half of it.
        assert!(matches!(served[5].1, Served::Inside(_)), "{:?}", served[5]);
        assert!(
            matches!(served[40].1, Served::BeyondUntested(_)),
            "{:?}",
            served[40]
        );
        assert!(
            (served[40].0 - 2.0 * u[240]).abs() < 1e-6,
            "{:?}",
            served[40]
        );
        let text = describe_served(&served, &g, 200);
        assert!(text.contains("further than the CV folds went"), "{text}");
    }

    #[test]
    fn a_choice_round_trips_through_json_with_figures_it_could_not_have() {
        let ev = plant(600, 2.0);
        let g = grid(&ev, "d", 5 * MIN).unwrap();
        let fams = [Family::Persistence, Family::Regression];
        let mut c = choose(&ev, &g, 400 * MIN, &fams, &grey_box_config(&g), None, 12).unwrap();
        let ch = c.choice.as_mut().unwrap();
        ch.inside.rmse = f64::NAN;
        ch.tested_excursion = f64::INFINITY;
        let text = serde_json::to_string(&c).unwrap();
        let back: ChannelChoice = serde_json::from_str(&text).unwrap();
        assert_eq!(back.family, c.family);
        assert!(back.choice.unwrap().inside.rmse.is_nan());
    }

    #[test]
    fn a_score_without_a_hold_out_round_trips_through_json() {
        let score = FamilyScore {
            family: "grey_box".into(),
            detail: String::new(),
            cv_rmse: 1.0,
            band68: 1.0,
            band95: 2.0,
            bands: None,
            cv_cover68: None,
            cv_cover95: None,
            holdout_rmse: f64::NAN,
            holdout_max: f64::NAN,
            cover68: f64::NAN,
            cover95: f64::NAN,
            chosen: true,
            weights: Vec::new(),
            relax_h: None,
        };
        let text = serde_json::to_string(&score).unwrap();
        assert!(text.contains("\"holdout_rmse\":null"), "{text}");
        let back: FamilyScore = serde_json::from_str(&text).unwrap();
        assert!(back.holdout_rmse.is_nan() && back.cover95.is_nan());
        assert_eq!(back.cv_rmse, 1.0);
    }
    use super::*;

    /// A free run is scored on the updated readings only, against the last reading before the
    /// origin held, each error judged by the band of its horizon.
    #[test]
    fn a_free_run_is_scored_on_updated_readings_with_the_band_of_each_horizon() {
        let g = Grid {
            channel: "d".into(),
            t_ns: (0..6).map(|k| k * MIN).collect(),
            y: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            names: vec![],
            inputs: vec![],
            // Index 4 holds the reading before it: not scored, whatever was served there.
            fresh: vec![true, true, true, true, false, true],
        };
        let bands = Bands {
            edges: vec![1],
            b68: vec![0.6, 0.01],
            b95: vec![1.0, 0.5],
        };
        let s = score_free_run(&g, 2, &[2.5, 3.2, 40.0, 5.0], &bands);
        assert_eq!(s.errors.len(), 3, "{s:?}");
        assert!(
            (s.rmse - ((0.25 + 0.04) / 3.0f64).sqrt()).abs() < 1e-12,
            "{s:?}"
        );
        // Holding y[1] = 1: errors -1, -2, -4.
        assert!((s.persistence_rmse - 7.0f64.sqrt()).abs() < 1e-12, "{s:?}");
        assert!((s.max_abs - 0.5).abs() < 1e-12, "{s:?}");
        // 0.5 at horizon 0 is within 0.6; 0.2 at horizon 1 is not within 0.01 but within 0.5.
        assert!((s.within68 - 2.0 / 3.0).abs() < 1e-12, "{s:?}");
        assert!((s.within95 - 1.0).abs() < 1e-12, "{s:?}");
    }

    const MIN: i64 = units::NS_PER_MIN;

    /// A first-order plant driven by one temperature, another temperature that is noise,
    /// sampled every minute.
    fn plant(n: usize, gain: f64) -> Vec<Event> {
        let mut ev = Vec::new();
        let mut x = 0.0;
        let mut rng = 12345u64;
        let mut noise = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 33) as f64 / (1u64 << 31) as f64) - 0.5
        };
        for k in 0..n {
            let t = k as i64 * MIN;
            let drive = 20.0 + 5.0 * ((k as f64) / 300.0).sin();
            x += (gain * (drive - 20.0) - x) / 60.0;
            ev.push(Event::Temperature {
                t_ns: t,
                sensor: "drive".into(),
                celsius: drive,
            });
            ev.push(Event::Temperature {
                t_ns: t,
                sensor: "other".into(),
                celsius: 20.0 + noise(),
            });
            ev.push(Event::Observation {
                t_ns: t,
                channel: "d".into(),
                value: x + 0.05 * noise(),
                sigma: None,
            });
        }
        ev
    }

    #[test]
    fn the_grid_holds_each_value_and_leaves_out_a_spindle_that_never_turned() {
        let mut ev = plant(30, 2.0);
        ev.push(Event::Spindle { t_ns: 0, rpm: 0.0 });
        ev.sort_by_key(|e| e.t_ns());
        let g = grid(&ev, "d", 5 * MIN).unwrap();
        assert_eq!(g.names, ["drive", "other"]);
        assert_eq!(g.len(), 6);
        assert_eq!(g.t_ns[1], 5 * MIN);
        assert!(grid(&ev, "nothing", MIN).is_none());
    }

    #[test]
    fn an_excursion_is_a_share_of_the_fit_range_and_names_its_input() {
        let g = Grid {
            channel: "d".into(),
            t_ns: vec![0, 1, 2],
            y: vec![0.0; 3],
            names: vec!["a".into(), "b".into(), "c".into()],
            inputs: vec![vec![20.0, 21.0, 23.0], vec![5.0, 5.0, 2.0], vec![1.0; 3]],
            fresh: vec![true; 3],
        };
        let ranges = input_ranges(&g, 2);
        assert_eq!(ranges, [[20.0, 21.0], [5.0, 5.0], [1.0, 1.0]]);
        assert_eq!(excursion_by_input(&g, &ranges, 1), (0.0, 0));
        // a is 2 of its range beyond it; b, constant over the fit data, moved: infinitely far.
        assert_eq!(excursion_by_input(&g, &ranges, 2), (f64::INFINITY, 1));
        let no_b = [ranges[0], [f64::NEG_INFINITY, f64::INFINITY], ranges[2]];
        assert_eq!(excursion_by_input(&g, &no_b, 2), (2.0, 0));
    }

    #[test]
    fn folds_with_overlapping_windows_are_one_trial() {
        assert_eq!(
            independent_folds(&[(0, 10), (5, 15), (10, 20), (15, 25)]),
            [1, 3]
        );
        assert_eq!(independent_folds(&[(0, 4), (4, 8), (8, 12)]), [0, 1, 2]);
        assert_eq!(independent_folds(&folds(96, 72)).len(), 1);
    }

    #[test]
    fn the_sign_test_asks_for_wins_chance_gives_under_five_percent() {
        assert_eq!(sign_test_wins(8), Some(7));
        assert_eq!(sign_test_wins(5), Some(5));
        assert_eq!(sign_test_wins(4), None);
        assert_eq!(sign_test_wins(10), Some(9));
        assert_eq!(sign_test_wins(20), Some(15));
    }

    #[test]
    fn folds_chain_forward_and_cover_the_second_half() {
        // A short horizon: origins from half the span to where the horizon still fits.
        assert_eq!(
            folds(80, 8),
            [40, 44, 49, 53, 58, 62, 67, 72].map(|o| (o, o + 8))
        );
        // A horizon longer than a quarter of the span: from half to three quarters, each
        // fold to the end.
        let long = folds(96, 72);
        assert_eq!(long.first(), Some(&(48, 96)));
        assert_eq!(long.last(), Some(&(72, 96)));
        assert!(long.iter().all(|f| f.1 == 96), "{long:?}");
        assert_eq!(tested_horizon(96, 72), 48);
        assert_eq!(tested_horizon(80, 8), 8);
        assert!(folds(1, 5).is_empty());
    }

    /// On a lagged plant the free-run ARX beats regression at the same time, both beat
    /// persistence, key selection finds the driving sensor, and the CV choice is ARX.
    #[test]
    fn the_family_that_matches_the_plant_wins_the_cross_validation() {
        let ev = plant(3000, 2.0);
        let g = grid(&ev, "d", 5 * MIN).unwrap();
        let n_train = g.index_at(2000 * MIN);
        assert_eq!(key_inputs(&g, n_train, 12), [0]);
        let s = compete(
            &ev,
            &g,
            2000 * MIN,
            &[
                Family::Persistence,
                Family::Regression,
                Family::KeyRegression,
                Family::Arx,
            ],
            &grey_box_config(&g),
            // An hour ahead: the second half of the fit holds eight separate windows.
            12,
        )
        .0;
        let by = |f: Family| s.iter().find(|x| x.family == f.as_str()).unwrap();
        let arx = by(Family::Arx);
        assert!(arx.chosen, "{s:#?}");
        assert!(
            arx.holdout_rmse < 0.2 * by(Family::Regression).holdout_rmse,
            "{s:#?}"
        );
        assert!(by(Family::Regression).holdout_rmse < by(Family::Persistence).holdout_rmse);
        // Its band, from the CV errors, covers about what it claims on the hold-out.
        assert!(arx.cover95 > 0.8, "{arx:?}");
    }

    /// Errors that grow with the horizon get a band that grows with it; the band from one
    /// fold's errors, judged on another fold like it, covers about its share.
    #[test]
    fn bands_widen_with_the_horizon_and_are_judged_on_other_folds() {
        let step = 5 * MIN;
        let mut rng = 7u64;
        let mut errors = Vec::new();
        for fold in 0..4 {
            for horizon in 0..300 {
                rng = rng
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = ((rng >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0;
                errors.push(CvError {
                    fold,
                    horizon,
                    e: u * (1.0 + horizon as f64 / 12.0),
                });
            }
        }
        let b = Bands::from_errors(&errors, step);
        // Edges at 1, 3, 8 and 20 h on a 5-min grid.
        assert_eq!(b.edges, [12, 36, 96, 240]);
        assert!(b.b68.windows(2).all(|w| w[0] <= w[1]), "{b:?}");
        assert!(b.at(0).0 < 0.5 * b.at(200).0, "{b:?}");
        assert!(b.at(0).0 < b.at(0).1);
        // Uniform errors: the 68 % quantile of |u| is 0.68 of the half-width.
        let (c68, c95) = cv_coverage(&errors, step);
        assert!(
            (c68 - 0.68).abs() < 0.05 && (c95 - 0.95).abs() < 0.03,
            "{c68} {c95}"
        );
    }

    /// Two runs with opposite errors: the inverse-MSE combination has the smaller CV error,
    /// weights that sum to one, and leaves persistence out.
    #[test]
    fn the_combination_weighs_by_cv_error_and_leaves_persistence_out() {
        let cv = |scale: f64| -> Vec<CvError> {
            (0..40)
                .map(|h| CvError {
                    fold: h / 20,
                    horizon: h % 20,
                    e: scale * if h % 2 == 0 { 1.0 } else { -1.0 },
                })
                .collect()
        };
        let run = |family, scale: f64| Run {
            family,
            detail: String::new(),
            cv: cv(scale),
            hold: vec![scale; 5],
            weights: Vec::new(),
            r0: vec![scale, scale],
            hold_r0: scale,
        };
        let runs = vec![
            run(Family::Persistence, 0.1),
            run(Family::Regression, 1.0),
            run(Family::Arx, -2.0),
        ];
        let c = combine(&runs).unwrap();
        let w: Vec<f64> = c.weights.iter().map(|x| x.1).collect();
        assert_eq!(c.weights[0].0, "regression");
        assert_eq!(c.weights.len(), 2);
        assert!(
            (w[0] - 0.8).abs() < 1e-12 && (w[1] - 0.2).abs() < 1e-12,
            "{w:?}"
        );
        // 0.8 * 1 + 0.2 * (-2) = 0.4 on every point.
        assert!((cv_rms(&c.cv) - 0.4).abs() < 1e-12);
        assert!(c.hold.iter().all(|h| (h - 0.4).abs() < 1e-12));
        assert!(combine(&runs[..2]).is_none());
    }

    /// A model off by its origin's residual for hours: the CV holds the residual (the longest
    /// relaxation); a residual that says nothing of what follows is not carried at all.
    #[test]
    fn the_cv_chooses_how_long_the_residual_at_the_origin_lasts() {
        let step = 5 * MIN;
        let run = |e: &dyn Fn(usize, usize) -> f64, r0: Vec<f64>| Run {
            family: Family::Combination,
            detail: String::new(),
            cv: (0..2)
                .flat_map(|fold| (0..100).map(move |horizon| (fold, horizon)))
                .map(|(fold, horizon)| CvError {
                    fold,
                    horizon,
                    e: e(fold, horizon),
                })
                .collect(),
            hold: vec![0.0; 3],
            weights: Vec::new(),
            r0,
            hold_r0: 1.0,
        };
        // The model is 2 um low (fold 0) or 1 um high (fold 1) throughout, and the last
        // reading said so.
        let (held, tau) =
            run(&|f, _| if f == 0 { -2.0 } else { 1.0 }, vec![2.0, -1.0]).relaxed(step);
        assert_eq!(tau, Some(64.0));
        assert!(cv_rms(&held.cv) < 0.2, "{:?}", &held.cv[..3]);
        assert!(held.hold.iter().all(|p| (p - 1.0).abs() < 0.01));
        // Errors that alternate whatever the residual was.
        let (plain, tau) =
            run(&|_, h| if h % 2 == 0 { 1.0 } else { -1.0 }, vec![3.0, -3.0]).relaxed(step);
        assert_eq!(tau, None);
        assert_eq!(plain.hold, vec![0.0; 3]);
    }

    #[test]
    fn an_unstable_arx_is_not_run() {
        // A growing series: the one-step fit has a pole outside the unit circle.
        let mut g = Grid {
            channel: "d".into(),
            t_ns: (0..50).collect(),
            y: (0..50).map(|k| 1.1f64.powi(k)).collect(),
            names: vec!["u".into()],
            inputs: vec![vec![0.0; 50]],
            fresh: vec![true; 50],
        };
        g.inputs[0][3] = 1.0;
        assert!(fit_arx(&g, 1, 2, &[0], 50).is_none());
    }
}
