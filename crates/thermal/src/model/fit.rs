//! The batch fit: each channel's posterior (weak prior, ridge by blocked cross-validation,
//! discrepancy), its learned offset walk, its held-out check, the temperature columns held to
//! the data's range, and the least squares on the inputs' changes that the model must beat.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::config::{ModelConfig, ModelError};
use super::events::Event;
use super::features::Features;
use super::fitted::{ChangeRegression, ChannelFit, MODEL_FORMAT, ThermalModel};
use super::guard::Guard;
use super::state::ChannelState;
use driftwatch_core::least_squares;

/// Each input's fastest column of `cfg`'s design row: the shortest spindle lag, the shortest
/// lag of each temperature (the temperature itself where a lag of 0 is configured).
fn fastest_columns(cfg: &ModelConfig) -> Vec<usize> {
    let argmin = |taus: &[f64]| {
        taus.iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))
            .map(|(i, _)| i)
    };
    let mut out = Vec::new();
    let mut at = 1;
    if let Some(i) = argmin(&cfg.taus_min) {
        out.push(at + i);
    }
    at += cfg.taus_min.len();
    for t in &cfg.temperatures {
        if let Some(i) = argmin(&t.taus_min) {
            out.push(at + i);
        }
        at += t.taus_min.len();
    }
    out
}

/// [`ChangeRegression`] on `obs` (time-ordered): within each run the means of the reading
/// and of the inputs are removed, inputs that do not vary within any run are left out.
fn fit_change_regression(cfg: &ModelConfig, obs: &[Obs]) -> Option<ChangeRegression> {
    let gap = driftwatch_core::units::h_to_ns(cfg.run_gap_h);
    let mut runs: Vec<&[Obs]> = Vec::new();
    let mut start = 0;
    for i in 1..=obs.len() {
        if i == obs.len() || obs[i].t_ns - obs[i - 1].t_ns > gap {
            runs.push(&obs[start..i]);
            start = i;
        }
    }
    let cols = fastest_columns(cfg);
    let mut x: Vec<Vec<f64>> = vec![Vec::new(); cols.len()];
    let mut y = Vec::new();
    for run in runs.iter().filter(|r| r.len() >= 2) {
        let m = run.len() as f64;
        let my = run.iter().map(|o| o.y).sum::<f64>() / m;
        y.extend(run.iter().map(|o| o.y - my));
        for (c, &j) in cols.iter().enumerate() {
            let mx = run.iter().map(|o| o.row[j]).sum::<f64>() / m;
            x[c].extend(run.iter().map(|o| o.row[j] - mx));
        }
    }
    let keep: Vec<usize> = (0..cols.len())
        .filter(|&c| x[c].iter().any(|v| v.abs() > 1e-9))
        .collect();
    let design = DMatrix::from_fn(y.len(), keep.len(), |i, k| x[keep[k]][i]);
    let gains = least_squares::least_squares(&design, &DVector::from_vec(y)).ok()?;
    Some(ChangeRegression {
        columns: keep.iter().map(|&c| cols[c]).collect(),
        gains: gains.iter().copied().collect(),
    })
}

/// Weak prior of the offset, um (the gains' is configured): wide against any machine.
const PRIOR_SD_OFFSET: f64 = 1e4;
/// Blocks of the time-ordered data for cross-validation.
const CV_BLOCKS: usize = 5;

/// One observation of a channel with its design row (the lag states at its time). The row is
/// shared: a cycle observes every channel at one time, and a service keeps a week of them for
/// each of its machines.
#[derive(Debug, Clone, PartialEq)]
pub struct Obs {
    pub t_ns: i64,
    pub row: Arc<DVector<f64>>,
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
                row: Arc::new(f.row()),
                y: *value,
                sigma: sigma.filter(|s| driftwatch_core::units::positive(*s)),
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

/// Posterior mean and precision matrix for weights `w` and prior precision `lambda` (the
/// Bayesian ridge of `least_squares::posterior`).
fn solve(obs: &[&Obs], w: &[f64], lambda: &[f64]) -> Option<least_squares::Posterior> {
    least_squares::posterior(obs.iter().zip(w).map(|(o, wi)| (&*o.row, o.y, *wi)), lambda).ok()
}

/// One channel's fit: the posterior on every observation, the offset walk learned from
/// them, and the held-out check that the served value starts from.
fn fit_channel(
    cfg: &ModelConfig,
    name: &str,
    obs: &[Obs],
    n: usize,
) -> Result<ChannelFit, ModelError> {
    let mut c = fit_posterior(cfg, name, obs, n)?;
    c.offset_walk_per_h = learn_walk(cfg, obs, &c);
    c.guard = holdout_guard(cfg, name, obs, n);
    c.regression = fit_change_regression(cfg, obs);
    Ok(c)
}

/// Observations the walk's likelihood needs beyond the ones that start the filter.
const MIN_WALK_SCORED: usize = 4;

/// The stated variance of an observation (0 when unknown).
fn obs_var(o: &Obs) -> f64 {
    o.sigma.map_or(0.0, |s| s * s)
}

/// The offset walk of the grid under which the channel's observations, each predicted from
/// the ones before it by the filter started from the fit's prior, are the likeliest (the
/// first ones, as many as there are parameters, only start the filter). `None` when the grid
/// is empty or too few observations are left to judge.
fn learn_walk(cfg: &ModelConfig, obs: &[Obs], fit: &ChannelFit) -> Option<f64> {
    let burn = fit.coef.len();
    if cfg.offset_walk_grid_per_h.is_empty() || obs.len() < burn + MIN_WALK_SCORED {
        return None;
    }
    let d2 = fit.discrepancy_um.powi(2);
    let mut best: Option<(f64, f64)> = None;
    for &q in &cfg.offset_walk_grid_per_h {
        let mut st = ChannelState::prior(&fit.prior_precision, d2, q / 3600.0, obs[0].t_ns);
        let mut ll = 0.0;
        for (i, o) in obs.iter().enumerate() {
            st.walk_to(o.t_ns);
            let (m, v) = st.predict_and_correct(&o.row, o.y, obs_var(o));
            let s = (v + obs_var(o)).max(1e-24);
            if i >= burn {
                ll -= 0.5 * (s.ln() + (o.y - m).powi(2) / s);
            }
        }
        // A larger walk must do better, not merely as well.
        if ll.is_finite() && best.is_none_or(|b| ll > b.0 + 1e-9) {
            best = Some((ll, q));
        }
    }
    best.map(|b| b.1)
}

/// The held-out check of a fit: the model fitted on all but the latest `holdout_share` of the
/// observations (with its own learned walk) predicts those one by one as the service would,
/// each scored before it corrects the filter. The guard it leaves holds the last value and
/// the scores, so the predictor continues from it.
fn holdout_guard(cfg: &ModelConfig, name: &str, obs: &[Obs], n: usize) -> Guard {
    let n_tail = (obs.len() as f64 * cfg.holdout_share).round() as usize;
    let n_head = obs.len() - n_tail;
    let mut g = Guard::default();
    let head = (n_tail > 0 && n_head >= 2)
        .then(|| fit_posterior(cfg, name, &obs[..n_head], n).ok())
        .flatten();
    let Some(head) = head else {
        if let Some(o) = obs.last() {
            g.observe(
                o.y,
                obs_var(o),
                (o.y, 0.0),
                (o.y, 0.0),
                o.y,
                cfg.min_scored,
                o.t_ns,
                &o.row,
                driftwatch_core::units::h_to_ns(cfg.run_gap_h),
            );
        }
        return g;
    };
    let walk = learn_walk(cfg, &obs[..n_head], &head).unwrap_or(cfg.offset_walk_per_h);
    let mut st = ChannelState::of_fit(&head, walk / 3600.0, obs[n_head - 1].t_ns);
    st.reg = fit_change_regression(cfg, &obs[..n_head]).map(Arc::new);
    st.anchoring = cfg.anchoring;
    let gap = driftwatch_core::units::h_to_ns(cfg.run_gap_h);
    // The head's last observation is only taken (the head's posterior holds it).
    for (i, o) in obs[n_head - 1..].iter().enumerate() {
        st.walk_to(o.t_ns);
        st.score_into(
            &mut g,
            (o.y, obs_var(o)),
            &o.row,
            o.t_ns,
            (cfg.min_scored, gap),
        );
        if i > 0 {
            st.correct(&o.row, o.y, obs_var(o));
        }
    }
    g
}

/// The batch posterior of one channel on `obs`.
fn fit_posterior(
    cfg: &ModelConfig,
    name: &str,
    obs: &[Obs],
    n: usize,
) -> Result<ChannelFit, ModelError> {
    let err = |m: String| channel_error(name, m);
    if obs.len() < 2 {
        return Err(err(format!(
            "{} observation(s); at least 2 needed",
            obs.len()
        )));
    }
    let p = Posterior::new(cfg, name, obs, n);
    let d2 = p.discrepancy(0.0)?;
    let w = p.weights(d2);
    // Blocked cross-validation over contiguous stretches of time, when there are enough
    // observations for each held-out block to say something (two per block); else the prior
    // alone regularises.
    let grid: &[f64] = if obs.len() >= 2 * CV_BLOCKS {
        &cfg.ridge_grid
    } else {
        &[0.0]
    };
    let best = p.best_ridge(grid, &w);
    let d2 = p.discrepancy(best.1)?;
    let w = p.weights(d2);
    let lambda = p.with_ridge(best.1);
    let post = solve(&p.all, &w, &lambda).ok_or_else(|| err("singular fit".into()))?;
    let cov = post
        .covariance()
        .map_err(|_| err("singular posterior".into()))?;
    let beta = post.mean;
    let held_to_range = held_temperature_columns(cfg, obs, &beta, &cov);
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
        chi2_dof: chi2 / p.dof,
        cv_rmse_um: best.0,
        offset_walk_per_h: None,
        guard: Guard::default(),
        regression: None,
        held_to_range,
    })
}

/// Where the falling `f` comes down to `target` in `[0, hi]` (`f(0) > target`): the high end
/// of the bracket after 80 halvings. Once the midpoint rounds to an end, no later halving can
/// move the high end (the low end always has `f > target`), so the search stops there, with
/// the value all 80 give.
fn bisect_falling(f: impl Fn(f64) -> f64, target: f64, hi: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, hi);
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if mid == lo || mid == hi {
            break;
        }
        if f(mid) > target { lo = mid } else { hi = mid }
    }
    hi
}

fn channel_error(name: &str, message: String) -> ModelError {
    ModelError::Channel {
        channel: name.to_string(),
        message,
    }
}

/// One channel's observations as [`fit_posterior`] solves them: the prior precision of each
/// parameter and the scale of each column, for any ridge factor and discrepancy.
struct Posterior<'a> {
    name: &'a str,
    obs: &'a [Obs],
    all: Vec<&'a Obs>,
    /// The prior precision of each parameter without the ridge.
    base: Vec<f64>,
    /// The mean square of each column over the data.
    ms: Vec<f64>,
    /// Whether the data determine the parameters (at least one degree of freedom), and the
    /// degrees of freedom (at least 1).
    determined: bool,
    dof: f64,
}

impl<'a> Posterior<'a> {
    fn new(cfg: &ModelConfig, name: &'a str, obs: &'a [Obs], n: usize) -> Self {
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
        // Parameters the data determine (the rest stay at their prior): at most the observations.
        let dof = obs.len() as f64 - n as f64;
        Posterior {
            name,
            obs,
            all: obs.iter().collect(),
            base,
            ms,
            determined: dof >= 1.0,
            dof: dof.max(1.0),
        }
    }

    /// The prior precisions with ridge factor `k` on the gains.
    fn with_ridge(&self, k: f64) -> Vec<f64> {
        self.base
            .iter()
            .zip(&self.ms)
            .enumerate()
            .map(|(j, (b, m))| if j == 0 { *b } else { b + k * m.max(1e-12) })
            .collect()
    }

    // Discrepancy so that chi2/dof = 1 (0 when the stated uncertainties already explain the
    // scatter): two passes are enough, the weights change little after the first.
    /// Each observation's weight with the discrepancy variance `d2` added to its own.
    fn weights(&self, d2: f64) -> Vec<f64> {
        self.obs
            .iter()
            .map(|o| {
                let v = o.sigma.map_or(0.0, |s| s * s) + d2;
                if v > 0.0 { 1.0 / v } else { 1.0 }
            })
            .collect()
    }

    /// The discrepancy that makes chi2/dof = 1 for a given ridge (0 when the stated
    /// uncertainties already explain the scatter); a few passes settle the weights.
    fn discrepancy(&self, k: f64) -> Result<f64, ModelError> {
        let obs = self.obs;
        let dof = self.dof;
        let mut d2 = 0.0;
        for _ in 0..3 {
            let beta = solve(&self.all, &self.weights(d2), &self.with_ridge(k))
                .ok_or_else(|| channel_error(self.name, "singular fit".into()))?
                .mean;
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
            if !self.determined {
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
                d2 = bisect_falling(chi, dof, r2.iter().map(|x| x.0).fold(1e-12, f64::max));
            }
        }
        Ok(d2)
    }

    /// The ridge factor of `grid` with the lowest blocked cross-validation RMSE under the
    /// weights `w`: (RMSE, factor).
    fn best_ridge(&self, grid: &[f64], w: &[f64]) -> (f64, f64) {
        let obs = self.obs;
        let blocks = CV_BLOCKS.min(obs.len());
        let lambdas: Vec<Vec<f64>> = grid.iter().map(|&k| self.with_ridge(k)).collect();
        let lambdas: Vec<&[f64]> = lambdas.iter().map(Vec::as_slice).collect();
        let mut sse = vec![0.0; grid.len()];
        let mut count = vec![0usize; grid.len()];
        for b in 0..blocks {
            let lo = b * obs.len() / blocks;
            let hi = (b + 1) * obs.len() / blocks;
            let train: Vec<(&DVector<f64>, f64, f64)> = obs[..lo]
                .iter()
                .zip(&w[..lo])
                .chain(obs[hi..].iter().zip(&w[hi..]))
                .map(|(o, wi)| (&*o.row, o.y, *wi))
                .collect();
            // Every factor of the grid on the same training rows: summed once.
            let fits = least_squares::posteriors(&train, &lambdas);
            for (g, fit) in fits.into_iter().enumerate() {
                let Ok(least_squares::Posterior { mean: beta, .. }) = fit else {
                    continue;
                };
                for o in &obs[lo..hi] {
                    sse[g] += (o.y - o.row.dot(&beta)).powi(2);
                    count[g] += 1;
                }
            }
        }
        let mut best = (f64::INFINITY, 0.0);
        for (g, &k) in grid.iter().enumerate() {
            let rmse = (sse[g] / count[g].max(1) as f64).sqrt();
            // A larger ridge must do better, not merely as well.
            if rmse < best.0 * (1.0 - 1e-9) {
                best = (rmse, k);
            }
        }
        best
    }
}

/// The temperature columns a channel's prediction holds to the range of its fit data: all of
/// them when their gains are not jointly significant (`beta_T' Sigma_TT^-1 beta_T` under the
/// chi-square's 95 % point), none otherwise. Gains fitted to noise would extrapolate that
/// noise to a hall colder or warmer than any the fit saw (a Monday morning); a response the
/// data show is extrapolated as fitted.
fn held_temperature_columns(
    cfg: &ModelConfig,
    obs: &[Obs],
    beta: &DVector<f64>,
    cov: &DMatrix<f64>,
) -> Vec<(usize, f64, f64)> {
    let first = 1 + cfg.taus_min.len();
    let n_temp: usize = cfg.temperatures.iter().map(|t| t.taus_min.len()).sum();
    if n_temp == 0 || obs.is_empty() || first + n_temp > beta.len() {
        return Vec::new();
    }
    let b = beta.rows(first, n_temp).into_owned();
    let c = cov.view((first, first), (n_temp, n_temp)).into_owned();
    let significant = driftwatch_core::least_squares::inverse_form(c, &b)
        .is_some_and(|w| w > driftwatch_core::stats::chi2_quantile(0.95, n_temp));
    if significant {
        return Vec::new();
    }
    (first..first + n_temp)
        .map(|j| {
            let (lo, hi) = obs
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), o| {
                    (lo.min(o.row[j]), hi.max(o.row[j]))
                });
            (j, lo, hi)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Served, TemperatureInput};
    use driftwatch_core::units;

    const MIN: i64 = units::NS_PER_MIN;

    /// The early stop of [`bisect_falling`] gives what all 80 halvings give, bit for bit, for
    /// chi-square sums of seeded residuals and stated variances, with answers from far inside
    /// the interval to ones so near 0 that 80 halvings do not reach them.
    #[test]
    fn the_bisection_stops_early_at_the_value_all_its_halvings_give() {
        use rand::{Rng, SeedableRng};
        // The 80 halvings, and whether the midpoint rounded to an end before the last.
        let all_80 = |f: &dyn Fn(f64) -> f64, target: f64, hi: f64| {
            let (mut lo, mut hi, mut met) = (0.0, hi, false);
            for _ in 0..80 {
                let mid = 0.5 * (lo + hi);
                met |= mid == lo || mid == hi;
                if f(mid) > target { lo = mid } else { hi = mid }
            }
            (hi, met)
        };
        let mut stopped = [0, 0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for case in 0..400 {
            let n = rng.random_range(3..60);
            let scale = 10f64.powi(rng.random_range(-12..6));
            let r2: Vec<(f64, f64)> = (0..n)
                .map(|_| {
                    let r: f64 = rng.random_range(-1.0..1.0) * scale;
                    (r * r, rng.random_range(0.0..2.0) * scale * scale * 1e-3)
                })
                .collect();
            let chi = |d2: f64| -> f64 {
                r2.iter()
                    .map(|(r, s)| if s + d2 > 0.0 { r / (s + d2) } else { 0.0 })
                    .sum()
            };
            let dof = (n as f64 * rng.random_range(0.05..0.9)).max(1.0);
            if chi(0.0) <= dof {
                continue;
            }
            let hi = r2.iter().map(|x| x.0).fold(1e-12, f64::max);
            let (want, met) = all_80(&chi, dof, hi);
            stopped[usize::from(met)] += 1;
            let got = bisect_falling(chi, dof, hi);
            assert_eq!(
                got.to_bits(),
                want.to_bits(),
                "case {case}: {got} != {want}"
            );
        }
        // Both kinds were tried: searches that stop early and ones that take all 80 steps.
        assert!(stopped[0] > 10 && stopped[1] > 10, "{stopped:?}");
    }

    #[test]
    fn least_squares_on_the_changes_takes_an_offset_per_run_and_is_served_when_it_wins() {
        let cfg = ModelConfig {
            taus_min: vec![6.0],
            temperatures: vec![TemperatureInput {
                sensor: "a".into(),
                taus_min: vec![0.0, 60.0],
            }],
            ..Default::default()
        };
        // Two runs ten hours apart, each with its own offset; y = 3 um/K of the sensor.
        let mut obs = Vec::new();
        for (run, offset) in [(0i64, 10.0), (1, -20.0)] {
            for k in 0..6 {
                let x = (k * k) as f64 * 0.5 + run as f64;
                obs.push(Obs {
                    t_ns: run * 16 * 60 * MIN + k * 30 * MIN,
                    row: Arc::new(DVector::from_vec(vec![1.0, 0.0, x, 0.7 * x])),
                    y: offset + 3.0 * x,
                    sigma: None,
                });
            }
        }
        let r = fit_change_regression(&cfg, &obs).unwrap();
        assert_eq!(r.columns, vec![2]);
        assert!((r.gains[0] - 3.0).abs() < 1e-6, "{r:?}");
        // From the last reading, the sensor's change since it.
        let to = DVector::from_vec(vec![1.0, 0.0, 14.0, 0.0]);
        assert!((r.value(20.0, &[1.0, 0.0, 13.0, 0.0], &to) - 23.0).abs() < 1e-6);
        // A guard whose model is 3 off where the regression is 0.2 off serves the regression.
        let at = |k: i64| k * 30 * MIN;
        let row = DVector::from_element(1, 1.0);
        let mut g = Guard::default();
        for k in 0..=6 {
            let y = 2.0 * k as f64;
            let reg = y + if k % 2 == 0 { 0.2 } else { -0.2 };
            g.observe(
                y,
                0.01,
                (y + 3.0, 0.5),
                (0.0, 0.1),
                reg,
                4,
                at(k),
                &row,
                i64::MAX,
            );
        }
        assert_eq!(g.source(4), Served::Regression);
        let (v, _, src) = g.serve((100.0, 0.5), (0.0, 0.1), 12.5, 4, at(7));
        assert_eq!((v, src), (12.5, Served::Regression));
        assert!(g.reason("EZ0B", 4, src).contains("least squares"));
        // Held longer than it was judged, it is stale like the last measured value.
        assert_eq!(
            g.serve((100.0, 0.5), (0.0, 0.1), 12.5, 4, at(6) + 6 * 60 * MIN)
                .2,
            Served::Model
        );
    }
}
