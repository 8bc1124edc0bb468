//! What the final model leaves, located and made a term (docs/physics.md 4.6.2, "Located
//! term"). The onset search ties a late drift to a temperature; that drift is then a term of
//! the channel's model like any other: the temperature's change since the onset,
//! `(T(t) - T(t_on)) 1[t >= t_on]`, or the same through a first-order lag, fitted and judged
//! by the forward selection's own rules (whitened delta-BIC against a surrogate bar that
//! replays this search, |t|, the rolling origins, the footprint, the held-out veto). Where
//! the recording cannot confirm it, the reason is named (too little after the onset, a drift
//! that the baseline's warm-up or any ramp fits as well, a sensor that cannot be told from
//! another) with the recording that would split it. Without an onset, a temperature that follows the residual's largest
//! departure is tried un-gated, with the same lags.

use super::scoring::ColumnScorer;
use super::{
    Design, DisplacementOptions, Judged, ModelInput, Term, judge_column, locate_departure,
    locate_onset,
};
use rand::SeedableRng;
use serde::Serialize;

/// Lags of the located temperature, min (0: the temperature itself). A lag is kept only when
/// it earns its parameter by BIC.
pub const LOCATED_TAUS_MIN: [f64; 4] = [0.0, 30.0, 120.0, 480.0];
/// A candidate whose correlation with a ramp over the span it is claimed on exceeds this is
/// confounded with the ramp: a drift of anything would fit as well.
pub const RAMP_R: f64 = 0.95;
/// Hours after the onset that a rolling origin's fit, and the held-out end, need to judge an
/// onset-gated term (a fit that sees less cannot estimate its gain).
pub const MIN_AFTER_ONSET_H: f64 = 2.0;
/// Where the window of the later located search starts, as a share of the training span:
/// its last 40 %. Inside the span the rolling origins judge (from its middle on), and late
/// enough that the window's own offset is not the end of an earlier warm-up: at the middle
/// (0.5) the 78-h spindle run's later onset landed at 23 h, in the rise before the decline
/// that starts near 29 h; the located bench gave the same false terms at both shares.
pub const LATE_WINDOW_SHARE: f64 = 0.6;
/// A departure is tied to a temperature (for an un-gated term) when it follows it this well.
const MIN_DRIVER_R: f64 = 0.5;
/// An onset is placed when its drift beats no change by this delta-BIC on the residual's
/// independent samples (positive evidence): the term it gates must still clear the
/// forward selection's rules, and the surrogate bar replays this same rule, so placing it
/// readily costs no false terms, while a stricter tie would leave a late drift un-gated.
const MIN_ONSET_DELTA_BIC: f64 = 2.0;

/// Why a located term is not confirmed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NotConfirmed {
    /// The recording holds too little after the onset for the rolling origins or the
    /// held-out end to judge the term.
    TooShort,
    /// The candidate moves with the baseline's warm-up (its spindle mode, or the thermal
    /// base) over the span it is claimed on (|r| > [`RAMP_R`]): a hall ramped while the
    /// machine warms up.
    ConfoundedWithWarmUp,
    /// The candidate moves with time over the span it is claimed on (|r| > [`RAMP_R`]).
    ConfoundedWithRamp,
    /// Another sensor explains it within delta-BIC 10 and the term failed a rule.
    ConfoundedWithSensor,
    /// It failed a rule, and nothing above explains why: the data do not support it.
    NotSupported,
}

/// The located drift made a term: the candidate chosen, its figures against the final model
/// of the forward selection, and whether it joined that model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LocatedTerm {
    pub sensor: String,
    /// First-order lag of the temperature, min (0: none).
    pub lag_min: f64,
    /// The onset, h from the start (located on the training part); none: un-gated.
    pub onset_h: Option<f64>,
    pub term: String,
    pub gain_um_per_k: f64,
    pub sigma_um_per_k: f64,
    pub t: f64,
    /// Whitened delta-BIC of adding it to the final model, the onset and the lag counted as
    /// parameters, and the bar it must clear (what the same search reaches on
    /// phase-randomised temperatures).
    pub delta_bic: f64,
    pub bar: f64,
    pub blocks_improved: usize,
    pub blocks: usize,
    /// Held-out RMS of the final model without the term and with it, um.
    pub heldout_before_um: f64,
    pub heldout_after_um: f64,
    /// Correlation of the candidate with a ramp from the onset (with time, un-gated) over
    /// every reading from the onset on.
    pub ramp_r: f64,
    /// Correlation of the candidate with the baseline's warm-up column (the spindle mode, or
    /// the thermal base) over the same readings; none when the baseline is the offset alone.
    pub warmup_r: Option<f64>,
    /// Other sensors within delta-BIC 10 of it, in the same shape (best first, at most 3).
    pub comparable: Vec<(String, f64)>,
    /// Held-out RMS of the final model with the same term on each sensor instead (the same
    /// onset and lag), best first, um: read beside the tie, not a rule.
    pub heldout_by_sensor: Vec<(String, f64)>,
    pub accepted: bool,
    /// The rule it failed, if any.
    pub rule: Option<String>,
    /// Why it is not confirmed (none when accepted).
    pub reason: Option<NotConfirmed>,
    /// The recording that would confirm or split it.
    pub split_by: Option<String>,
    pub statement: String,
    /// The candidate on every thinned reading (to add it to the final model).
    #[serde(skip)]
    pub x: Vec<f64>,
}

/// `x` (at times `t`, min) through a first-order lag of `tau` min, the input held between
/// samples (exact zero-order hold), started at the first value.
fn lagged(t: &[f64], x: &[f64], tau: f64) -> Vec<f64> {
    if tau <= 0.0 || x.is_empty() {
        return x.to_vec();
    }
    let mut y = x[0];
    let mut out = Vec::with_capacity(x.len());
    out.push(y);
    for i in 1..x.len() {
        y += (x[i - 1] - y) * (1.0 - (-(t[i] - t[i - 1]) / tau).exp());
        out.push(y);
    }
    out
}

/// `x`'s change since row `k`, zero before it.
fn gated(x: &[f64], k: Option<usize>) -> Vec<f64> {
    match k {
        None => x.to_vec(),
        Some(k) => (0..x.len())
            .map(|i| if i >= k { x[i] - x[k] } else { 0.0 })
            .collect(),
    }
}

/// Other sensors that follow the residual `rt` within delta-BIC 10 of sensor `s`, in its
/// shape (gated at `gate`), on the onset search's own scale: an offset and the temperature's
/// change, the samples counted as `n (1 - r) / (1 + r)` independent ones (`r` the lag-1
/// autocorrelation `s` leaves). The whitened score would not do: it rewards a sensor for
/// whatever fast swing of the residual it also carries, not for following the drift. Best
/// first (their delta-BIC over no change), at most 3.
fn comparable(
    rt: &[f64],
    temps: &[(String, Vec<f64>)],
    s: usize,
    gate: Option<usize>,
) -> Vec<(String, f64)> {
    let n = rt.len() as f64;
    let x = gated(&temps[s].1, gate);
    let rho = {
        let (mx, mr) = (x.iter().sum::<f64>() / n, rt.iter().sum::<f64>() / n);
        let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
        let sxr: f64 = x.iter().zip(rt).map(|(a, b)| (a - mx) * (b - mr)).sum();
        let gain = if sxx > 0.0 { sxr / sxx } else { 0.0 };
        let left: Vec<f64> = x
            .iter()
            .zip(rt)
            .map(|(a, b)| b - mr - gain * (a - mx))
            .collect();
        super::ar1(&left).clamp(0.0, 0.99)
    };
    let n_eff = n * (1.0 - rho) / (1.0 + rho);
    let sse0 = super::sse_with(rt, &vec![0.0; rt.len()]);
    let score = |x: &[f64]| {
        n_eff * (sse0 / super::sse_with(rt, x).max(1e-300)).ln() - 2.0 * n_eff.max(1.0).ln()
    };
    let mine = score(&x);
    // A sensor that does not stand out over no change has no group to speak of.
    if mine < 10.0 {
        return Vec::new();
    }
    let mut out: Vec<(String, f64)> = temps
        .iter()
        .enumerate()
        .filter(|(o, _)| *o != s)
        .map(|(_, (name, y))| (name.clone(), score(&gated(y, gate))))
        .filter(|(_, v)| mine - v < 10.0)
        .collect();
    out.sort_by(|a, b| b.1.total_cmp(&a.1));
    out.truncate(3);
    out
}

/// The located candidate: the sensor, its lag, its score and the AR coefficients it was
/// scored with.
struct Pick {
    sensor: usize,
    tau: f64,
    score: f64,
    phi: Vec<f64>,
}

/// The best lag of sensor `x` (on the training rows, times `tt`), gated at training row
/// `gate`, added to the final model of `w`. The sensor is the one the onset search named:
/// scored as a term (whitened) against every other sensor it would pick one for whatever
/// fast swing of the residual it shares, not for following the drift (fl-thermal's t16_C
/// over an injected t11_C drift).
fn best_pick(
    w: &ColumnScorer,
    tt: &[f64],
    (sensor, x): (usize, &[f64]),
    gate: Option<usize>,
) -> Option<Pick> {
    let mut best: Option<Pick> = None;
    {
        for tau in LOCATED_TAUS_MIN {
            let extra = usize::from(gate.is_some()) + usize::from(tau > 0.0);
            let Some(s) = w.score(&gated(&lagged(tt, x, tau), gate), extra) else {
                continue;
            };
            if best.as_ref().is_none_or(|b| s.delta_bic > b.score) {
                best = Some(Pick {
                    sensor,
                    tau,
                    score: s.delta_bic,
                    phi: s.phi,
                });
            }
        }
    }
    best
}

/// Where the residual `rt` (training rows, times `tt`) is tied to a temperature of `temps`:
/// the sensor and the onset row when an onset stands out over no change (delta-BIC of
/// [`MIN_ONSET_DELTA_BIC`]); else, when `structured`, the sensor that follows its largest departure
/// best (|r| >= [`MIN_DRIVER_R`]), un-gated.
///
/// A later departure is sought in its own window, training rows `from..`: the onset search
/// sees only them (its offset is theirs), so a smaller drift late in the fit is not swamped
/// by the misfit of what came before; there the tie is by an onset alone.
fn tie(
    tt: &[f64],
    rt: &[f64],
    temps: &[(String, Vec<f64>)],
    structured: bool,
    from: usize,
) -> Option<(usize, Option<usize>)> {
    let index = |name: &str| temps.iter().position(|t| t.0 == name);
    if from > 0 {
        let window: Vec<(String, Vec<f64>)> = temps
            .iter()
            .map(|(n, x)| (n.clone(), x.get(from..).unwrap_or_default().to_vec()))
            .collect();
        let (tw, rw) = (tt.get(from..)?, rt.get(from..)?);
        let o = locate_onset(tw, rw, &window).filter(|o| o.delta_bic >= MIN_ONSET_DELTA_BIC)?;
        // An onset at the window's first hour is a drift that began before the window: the
        // tail of the departure the first search took, not a later one (on fl-thermal, such
        // tails of drifts injected from 20 and 25 h were tied to a neighbouring sensor and
        // accepted: 5 false terms in 180 injections).
        let first_h = (tw[0] + 0.1 * (tw[tw.len() - 1] - tw[0])) / 60.0;
        if onset_row(tw, o.at_h) <= onset_row(tw, first_h) {
            return None;
        }
        return index(&o.sensor).map(|s| (s, Some(from + onset_row(tw, o.at_h))));
    }
    if let Some(o) = locate_onset(tt, rt, temps).filter(|o| o.delta_bic >= MIN_ONSET_DELTA_BIC) {
        return index(&o.sensor).map(|s| (s, Some(onset_row(tt, o.at_h))));
    }
    if !structured {
        return None;
    }
    let d = locate_departure(tt, rt, temps)?;
    let (name, r) = d.drivers.first()?;
    (r.abs() >= MIN_DRIVER_R)
        .then(|| index(name))
        .flatten()
        .map(|s| (s, None))
}

/// The training row of an onset at `at_h`.
fn onset_row(tt: &[f64], at_h: f64) -> usize {
    tt.partition_point(|t| *t < at_h * 60.0 - 1e-6)
}

/// What the best of this search reaches by chance: the highest, over `opts.surrogates`
/// replicates, of the located term's score when every temperature is phase-randomised (same
/// spectrum, no relation to the readings) and the residual located and tied again on them.
fn surrogate_bar(
    w: &ColumnScorer,
    tt: &[f64],
    rt: &[f64],
    temps: &[Vec<f64>],
    (structured, from): (bool, usize),
    seed: u64,
    opts: &DisplacementOptions,
) -> f64 {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut bar = opts.min_delta_bic;
    for k in 0..opts.surrogates {
        let sur: Vec<(String, Vec<f64>)> = temps
            .iter()
            .enumerate()
            .map(|(s, x)| {
                let x = crate::surrogates::phase_randomised(x, &mut rng);
                (format!("{k}:{s}"), x)
            })
            .collect();
        let Some((s, gate)) = tie(tt, rt, &sur, structured, from) else {
            continue;
        };
        if let Some(p) = best_pick(w, tt, (s, &sur[s].1), gate) {
            bar = bar.max(p.score);
        }
    }
    bar
}

/// The located candidate of one channel: the residual of the selection's model (`chosen` on
/// `base_cols`) located on the training rows and tied to a temperature of `temps` (every
/// thinned reading), made a candidate, fitted and judged against that model (its held-out
/// figures are settled with the held-out veto, then [`verdict`] gives the term). None when
/// nothing is tied to a temperature.
pub(super) fn locate(
    design: &Design,
    base_cols: &[Vec<f64>],
    chosen: &[usize],
    t_min: &[f64],
    temps: &[(String, Vec<f64>)],
    (channel, from_min): (&str, Option<f64>),
    opts: &DisplacementOptions,
) -> Option<Found> {
    let m = design.matrix(chosen, base_cols);
    let final_fit = design.fit(&m).1;
    let beta = design.ols(&m, &design.train);
    let pred = &m * &beta;
    let pick = |v: &[f64]| -> Vec<f64> { design.train.iter().map(|&i| v[i]).collect() };
    let tt = pick(t_min);
    let rt: Vec<f64> = design
        .train
        .iter()
        .map(|&i| design.y[i] - pred[i])
        .collect();
    let temps_t: Vec<(String, Vec<f64>)> =
        temps.iter().map(|(n, x)| (n.clone(), pick(x))).collect();
    // Where it starts and what it follows: an onset that stands out over no change gates
    // the term; without one, a temperature that follows the largest departure of a
    // structured residual is tried un-gated.
    let structured = final_fit.ar1 > 0.5 && final_fit.ljung_box_p < 0.01;
    let from = from_min.map_or(0, |f| tt.partition_point(|t| *t < f));
    let (s, gate) = tie(&tt, &rt, &temps_t, structured, from)?;
    let w = ColumnScorer::new(design, &m, opts.located_noise);
    let best = best_pick(&w, &tt, (s, &temps_t[s].1), gate)?;
    let sensor = best.sensor;
    let bar = if opts.surrogates == 0 || best.score < opts.min_delta_bic {
        opts.min_delta_bic
    } else {
        let seed = opts.seed
            ^ 0x006c_6f63_6174_6564
            ^ from as u64
            ^ channel
                .bytes()
                .fold(0u64, |h, b| h.wrapping_mul(31).wrapping_add(b as u64));
        let xs: Vec<Vec<f64>> = temps_t.iter().map(|t| t.1.clone()).collect();
        surrogate_bar(&w, &tt, &rt, &xs, (structured, from), seed, opts)
    };
    // The candidate on every reading: the lag runs on through the held-out end (a causal
    // filter, so its training part is what was scored).
    let k_all = gate.map(|k| design.train[k]);
    let x = gated(&lagged(t_min, &temps[sensor].1, best.tau), k_all);
    let mut m2 = m.clone().insert_column(m.ncols(), 0.0);
    m2.column_mut(m.ncols()).copy_from_slice(&x);
    let judged = judge_column(design, &x, &m, &m2, &best.phi, opts);
    let before = design.fit(&m).1.rms_heldout_um;
    let after = design.fit(&m2).1.rms_heldout_um;
    let comparable = comparable(&rt, &temps_t, sensor, gate);
    let heldout_by_sensor = heldout_by_sensor(design, &m, t_min, temps, (best.tau, k_all));
    // What a drift of anything would fit as well over the span the term is claimed on: a
    // ramp, or the baseline's own warm-up (its column after the offset).
    let from = k_all.unwrap_or(0);
    let ramp_r = super::corr(&x[from..], &t_min[from..]);
    let warmup_r = base_cols
        .get(1)
        .map(|w| super::corr(&x[from..], &w[from..]));
    let found = Found {
        sensor: temps[sensor].0.clone(),
        tau: best.tau,
        onset_min: k_all.map(|k| t_min[k]),
        score: best.score,
        bar,
        judged,
        before,
        after,
        ramp_r,
        warmup_r,
        comparable,
        heldout_by_sensor,
        blocks: design.blocks.len(),
        x,
    };
    Some(found)
}

/// Whether a located candidate passes every rule before the held-out veto: the bar and
/// [`judge_column`]'s.
pub(super) fn passes_before_veto(f: &Found) -> bool {
    f.score >= f.bar && f.judged.reason.is_none()
}

/// The chosen candidate's figures, before the verdict.
pub(super) struct Found {
    sensor: String,
    tau: f64,
    onset_min: Option<f64>,
    score: f64,
    bar: f64,
    judged: Judged,
    /// Held-out RMS of the final model without it and with it (set once the veto settled
    /// that model).
    pub before: f64,
    pub after: f64,
    ramp_r: f64,
    warmup_r: Option<f64>,
    comparable: Vec<(String, f64)>,
    heldout_by_sensor: Vec<(String, f64)>,
    blocks: usize,
    pub x: Vec<f64>,
}

/// The held-out RMS of model `m` with the same term on each sensor instead (the same lag
/// `tau` and gate `k`), best first: what the held-out end says of which sensor the drift
/// follows. Not a rule (the sensor is chosen on the training part alone), a figure to read
/// beside the tie: where the training part cannot tell two sensors apart, the hold-out may.
fn heldout_by_sensor(
    design: &Design,
    m: &nalgebra::DMatrix<f64>,
    t_min: &[f64],
    temps: &[(String, Vec<f64>)],
    (tau, k): (f64, Option<usize>),
) -> Vec<(String, f64)> {
    let mut out: Vec<(String, f64)> = temps
        .iter()
        .filter_map(|(name, x)| {
            let x = gated(&lagged(t_min, x, tau), k);
            let mut m2 = m.clone().insert_column(m.ncols(), 0.0);
            m2.column_mut(m.ncols()).copy_from_slice(&x);
            let held = design.fit(&m2).1.rms_heldout_um;
            held.is_finite().then(|| (name.clone(), held))
        })
        .collect();
    out.sort_by(|a, b| a.1.total_cmp(&b.1));
    out
}

/// The rule a located candidate fails, in the forward selection's order (the bar, then
/// [`judge_column`]'s rules, then the held-out veto), and whether it is one of prediction
/// (the rolling origins, the held-out end): only those can a short recording or a
/// confounded sensor explain; a term that does not stand out of the residual is not there.
fn failed_rule(f: &Found, opts: &DisplacementOptions) -> Option<(bool, String)> {
    if f.score < f.bar {
        Some((
            false,
            format!(
                "delta-BIC {:.1} below what the same search reaches on phase-randomised temperatures ({:.1}, the highest of {} replicates)",
                f.score, f.bar, opts.surrogates
            ),
        ))
    } else if let Some(r) = &f.judged.reason {
        Some((r.starts_with("improves"), r.clone()))
    } else if f.after > f.before {
        Some((
            true,
            format!(
                "vetoed: worsens the held-out end ({:.2} um without it, {:.2} um with it)",
                f.before, f.after
            ),
        ))
    } else {
        None
    }
}

/// Hours of the recording the rolling origins and the held-out end would need after an
/// onset at `onset_min` to judge a gated term, if the recording falls short: `(training
/// span needed, h; held-out hours after the onset, h)`.
fn shortfall(
    design: &Design,
    t_min: &[f64],
    onset_min: f64,
    opts: &DisplacementOptions,
) -> Option<(f64, f64)> {
    let need = onset_min + 60.0 * MIN_AFTER_ONSET_H;
    let seeing = design
        .blocks
        .iter()
        .filter(|(fit, _)| fit.last().is_some_and(|&i| t_min[i] >= need))
        .count();
    let held_h = match (design.test.first(), design.test.last()) {
        (Some(&a), Some(&b)) => (t_min[b] - t_min[a].max(onset_min)) / 60.0,
        _ => 0.0,
    };
    let short_folds = seeing < opts.min_blocks_improved;
    if !short_folds && held_h >= MIN_AFTER_ONSET_H {
        return None;
    }
    // The rolling origins sit at 1/2 + k/(2n) of the training span: the
    // `min_blocks_improved`-th latest must fall `MIN_AFTER_ONSET_H` after the onset.
    let n = design.blocks.len().max(1) as f64;
    let k = (n - opts.min_blocks_improved as f64).max(0.0);
    let frac = 0.5 + k / (2.0 * n);
    let t0 = design.train.first().map_or(0.0, |&i| t_min[i]);
    Some(((need - t0) / frac / 60.0, held_h))
}

/// Accepted, or not confirmed with the reason and the recording that would split it; the
/// one statement of the located term.
pub(super) fn verdict(
    design: &Design,
    t_min: &[f64],
    f: Found,
    channel: &str,
    opts: &DisplacementOptions,
) -> LocatedTerm {
    let (predictive, rule) = match failed_rule(&f, opts) {
        Some((p, r)) => (p, Some(r)),
        None => (false, None),
    };
    let sensor = f.sensor.clone();
    let others = f
        .comparable
        .iter()
        .map(|(n, _)| n.as_str())
        .collect::<Vec<_>>()
        .join(", ");
    let ramp = f.ramp_r.abs() > RAMP_R;
    let warm_up = f.warmup_r.is_some_and(|r| r.abs() > RAMP_R);
    let short = f.onset_min.and_then(|o| shortfall(design, t_min, o, opts));
    let (reason, split_by) = if warm_up {
        // The baseline's warm-up column would carry the same drift: only a run where the
        // machine warms up as here while the sensor stays put (or the sensor moves while the
        // machine does not) tells them apart.
        (
            Some(NotConfirmed::ConfoundedWithWarmUp),
            Some(format!(
                "a run at the same spindle schedule with {sensor}'s source (the hall, a coolant) held constant: the warm-up goes on there without {sensor}'s drift"
            )),
        )
    } else if ramp {
        (
            Some(NotConfirmed::ConfoundedWithRamp),
            Some(format!(
                "a run where {sensor} and time do not move together: e.g. a day with {sensor}'s source (the hall, a coolant) held constant while the drift goes on, or cycled up and down"
            )),
        )
    } else if rule.is_none() {
        (None, None)
    } else if !predictive {
        (Some(NotConfirmed::NotSupported), None)
    } else if let Some((train_h, held_h)) = short {
        (
            Some(NotConfirmed::TooShort),
            Some(format!(
                "a recording that goes on after the onset: a training span of {train_h:.0} h or more (so that {} of the rolling origins fall {MIN_AFTER_ONSET_H} h after it) and a held-out end of {MIN_AFTER_ONSET_H} h or more after it (now {held_h:.1} h)",
                opts.min_blocks_improved
            )),
        )
    } else if !f.comparable.is_empty() {
        (
            Some(NotConfirmed::ConfoundedWithSensor),
            Some(format!("a run where {sensor} and {others} move apart")),
        )
    } else {
        (Some(NotConfirmed::NotSupported), None)
    };
    let accepted = reason.is_none();
    let term = match (f.onset_min, f.tau) {
        (Some(o), t) if t > 0.0 => {
            format!("{sensor} lag {t} min, change since {:.1} h", o / 60.0)
        }
        (Some(o), _) => format!("{sensor} change since {:.1} h", o / 60.0),
        (None, t) => super::lag_label(&sensor, t),
    };
    let statement = statement(channel, &term, &f, accepted, reason, rule.as_deref())
        + &split_by
            .as_ref()
            .map(|s| format!("; what would split it: {s}"))
            .unwrap_or_default();
    LocatedTerm {
        sensor,
        lag_min: f.tau,
        onset_h: f.onset_min.map(|o| o / 60.0),
        term,
        gain_um_per_k: f.judged.value,
        sigma_um_per_k: f.judged.sd,
        t: f.judged.t,
        delta_bic: f.score,
        bar: f.bar,
        blocks_improved: f.judged.wins,
        blocks: design.blocks.len(),
        heldout_before_um: f.before,
        heldout_after_um: f.after,
        ramp_r: f.ramp_r,
        warmup_r: f.warmup_r,
        comparable: f.comparable,
        heldout_by_sensor: f.heldout_by_sensor,
        accepted,
        rule,
        reason,
        split_by,
        statement,
        x: f.x,
    }
}

/// The located term in words: where, what, how it was modelled, and the verdict.
fn statement(
    channel: &str,
    term: &str,
    f: &Found,
    accepted: bool,
    reason: Option<NotConfirmed>,
    rule: Option<&str>,
) -> String {
    let what = match f.onset_min {
        Some(o) => format!(
            "a drift from {:.1} h that follows {:.2} ± {:.2} um/K of {}'s change since then{}",
            o / 60.0,
            f.judged.value,
            f.judged.sd,
            f.sensor,
            if f.tau > 0.0 {
                format!(" (through a {}-min lag)", f.tau)
            } else {
                String::new()
            }
        ),
        None => format!(
            "the residual follows {term} at {:.2} ± {:.2} um/K (no onset: the whole span)",
            f.judged.value, f.judged.sd
        ),
    };
    let modelled = format!(
        "modelled as an added term: held-out RMS {:.2} -> {:.2} um, delta-BIC {:.1} (bar {:.1}), t {:.1}, better predictions from {} of {} rolling origins",
        f.before, f.after, f.score, f.bar, f.judged.t, f.judged.wins, f.blocks
    );
    let modelled = modelled + &heldout_ranking(f);
    let others = |lead: &str| {
        if f.comparable.is_empty() {
            String::new()
        } else {
            format!(
                "{lead}{} explain it comparably (within delta-BIC 10)",
                f.comparable
                    .iter()
                    .map(|(n, b)| format!("{n} ({b:.0})"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }
    };
    let verdict = if accepted {
        format!("accepted into the final model{}", others("; "))
    } else {
        let why = match reason {
            Some(NotConfirmed::ConfoundedWithWarmUp) => format!(
                "confounded with the warm-up: the candidate follows the baseline's warm-up term (r {:.2}; with time, r {:.2}), so the warm-up would carry the same drift",
                f.warmup_r.unwrap_or(f64::NAN),
                f.ramp_r
            ),
            Some(NotConfirmed::ConfoundedWithRamp) => format!(
                "confounded with a ramp: the candidate follows the time since {} (r {:.2}), so a drift of anything would fit as well",
                if f.onset_min.is_some() {
                    "the onset"
                } else {
                    "the start"
                },
                f.ramp_r
            ),
            Some(NotConfirmed::TooShort) => {
                "the recording is too short after the onset to confirm it".to_string()
            }
            Some(NotConfirmed::ConfoundedWithSensor) => {
                format!("confounded with another sensor{}", others(": "))
            }
            _ => "the data do not support it".to_string(),
        };
        match rule {
            Some(r) => format!("not confirmed: {why} ({r})"),
            None => format!("not confirmed: {why}"),
        }
    };
    format!("{channel}: located: {what}; {modelled}; {verdict}")
}

/// The held-out end's ranking of the same term on each sensor, in words: the best three,
/// and where the tied sensor stands when it is not among them.
fn heldout_ranking(f: &Found) -> String {
    let rank = &f.heldout_by_sensor;
    if rank.len() < 2 {
        return String::new();
    }
    let mut shown: Vec<String> = rank
        .iter()
        .take(3)
        .map(|(n, h)| format!("{n} {h:.2}"))
        .collect();
    if let Some(k) = rank.iter().skip(3).position(|(n, _)| *n == f.sensor) {
        shown.push(format!(
            "... {} {:.2} ({}th)",
            f.sensor,
            rank[k + 3].1,
            k + 4
        ));
    }
    format!(
        "; the same term on each sensor instead, held-out RMS {} um (of {} sensors)",
        shown.join(", "),
        rank.len()
    )
}

impl NotConfirmed {
    /// The reason in a few words.
    pub fn words(self) -> &'static str {
        match self {
            NotConfirmed::TooShort => "too short after the onset",
            NotConfirmed::ConfoundedWithWarmUp => "confounded with the warm-up",
            NotConfirmed::ConfoundedWithRamp => "confounded with a ramp",
            NotConfirmed::ConfoundedWithSensor => "confounded with another sensor",
            NotConfirmed::NotSupported => "not supported by the data",
        }
    }
}

impl LocatedTerm {
    /// The accepted located term as a term of the final model. An onset-gated term is not
    /// carried into the thermal model (it has no onset: fitted on the whole span it would
    /// be wrong before it); an un-gated one is a temperature input like any other.
    pub fn as_term(&self) -> Term {
        Term {
            effect: if self.onset_h.is_some() {
                "onset_drift"
            } else {
                "missing_temperature"
            },
            term: self.term.clone(),
            unit: "um/K",
            value: self.gain_um_per_k,
            sigma: self.sigma_um_per_k,
            delta_bic: self.delta_bic,
            t: self.t,
            blocks_improved: self.blocks_improved,
            heldout_before_um: self.heldout_before_um,
            heldout_after_um: self.heldout_after_um,
            ambiguous_with: self.comparable.iter().map(|c| c.0.clone()).collect(),
            input: match self.onset_h {
                Some(_) => ModelInput::None,
                None => ModelInput::Temperature {
                    sensor: self.sensor.clone(),
                    taus_min: vec![self.lag_min],
                },
            },
            statement: self.statement.clone(),
        }
    }
}
