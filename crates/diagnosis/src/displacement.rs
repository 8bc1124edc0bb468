//! Diagnosis of displacement recordings (imported thermal tests, ISO 230-3 style), pure code.
//! The baseline is what a spindle-only model can do: one thermal mode of the spindle heat
//! input per channel, its time constant chosen on the training part. The search then tries the
//! thermal candidates: a second mode (free sign, so it can make an overshoot), each logged
//! temperature and its lags (a missing input), each temperature's fast swing (a coolant or
//! chiller cycle), a 24-h Fourier pair (ambient) and the instant speed term.
//!
//! Readings of a thermal test are seconds apart and their misfit is smooth, so consecutive
//! residuals are far from independent. The selection therefore works on thinned samples
//! (`thin_s`) and, at each step, on the AR(p)-whitened model (feasible GLS, p by BIC):
//! delta-BIC is `N ln(SSE0 / SSE1) - ln N` on the whitened residuals and must clear the bar
//! that phase-randomised surrogates of the candidates set; each term must also improve the
//! rolling-origin held-out prediction, and the held-out end vetoes any that worsen it
//! (docs/physics.md 4.6.2).

use driftwatch_core::units;
use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use rand::SeedableRng;
use serde::Serialize;

use crate::cycles::DIAGNOSIS_TAUS_MIN;
use crate::effects::TEMPERATURE_TAUS_MIN;
use crate::stepwise::{Rules, Scoring, Verdict, stepwise};
use driftwatch_core::least_squares::lsq;
use driftwatch_thermal::model::{Event, Features, ModelConfig, ModelInput};

mod located;
mod scoring;
mod thermal_base;
pub use located::{
    LATE_WINDOW_SHARE, LOCATED_TAUS_MIN, LocatedTerm, MIN_AFTER_ONSET_H, NotConfirmed, RAMP_R,
};
pub use scoring::NoiseModel;
pub use thermal_base::ThermalBase;

#[derive(Debug, thiserror::Error)]
pub enum DisplacementError {
    #[error("no displacement readings")]
    NoReadings,
    #[error("channel {0}: {1} thinned readings before the held-out part (30 needed)")]
    TooFewTraining(String, usize),
    #[error("channel {0}: no reading in the held-out part")]
    NoHeldOut(String),
    #[error("no channel could be diagnosed: {0}")]
    NoChannel(String),
}

/// Options: the acceptance rules of docs/physics.md 4.6.2.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DisplacementOptions {
    pub n_ref_rpm: f64,
    pub gamma: f64,
    /// One sample per this many seconds is used by the fits.
    pub thin_s: f64,
    /// Readings from this time on are held out of every fit (the last 15 % of the span when
    /// not given).
    pub holdout_from_ns: Option<i64>,
    pub min_delta_bic: f64,
    pub min_t: f64,
    /// Held-out blocks of the training span, and how many a term must improve.
    pub blocks: usize,
    pub min_blocks_improved: usize,
    pub max_terms: usize,
    /// Largest plausible footprint of one term, um.
    pub max_um: f64,
    /// Band searched for a periodic residual, min.
    pub band_min: (f64, f64),
    /// Smallest post-change excursion reported as an overshoot, um.
    pub min_overshoot_um: f64,
    /// Largest order of the AR noise model the acceptance whitens with; the order is chosen
    /// by BIC on the residual up to it (1: AR(1), as in the earlier rules).
    pub ar_max: usize,
    /// Where the AR noise model a candidate of the forward selection is scored with comes
    /// from ([`NoiseModel`]).
    pub noise: NoiseModel,
    /// The same for the located term.
    pub located_noise: NoiseModel,
    /// The folds a term must improve: rolling origins (fit on what came before, predict the
    /// rest of the training span), or leave-one-block-out blocks (as in the earlier rules).
    pub rolling_origin: bool,
    /// Drop a final term that worsens the held-out end (then the held-out RMS is a
    /// validation figure the selection has seen, and is labelled so).
    pub heldout_veto: bool,
    /// Surrogate replicates of the best-candidate threshold (0: none, the fixed delta-BIC
    /// alone). In each, every candidate is replaced by a phase-randomised copy (the same
    /// spectrum, no relation to the readings) and the best delta-BIC among them noted; a
    /// term must beat the highest of those (with 39, the 97.5 % point: each step of the
    /// forward selection is a test, and a selection takes several). The bar is then what
    /// the best of this many candidates reaches by chance on residuals like these, not a
    /// fixed number.
    pub surrogates: usize,
    /// Seed of the surrogates.
    pub seed: u64,
}

impl DisplacementOptions {
    /// The earlier acceptance rules (AR(1) whitening, leave-one-block-out blocks, no
    /// held-out veto): kept to measure what the change did.
    pub fn earlier_rules() -> Self {
        DisplacementOptions {
            ar_max: 1,
            noise: NoiseModel::WithoutCandidate,
            located_noise: NoiseModel::WithoutCandidate,
            rolling_origin: false,
            heldout_veto: false,
            surrogates: 0,
            ..Default::default()
        }
    }
}

impl Default for DisplacementOptions {
    fn default() -> Self {
        DisplacementOptions {
            n_ref_rpm: 20000.0,
            gamma: 1.5,
            thin_s: 300.0,
            holdout_from_ns: None,
            min_delta_bic: 10.0,
            min_t: 4.0,
            blocks: 3,
            min_blocks_improved: 2,
            max_terms: 6,
            max_um: 200.0,
            band_min: (10.0, 60.0),
            min_overshoot_um: 1.5,
            ar_max: 4,
            noise: NoiseModel::WithoutCandidate,
            located_noise: NoiseModel::Profile,
            rolling_origin: true,
            heldout_veto: true,
            surrogates: 39,
            seed: 14,
        }
    }
}

#[derive(Debug, Clone)]
struct Candidate {
    effect: &'static str,
    term: String,
    unit: &'static str,
    x: Vec<f64>,
    input: ModelInput,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mode {
    pub tau_min: f64,
    /// Gain at the reference speed, um per unit heat input.
    pub gain_um: f64,
    pub offset_um: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Fit {
    pub parameters: usize,
    pub rms_train_um: f64,
    /// RMS on the held-out end of the recording, fitted on the training part alone.
    pub rms_heldout_um: f64,
    /// Lag-1 autocorrelation of the thinned training residuals.
    pub ar1: f64,
    /// Ljung-Box p-value of the thinned training residuals over 10 lags.
    pub ljung_box_p: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhaseResidual {
    pub phase: &'static str,
    pub n: usize,
    pub mean_um: f64,
    pub rms_um: f64,
}

/// What the final model leaves unexplained: whether it is structure, not noise, where it
/// departs most, and the temperatures that follow it there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Unexplained {
    /// The final training residual's lag-1 autocorrelation and Ljung-Box p (10 lags).
    pub ar1: f64,
    pub ljung_box_p: f64,
    /// Autocorrelated beyond noise (|ar1| > 0.5 and Ljung-Box p < 0.01).
    pub structured: bool,
    /// The largest departure of the residual (2-h smoothing): the run of one sign around its
    /// largest value, h from the start, and its mean, um.
    pub from_h: f64,
    pub to_h: f64,
    pub mean_um: f64,
    /// Sensors whose temperature follows the residual over that span, best first: name and
    /// correlation (at most 3).
    pub drivers: Vec<(String, f64)>,
    /// The best drift that starts at some hour and follows a temperature.
    pub onset: Option<Onset>,
}

/// A drift of the residual that starts at some hour and follows one temperature from then
/// on: `c + a (T(t) - T(t_on))` after `t_on`, `c` before, fitted over every sensor and every
/// onset on an hourly grid (10 % to 90 % of the span). A location, not an acceptance test.
/// Its delta-BICs count the residual's samples as `n (1 - r) / (1 + r)` independent ones
/// (`r` the lag-1 autocorrelation left by the best fit): a slow residual holds far fewer
/// independent readings than samples, and raw figures would tell apart what it cannot.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Onset {
    pub at_h: f64,
    /// The onsets within delta-BIC 2 of the best, for its sensor: a temperature that stays
    /// flat for hours cannot say when within them the drift began.
    pub earliest_h: f64,
    pub latest_h: f64,
    pub sensor: String,
    pub gain_um_per_k: f64,
    /// Independent samples the delta-BICs count.
    pub n_eff: f64,
    /// Against no change, and against the best change of shape that follows no temperature
    /// (a step or a ramp from some hour on the same grid); both with two parameters more.
    pub delta_bic: f64,
    pub delta_bic_vs_shape: f64,
    /// The other sensors' delta-BIC with the same onset, best first (at most 3).
    pub others: Vec<(String, f64)>,
    /// Told apart: at least 10 above the shapes and above every other sensor.
    pub tied: bool,
}

/// The SSE of `r` fitted by an offset and `x` (the offset alone when `x` is constant).
fn sse_with(r: &[f64], x: &[f64]) -> f64 {
    let n = r.len() as f64;
    let (mr, mx) = (r.iter().sum::<f64>() / n, x.iter().sum::<f64>() / n);
    let (mut sxx, mut sxr, mut srr) = (0.0, 0.0, 0.0);
    for (a, b) in r.iter().zip(x) {
        sxx += (b - mx).powi(2);
        sxr += (b - mx) * (a - mr);
        srr += (a - mr).powi(2);
    }
    if sxx <= 1e-12 {
        srr
    } else {
        srr - sxr * sxr / sxx
    }
}

/// The onset search of [`Onset`] on residual `r` at times `t_min`, temperatures `temps`.
fn locate_onset(t_min: &[f64], r: &[f64], temps: &[(String, Vec<f64>)]) -> Option<Onset> {
    let n = r.len();
    if n < 20 {
        return None;
    }
    let (t0, t1) = (t_min[0], t_min[n - 1]);
    let sse0 = sse_with(r, &vec![0.0; n]);
    let onsets: Vec<usize> = {
        let mut v = Vec::new();
        let mut h = t0 + 0.1 * (t1 - t0);
        while h <= t0 + 0.9 * (t1 - t0) {
            v.push(t_min.partition_point(|t| *t < h));
            h += 60.0;
        }
        v.dedup();
        v
    };
    let mut shape = f64::INFINITY;
    // (sse, onset row, sensor index); every sensor's SSE at every onset.
    let mut best: Option<(f64, usize, usize)> = None;
    let mut table: Vec<Vec<f64>> = vec![Vec::new(); temps.len()];
    for &k in &onsets {
        let step: Vec<f64> = (0..n).map(|i| f64::from(u8::from(i >= k))).collect();
        let ramp: Vec<f64> = (0..n).map(|i| (t_min[i] - t_min[k]).max(0.0)).collect();
        shape = shape.min(sse_with(r, &step)).min(sse_with(r, &ramp));
        for (s, (_, x)) in temps.iter().enumerate() {
            let g: Vec<f64> = (0..n)
                .map(|i| if i >= k { x[i] - x[k] } else { 0.0 })
                .collect();
            let sse = sse_with(r, &g);
            table[s].push(sse);
            if best.is_none_or(|b| sse < b.0) {
                best = Some((sse, k, s));
            }
        }
    }
    let (sse, k, s) = best?;
    let gated = |x: &[f64]| -> Vec<f64> {
        (0..n)
            .map(|i| if i >= k { x[i] - x[k] } else { 0.0 })
            .collect()
    };
    let g = gated(&temps[s].1);
    let nf = n as f64;
    let (gain, rho) = {
        let (mg, mr) = (g.iter().sum::<f64>() / nf, r.iter().sum::<f64>() / nf);
        let sxx: f64 = g.iter().map(|v| (v - mg).powi(2)).sum();
        let sxr: f64 = g.iter().zip(r).map(|(a, b)| (a - mg) * (b - mr)).sum();
        let gain = if sxx > 0.0 { sxr / sxx } else { 0.0 };
        let left: Vec<f64> = g
            .iter()
            .zip(r)
            .map(|(a, b)| b - mr - gain * (a - mg))
            .collect();
        (gain, ar1(&left).clamp(0.0, 0.99))
    };
    let n_eff = nf * (1.0 - rho) / (1.0 + rho);
    let dbic = |sse: f64, base: f64| n_eff * (base / sse.max(1e-300)).ln();
    let near: Vec<f64> = onsets
        .iter()
        .zip(&table[s])
        .filter(|(_, e)| dbic(**e, sse) > -2.0)
        .map(|(&k, _)| t_min[k] / 60.0)
        .collect();
    let mut others: Vec<(String, f64)> = temps
        .iter()
        .enumerate()
        .filter(|(o, _)| *o != s)
        .map(|(_, (name, x))| {
            (
                name.clone(),
                dbic(sse_with(r, &gated(x)), sse0) - 2.0 * n_eff.ln(),
            )
        })
        .collect();
    others.sort_by(|a, b| b.1.total_cmp(&a.1));
    others.truncate(3);
    let delta_bic = dbic(sse, sse0) - 2.0 * n_eff.ln();
    let delta_bic_vs_shape = dbic(sse, shape);
    let tied = delta_bic_vs_shape >= 10.0 && others.first().is_none_or(|o| delta_bic - o.1 >= 10.0);
    Some(Onset {
        at_h: t_min[k] / 60.0,
        earliest_h: near.iter().copied().fold(f64::INFINITY, f64::min),
        latest_h: near.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        sensor: temps[s].0.clone(),
        gain_um_per_k: gain,
        n_eff,
        delta_bic,
        delta_bic_vs_shape,
        others,
        tied,
    })
}

/// A span of readings `from..=to` where the residual departs, its mean and the sensors that
/// follow it there.
struct Departure {
    from: usize,
    to: usize,
    mean: f64,
    drivers: Vec<(String, f64)>,
}

/// Locate the largest departure of `resid` (times `t_min`) and rank `temps` by how well they
/// follow it there.
fn locate_departure(
    t_min: &[f64],
    resid: &[f64],
    temps: &[(String, Vec<f64>)],
) -> Option<Departure> {
    let s = moving_average(t_min, resid, 120.0);
    let peak = (0..s.len()).max_by(|&a, &b| s[a].abs().total_cmp(&s[b].abs()))?;
    let sign = s[peak].signum();
    let (mut a, mut b) = (peak, peak);
    while a > 0 && s[a - 1].signum() == sign {
        a -= 1;
    }
    while b + 1 < s.len() && s[b + 1].signum() == sign {
        b += 1;
    }
    let mean = resid[a..=b].iter().sum::<f64>() / (b - a + 1) as f64;
    let mut drivers: Vec<(String, f64)> = temps
        .iter()
        .map(|(name, x)| (name.clone(), corr(&resid[a..=b], &x[a..=b])))
        .filter(|(_, r)| r.is_finite() && *r != 0.0)
        .collect();
    drivers.sort_by(|x, y| y.1.abs().total_cmp(&x.1.abs()));
    drivers.truncate(3);
    Some(Departure {
        from: a,
        to: b,
        mean,
        drivers,
    })
}

/// A periodic component of the baseline residual and the logged temperature that carries it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Periodic {
    pub period_min: f64,
    /// Amplitude of the sinusoid at that period, um.
    pub amplitude_um: f64,
    /// RMS of the residual in the band, um.
    pub band_rms_um: f64,
    pub driver: Option<String>,
    /// Correlation of the band-passed residual with the band-passed driver.
    pub driver_r: f64,
    /// The driver's own strongest period in the band, min.
    pub driver_period_min: f64,
    /// The driver's period is within 20 % of the residual's: it carries that cycle.
    pub matched: bool,
}

/// The response after one speed change: a single first-order mode moves monotonically from
/// where it was toward its new level, so an excursion beyond both ends is something it
/// cannot make.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Transient {
    pub at_h: f64,
    pub from_rpm: f64,
    pub to_rpm: f64,
    /// Largest excursion of the measured (30-min smoothed) displacement beyond both the
    /// level at the change and the level at the end of the window, um.
    pub excursion_um: f64,
    pub after_min: f64,
    /// The same excursion of the baseline's and of the final model's prediction, um.
    pub baseline_excursion_um: f64,
    pub final_excursion_um: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Term {
    pub effect: &'static str,
    pub term: String,
    pub unit: &'static str,
    pub value: f64,
    pub sigma: f64,
    pub delta_bic: f64,
    pub t: f64,
    pub blocks_improved: usize,
    /// Held-out RMS of the final model without this term and with it, um.
    pub heldout_before_um: f64,
    pub heldout_after_um: f64,
    /// Candidates within delta-BIC 10 of this one at its step.
    pub ambiguous_with: Vec<String>,
    pub input: ModelInput,
    pub statement: String,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RefusedTerm {
    pub effect: &'static str,
    pub term: String,
    pub delta_bic: f64,
    pub t: f64,
    pub blocks_improved: usize,
    pub reason: String,
}

/// Plot data of one channel (not serialised).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ChannelSeries {
    pub t_h: Vec<f64>,
    pub y_um: Vec<f64>,
    pub baseline_um: Vec<f64>,
    pub final_um: Vec<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelDiagnosis {
    pub channel: String,
    pub n_train: usize,
    pub n_heldout: usize,
    /// The baseline's spindle mode; none when the spindle never turned (no spindle log): the
    /// baseline is then the offset alone and only temperatures can explain the readings.
    pub baseline_mode: Option<Mode>,
    pub baseline: Fit,
    pub final_fit: Fit,
    pub phases: Vec<PhaseResidual>,
    pub periodic: Option<Periodic>,
    pub transients: Vec<Transient>,
    /// What the final model leaves, located (none without readings).
    pub unexplained: Option<Unexplained>,
    /// Without a spindle log, when the forward selection took no term: the temperature that
    /// carries the warm-up in a baseline the search runs on again (when kept, also the first
    /// of `accepted`); none otherwise, or when no temperature passes the selection's rules.
    pub thermal_base: Option<ThermalBase>,
    /// What the forward selection left, located, tied to a temperature and made a term:
    /// accepted into the final model (then also in `accepted`) or not confirmed, with the
    /// reason. None when nothing was tied to a temperature.
    pub located_term: Option<LocatedTerm>,
    /// A later departure, located in the latest part of the fit on the model with the
    /// located term's candidate, and made a term the same way (none when nothing there is
    /// tied to a temperature).
    pub late_term: Option<LocatedTerm>,
    /// Candidates that could be scored at all (a singular design drops one before scoring).
    pub candidates_tested: usize,
    /// The surrogate bar of each selection step (delta-BIC), where one was computed.
    pub surrogate_bars: Vec<f64>,
    pub accepted: Vec<Term>,
    pub refused: Vec<RefusedTerm>,
    /// What the diagnosis found, in words.
    pub statements: Vec<String>,
    #[serde(skip)]
    pub series: ChannelSeries,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DisplacementDiagnosis {
    pub span_h: f64,
    pub heldout_from_h: f64,
    pub sensors: Vec<String>,
    pub channels: Vec<ChannelDiagnosis>,
    /// The thermal-model configuration with every accepted term that it can carry: the new
    /// model version.
    pub model: ModelConfig,
    /// Accepted terms the thermal model cannot carry.
    pub not_carried: Vec<String>,
    /// Channels not diagnosed, and why.
    pub skipped: Vec<String>,
}

/// Centred moving average over `window` (same units as `t`), for a sorted `t`.
fn moving_average(t: &[f64], y: &[f64], window: f64) -> Vec<f64> {
    let (mut a, mut b, mut s) = (0usize, 0usize, 0.0);
    let mut out = Vec::with_capacity(y.len());
    for i in 0..t.len() {
        while b < t.len() && t[b] <= t[i] + window / 2.0 {
            s += y[b];
            b += 1;
        }
        while t[a] < t[i] - window / 2.0 {
            s -= y[a];
            a += 1;
        }
        out.push(s / (b - a) as f64);
    }
    out
}

/// The strongest period in `band` (min) of `y` sampled at `t` (min): (period, amplitude).
fn strongest_period(t: &[f64], y: &[f64], band: (f64, f64)) -> (f64, f64) {
    let mut best = (f64::NAN, 0.0);
    let mut p = band.0;
    while p <= band.1 {
        let w = std::f64::consts::TAU / p;
        let (c, s) = t.iter().zip(y).fold((0.0, 0.0), |(c, s), (ti, yi)| {
            (c + yi * (w * ti).cos(), s + yi * (w * ti).sin())
        });
        let amp = 2.0 * (c * c + s * s).sqrt() / y.len().max(1) as f64;
        if amp > best.1 {
            best = (p, amp);
        }
        p += 0.25;
    }
    best
}

fn corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 { 0.0 } else { (s / n as f64).sqrt() }
}

fn ar1(e: &[f64]) -> f64 {
    corr(&e[1..], &e[..e.len() - 1]).clamp(0.0, 0.999)
}

/// Excursion of `y` (smoothed, window `[a, b)`) beyond both its first and last value:
/// `(um, index)`.
fn excursion(y: &[f64]) -> (f64, usize) {
    let (Some(&y0), Some(&y1)) = (y.first(), y.last()) else {
        return (0.0, 0);
    };
    let (hi, lo) = (y0.max(y1), y0.min(y1));
    let mut best = (0.0, 0);
    for (i, v) in y.iter().enumerate() {
        let e = (v - hi).max(lo - v);
        if e > best.0 {
            best = (e, i);
        }
    }
    best
}

/// Whether the AR polynomial with coefficients `phi` has real roots only: an overdamped
/// process, as slow thermal noise is. An oscillating one is refused: a cycle in the
/// residuals is a candidate's to explain (a chiller cycle is an AR(2) process with complex
/// roots, and whitening with it would annihilate the very column that explains it).
fn overdamped(phi: &[f64]) -> bool {
    let p = phi.len();
    let companion = DMatrix::from_fn(p, p, |r, c| {
        if r == 0 {
            phi[c]
        } else if r == c + 1 {
            1.0
        } else {
            0.0
        }
    });
    companion
        .complex_eigenvalues()
        .iter()
        .all(|z| z.im.abs() <= 1e-9 * z.norm().max(1e-12))
}

/// AR coefficients of `e`, the order (1..=`p_max`) chosen by BIC on the same rows among the
/// overdamped fits.
fn ar_by_bic(e: &[f64], p_max: usize) -> Vec<f64> {
    let n = e.len();
    if n <= 2 * p_max + 2 {
        return vec![ar1(e)];
    }
    let y = DVector::from_fn(n - p_max, |r, _| e[r + p_max]);
    let mut best: Option<(f64, Vec<f64>)> = None;
    for p in 1..=p_max {
        let x = DMatrix::from_fn(n - p_max, p, |r, l| e[r + p_max - 1 - l]);
        let f = lsq(&x, &y);
        let m = (n - p_max) as f64;
        let bic = m * (f.chi2 / m).max(1e-300).ln() + p as f64 * m.ln();
        let phi: Vec<f64> = f.beta.iter().copied().collect();
        if overdamped(&phi) && best.as_ref().is_none_or(|b| bic < b.0) {
            best = Some((bic, phi));
        }
    }
    best.map_or_else(|| vec![ar1(e)], |b| b.1)
}

/// The design of one channel's thinned samples.
struct Design<'a> {
    cands: &'a [Candidate],
    y: DVector<f64>,
    train: Vec<usize>,
    test: Vec<usize>,
    /// Folds of the training span: the rows a fit sees, and the rows it predicts.
    blocks: Vec<(Vec<usize>, Vec<usize>)>,
    ar_max: usize,
}

impl Design<'_> {
    fn matrix(&self, cols: &[usize], base: &[Vec<f64>]) -> DMatrix<f64> {
        let n = self.y.len();
        let all: Vec<&Vec<f64>> = base
            .iter()
            .chain(cols.iter().map(|c| &self.cands[*c].x))
            .collect();
        DMatrix::from_fn(n, all.len(), |i, j| all[j][i])
    }

    fn ols(&self, m: &DMatrix<f64>, rows: &[usize]) -> DVector<f64> {
        lsq(
            &m.select_rows(rows.iter()),
            &self.y.select_rows(rows.iter()),
        )
        .beta
    }

    /// Whitened training rows of `m` and `y` for AR coefficients `phi` (the first
    /// `ar_max` rows are dropped whatever the order, so that every order compares on the
    /// same rows).
    fn whiten(&self, m: &DMatrix<f64>, phi: &[f64]) -> (DMatrix<f64>, DVector<f64>) {
        let rows: Vec<usize> = (self.ar_max.max(1)..self.train.len()).collect();
        let w = |col: &dyn Fn(usize) -> f64, r: usize| {
            col(self.train[r])
                - phi
                    .iter()
                    .enumerate()
                    .map(|(l, p)| p * col(self.train[r - 1 - l]))
                    .sum::<f64>()
        };
        let mw = DMatrix::from_fn(rows.len(), m.ncols(), |r, j| w(&|i| m[(i, j)], rows[r]));
        let yw = DVector::from_fn(rows.len(), |r, _| w(&|i| self.y[i], rows[r]));
        (mw, yw)
    }

    /// The training rows of `m` whitened with the AR model of its own OLS residuals:
    /// `(phi, whitened m, whitened y, whitened SSE)`.
    fn whitened(&self, m: &DMatrix<f64>) -> (Vec<f64>, DMatrix<f64>, DVector<f64>, f64) {
        let beta = self.ols(m, &self.train);
        let pred = m * &beta;
        let e: Vec<f64> = self.train.iter().map(|&i| self.y[i] - pred[i]).collect();
        let phi = self.ar_of(&e);
        let (mw, yw) = self.whiten(m, &phi);
        let sse = lsq(&mw, &yw).chi2;
        (phi, mw, yw, sse)
    }

    fn fit(&self, m: &DMatrix<f64>) -> (DVector<f64>, Fit) {
        let beta = self.ols(m, &self.train);
        let pred = m * &beta;
        let e: Vec<f64> = self.train.iter().map(|&i| self.y[i] - pred[i]).collect();
        let held = if self.test.is_empty() {
            f64::NAN
        } else {
            rms(self.test.iter().map(|&i| self.y[i] - pred[i]))
        };
        let fit = Fit {
            parameters: m.ncols(),
            rms_train_um: rms(e.iter().copied()),
            rms_heldout_um: held,
            ar1: ar1(&e),
            ljung_box_p: driftwatch_core::stats::ljung_box(&e, 10).map_or(f64::NAN, |l| l.p_value),
        };
        (pred, fit)
    }

    /// The folds in which `m2` predicts better than `m` (each fitted on the fold's fit rows,
    /// judged on its predicted rows), and whether it does over all folds together.
    fn blocks_improved(&self, m: &DMatrix<f64>, m2: &DMatrix<f64>) -> (usize, bool) {
        let (mut wins, mut sum, mut sum2) = (0, 0.0, 0.0);
        for (fit, judge) in &self.blocks {
            let sse = |m: &DMatrix<f64>| {
                let beta = self.ols(m, fit);
                judge
                    .iter()
                    .map(|&i| (self.y[i] - m.row(i).transpose().dot(&beta)).powi(2))
                    .sum::<f64>()
            };
            let (a, b) = (sse(m), sse(m2));
            wins += usize::from(b < a);
            sum += a;
            sum2 += b;
        }
        (wins, sum2 < sum)
    }
}

/// Everything the candidates and the baseline need, at every reading of one channel.
struct Columns {
    t_ns: Vec<i64>,
    y: Vec<f64>,
    spindle: Vec<Vec<f64>>,
    /// Per sensor, per lag of `TEMPERATURE_TAUS_MIN`.
    temps: Vec<Vec<Vec<f64>>>,
    speed2: Vec<f64>,
}

fn columns(events: &[Event], channel: &str, sensors: &[String], cfg: &ModelConfig) -> Columns {
    let mut f = Features::new(
        cfg,
        &BTreeMap::new(),
        events.first().map_or(0, |e| e.t_ns()),
    );
    let ncol = cfg.columns().len();
    let mut x: Vec<Vec<f64>> = vec![Vec::new(); ncol];
    let (mut t_ns, mut y) = (Vec::new(), Vec::new());
    for e in events {
        f.apply(e);
        if let Event::Observation {
            t_ns: t,
            channel: c,
            value,
            ..
        } = e
            && c == channel
            && value.is_finite()
        {
            t_ns.push(*t);
            y.push(*value);
            for (j, v) in f.row().iter().enumerate() {
                x[j].push(*v);
            }
        }
    }
    let mut it = x.into_iter().skip(1);
    let spindle: Vec<Vec<f64>> = it.by_ref().take(cfg.taus_min.len()).collect();
    let temps = sensors
        .iter()
        .map(|_| it.by_ref().take(TEMPERATURE_TAUS_MIN.len()).collect())
        .collect();
    let speed2 = it.next().unwrap_or_default();
    Columns {
        t_ns,
        y,
        spindle,
        temps,
        speed2,
    }
}

/// The spindle speed in force at each of `t_ns` (sorted), and the speed changes.
fn speed_timeline(events: &[Event]) -> Vec<(i64, f64)> {
    let mut ch = Vec::new();
    let mut last = 0.0;
    for e in events {
        if let Event::Spindle { t_ns, rpm } = e
            && rpm.is_finite()
            // A measured speed jitters: a change is a move of more than 1 % (or from zero).
            && ((*rpm - last).abs() > 0.01 * last.abs().max(rpm.abs()))
        {
            ch.push((*t_ns, *rpm));
            last = *rpm;
        }
    }
    ch
}

fn phase_of(t: i64, changes: &[(i64, f64)]) -> &'static str {
    let k = changes.partition_point(|c| c.0 <= t);
    let (since, rpm) = match k {
        0 => (i64::MAX, 0.0),
        _ => (t - changes[k - 1].0, changes[k - 1].1),
    };
    let settling = since < units::NS_PER_H;
    match (rpm != 0.0, settling) {
        (true, true) => "warm-up",
        (true, false) => "steady",
        (false, true) => "cool-down",
        (false, false) => "idle",
    }
}

/// Diagnose every displacement channel of `events` (inputs and `Observation`s of
/// `channels`).
pub fn diagnose_displacements(
    events: &[Event],
    channels: &[String],
    opts: &DisplacementOptions,
) -> Result<DisplacementDiagnosis, DisplacementError> {
    let sensors = driftwatch_thermal::model::sensors_of(events);
    let cfg = ModelConfig {
        taus_min: DIAGNOSIS_TAUS_MIN.to_vec(),
        n_ref_rpm: opts.n_ref_rpm,
        gamma: opts.gamma,
        temperatures: crate::effects::temperature_inputs(&sensors),
        instant_speed: true,
        ..ModelConfig::default()
    };
    let obs_times: Vec<i64> = events
        .iter()
        .filter_map(|e| match e {
            Event::Observation { t_ns, channel, .. } if channels.contains(channel) => Some(*t_ns),
            _ => None,
        })
        .collect();
    let (Some(&t0), Some(&t1)) = (obs_times.iter().min(), obs_times.iter().max()) else {
        return Err(DisplacementError::NoReadings);
    };
    let holdout = opts
        .holdout_from_ns
        .unwrap_or(t0 + ((t1 - t0) as f64 * 0.85) as i64);
    let changes = speed_timeline(events);
    let h = |t: i64| units::ns_to_h(t - t0);

    let mut out = Vec::new();
    let mut not_carried = Vec::new();
    let mut skipped = Vec::new();
    for channel in channels {
        let c = columns(events, channel, &sensors, &cfg);
        let d = match diagnose_channel(channel, &c, &sensors, &changes, holdout, t0, opts) {
            Ok(d) => d,
            Err(e) => {
                skipped.push(e.to_string());
                continue;
            }
        };
        for term in &d.accepted {
            if term.input == ModelInput::None {
                not_carried.push(format!("{channel}: {}", term.term));
            }
        }
        out.push(d);
    }
    // The new model version: the baselines' modes and every accepted input, on the
    // reference speed and exponent the diagnosis used.
    let base = ModelConfig {
        taus_min: out
            .iter()
            .filter_map(|c| c.baseline_mode.as_ref().map(|m| m.tau_min))
            .collect(),
        temperatures: Vec::new(),
        n_ref_rpm: opts.n_ref_rpm,
        gamma: opts.gamma,
        ..ModelConfig::default()
    };
    let inputs: Vec<ModelInput> = out
        .iter()
        .flat_map(|c| c.accepted.iter().map(|t| t.input.clone()))
        .collect();
    let model = base.with_inputs(&inputs);
    if out.is_empty() {
        return Err(DisplacementError::NoChannel(skipped.join("; ")));
    }
    Ok(DisplacementDiagnosis {
        span_h: h(t1),
        heldout_from_h: h(holdout),
        sensors,
        channels: out,
        model,
        not_carried,
        skipped,
    })
}

/// Rolling origins over the training rows: at 1/2, then evenly to the last `n - 1`-th, each
/// fold fitted on the rows before it and judged on the rest of the training span (a term
/// must help predict what comes later, not fill a gap between known rows).
fn rolling_folds(train: &[usize], n: usize) -> Vec<(Vec<usize>, Vec<usize>)> {
    (0..n)
        .map(|k| train.len() / 2 + k * train.len() / (2 * n))
        .filter(|&o| o > 0 && o < train.len())
        .map(|o| (train[..o].to_vec(), train[o..].to_vec()))
        .collect()
}

/// `nb` blocks of the training span by time, each judged on a fit to the others.
fn leave_block_out(train: &[usize], times: &[i64], nb: usize) -> Vec<(Vec<usize>, Vec<usize>)> {
    let span = (times[train[train.len() - 1]] - times[train[0]]) as f64;
    (0..nb)
        .map(|b| {
            let (judge, fit): (Vec<usize>, Vec<usize>) = train.iter().partition(|&&i| {
                let f = (times[i] - times[train[0]]) as f64 / span;
                ((f * nb as f64) as usize).min(nb - 1) == b
            });
            (fit, judge)
        })
        .collect()
}

fn lag_label(sensor: &str, tau: f64) -> String {
    if tau == 0.0 {
        sensor.to_string()
    } else {
        format!("{sensor} lag {tau} min")
    }
}

/// The candidate columns of one channel on its thinned samples `keep` (times `t_min`): the
/// spindle lags and the speed term when the spindle turned, every temperature with its lags
/// and its fast swing, the day cycle.
fn candidates(
    c: &Columns,
    sensors: &[String],
    keep: &[usize],
    t_min: &[f64],
    spins: bool,
) -> Vec<Candidate> {
    let pick = |v: &[f64]| -> Vec<f64> { keep.iter().map(|&i| v[i]).collect() };
    let mut cands = Vec::new();
    for (k, tau) in DIAGNOSIS_TAUS_MIN.iter().enumerate().filter(|_| spins) {
        cands.push(Candidate {
            effect: "second_mode",
            term: format!("spindle lag {tau} min"),
            unit: "um per unit heat input",
            x: pick(&c.spindle[k]),
            input: ModelInput::SpindleLag { tau_min: *tau },
        });
    }
    for (s, sensor) in sensors.iter().enumerate() {
        for (k, tau) in TEMPERATURE_TAUS_MIN.iter().enumerate() {
            cands.push(Candidate {
                effect: "missing_temperature",
                term: lag_label(sensor, *tau),
                unit: "um/K",
                x: pick(&c.temps[s][k]),
                input: ModelInput::Temperature {
                    sensor: sensor.clone(),
                    taus_min: vec![*tau],
                },
            });
        }
        // The fast swing: the temperature less its 60-min lag.
        let hp: Vec<f64> = c.temps[s][0]
            .iter()
            .zip(&c.temps[s][1])
            .map(|(a, b)| a - b)
            .collect();
        cands.push(Candidate {
            effect: "coolant_cycle",
            term: format!("{sensor} less its 60-min lag"),
            unit: "um/K",
            x: pick(&hp),
            input: ModelInput::Temperature {
                sensor: sensor.clone(),
                taus_min: vec![0.0, 60.0],
            },
        });
    }
    let day = std::f64::consts::TAU / 1440.0;
    for (name, f) in [("sin", f64::sin as fn(f64) -> f64), ("cos", f64::cos)] {
        cands.push(Candidate {
            effect: "ambient",
            term: format!("24-h Fourier {name}"),
            unit: "um",
            x: t_min.iter().map(|t| f(day * t)).collect(),
            input: ModelInput::None,
        });
    }
    if spins {
        cands.push(Candidate {
            effect: "speed_shift",
            term: "(n/n_ref)^2".into(),
            unit: "um",
            x: pick(&c.speed2),
            input: ModelInput::InstantSpeed,
        });
    }
    cands
}

fn diagnose_channel(
    channel: &str,
    c: &Columns,
    sensors: &[String],
    changes: &[(i64, f64)],
    holdout: i64,
    t0: i64,
    opts: &DisplacementOptions,
) -> Result<ChannelDiagnosis, DisplacementError> {
    // Thinned samples.
    let keep = thinned(&c.t_ns, (opts.thin_s * 1e9) as i64);
    let pick = |v: &[f64]| -> Vec<f64> { keep.iter().map(|&i| v[i]).collect() };
    let times: Vec<i64> = keep.iter().map(|&i| c.t_ns[i]).collect();
    let t_min: Vec<f64> = times.iter().map(|t| (t - t0) as f64 / 6e10).collect();
    let (train, test) = split(&times, holdout, channel)?;

    // A spindle that never turned (no spindle log) gives columns of zeros: no spindle
    // candidate and no spindle mode in the baseline, or every design is singular.
    let spins = c.speed2.iter().any(|v| *v != 0.0);
    let cands = candidates(c, sensors, &keep, &t_min, spins);

    let blocks = if opts.rolling_origin {
        rolling_folds(&train, opts.blocks.max(2) + 1)
    } else {
        leave_block_out(&train, &times, opts.blocks.max(2))
    };
    let design = Design {
        cands: &cands,
        y: DVector::from_vec(pick(&c.y)),
        train,
        test,
        blocks,
        ar_max: opts.ar_max.max(1),
    };

    // Baseline: one spindle mode, its time constant by the training fit (the offset alone
    // without a spindle log).
    let ones = vec![1.0; keep.len()];
    let k0 = spins.then(|| spindle_mode(&design, &ones)).flatten();
    let base_cols: Vec<Vec<f64>> = std::iter::once(ones)
        .chain(k0.map(|k| cands[k].x.clone()))
        .collect();
    let m0 = design.matrix(&[], &base_cols);
    let (base_pred, baseline) = design.fit(&m0);
    let b0 = design.ols(&m0, &design.train);
    let baseline_mode = k0.map(|k| Mode {
        tau_min: DIAGNOSIS_TAUS_MIN[k],
        gain_um: b0[1],
        offset_um: b0[0],
    });
    let baseline_name = if spins {
        "one spindle mode"
    } else {
        "the offset alone (no spindle log)"
    };
    let resid: Vec<f64> = (0..keep.len())
        .map(|i| design.y[i] - base_pred[i])
        .collect();

    // Locate: phases, the periodic part and its driver.
    let phases = phase_residuals(&design.train, &times, changes, &resid);
    let temps_now: Vec<(String, Vec<f64>)> = sensors
        .iter()
        .enumerate()
        .map(|(s, name)| (name.clone(), pick(&c.temps[s][0])))
        .collect();
    let periodic = periodic_of(&design.train, &t_min, &resid, &temps_now, opts);

    let span = (t_min.as_slice(), temps_now.as_slice());
    let (run, thermal_base) = search_channel(&design, &base_cols, (k0, spins), span, channel, opts);
    let Search {
        sel,
        located_term,
        late_term,
        final_pred,
        final_fit,
        ..
    } = run;
    let Selection {
        chosen,
        mut accepted,
        refused,
        candidates_tested,
        surrogate_bars,
    } = sel;
    let final_resid: Vec<f64> = (0..keep.len())
        .map(|i| design.y[i] - final_pred[i])
        .collect();
    let unexplained = unexplained_of(&t_min, &final_resid, &temps_now, &final_fit);

    let transients = transients(c, t0, &t_min, changes, (&base_pred, &final_pred), opts);
    let overshoots = !transients.is_empty();
    for (t, &j) in accepted.iter_mut().zip(&chosen) {
        t.statement = statement(
            channel,
            &cands[j],
            t.value,
            t.sigma,
            baseline_mode.as_ref(),
            periodic.as_ref(),
            overshoots,
        );
    }
    accepted.extend(
        located_term
            .iter()
            .chain(&late_term)
            .filter(|l| l.accepted)
            .map(LocatedTerm::as_term),
    );
    if let Some(b) = thermal_base.as_ref().filter(|b| b.kept) {
        accepted.insert(0, b.term.clone());
    }
    let mut d = ChannelDiagnosis {
        channel: channel.to_string(),
        n_train: design.train.len(),
        n_heldout: design.test.len(),
        baseline_mode,
        baseline,
        final_fit,
        phases,
        periodic,
        transients,
        unexplained,
        thermal_base,
        located_term,
        late_term,
        candidates_tested,
        surrogate_bars,
        accepted,
        refused,
        statements: Vec::new(),
        series: ChannelSeries {
            t_h: t_min.iter().map(|t| t / 60.0).collect(),
            y_um: design.y.iter().copied().collect(),
            baseline_um: base_pred.iter().copied().collect(),
            final_um: final_pred.iter().copied().collect(),
        },
    };
    d.statements = statements_of(&d, changes, baseline_name, opts);
    Ok(d)
}

/// The training and held-out rows of thinned samples at `times`: before `holdout` and from
/// it; an error when either is too small to diagnose.
fn split(
    times: &[i64],
    holdout: i64,
    channel: &str,
) -> Result<(Vec<usize>, Vec<usize>), DisplacementError> {
    let train: Vec<usize> = (0..times.len()).filter(|&i| times[i] < holdout).collect();
    let test: Vec<usize> = (0..times.len()).filter(|&i| times[i] >= holdout).collect();
    if train.len() < 30 {
        return Err(DisplacementError::TooFewTraining(
            channel.into(),
            train.len(),
        ));
    }
    if test.is_empty() {
        return Err(DisplacementError::NoHeldOut(channel.into()));
    }
    Ok((train, test))
}

/// The search on the baseline `base_cols` (spindle mode `k0`, if the spindle turned);
/// without a spindle log, when it takes nothing, again on a thermal base (a temperature
/// carries the warm-up, as the spindle mode would), kept when the held-out veto keeps it.
fn search_channel(
    design: &Design,
    base_cols: &[Vec<f64>],
    (k0, spins): (Option<usize>, bool),
    span: (&[f64], &[(String, Vec<f64>)]),
    channel: &str,
    opts: &DisplacementOptions,
) -> (Search, Option<ThermalBase>) {
    let mut run = search(design, base_cols, (k0, spins), span, channel, opts);
    let base = if spins || !run.sel.chosen.is_empty() {
        None
    } else {
        thermal_base::settle(design, base_cols, &mut run, span, channel, opts)
    };
    (run, base)
}

/// One search on a baseline: the selection, the located terms, and the final model (its
/// columns beside the chosen candidates, its prediction on every reading and its fit).
struct Search {
    sel: Selection,
    located_term: Option<LocatedTerm>,
    late_term: Option<LocatedTerm>,
    final_cols: Vec<Vec<f64>>,
    final_pred: DVector<f64>,
    final_fit: Fit,
}

/// The forward selection, the located terms and the final model on the baseline
/// `base_cols` (candidate `k0` is in it; `warm_up`: the baseline models the warm-up).
fn search(
    design: &Design,
    base_cols: &[Vec<f64>],
    (k0, warm_up): (Option<usize>, bool),
    span: (&[f64], &[(String, Vec<f64>)]),
    channel: &str,
    opts: &DisplacementOptions,
) -> Search {
    let (mut sel, located_term, late_term) =
        select_and_locate(design, base_cols, (k0, warm_up), span, channel, opts);
    let final_cols = final_columns(
        design,
        base_cols,
        &sel.chosen,
        &[&located_term, &late_term],
        &mut sel.accepted,
    );
    let (final_pred, final_fit) = design.fit(&design.matrix(&sel.chosen, &final_cols));
    Search {
        sel,
        located_term,
        late_term,
        final_cols,
        final_pred,
        final_fit,
    }
}

/// The forward selection with its held-out veto, then what it leaves tied to a temperature
/// and made a term, settled by the veto over the model with it.
fn select_and_locate(
    design: &Design,
    base_cols: &[Vec<f64>],
    (k0, warm_up): (Option<usize>, bool),
    (t_min, temps_now): (&[f64], &[(String, Vec<f64>)]),
    channel: &str,
    opts: &DisplacementOptions,
) -> (Selection, Option<LocatedTerm>, Option<LocatedTerm>) {
    let mut sel = select(design, base_cols, k0, channel, opts, Scope::all(opts));
    // The selection's own veto first: the located search works on what its final model
    // leaves (located on the model before the veto, a late drift is sought in the misfit
    // of terms the veto drops, and fl-thermal's injected t11_C drift was tied to t4_C).
    if opts.heldout_veto {
        veto(
            design,
            base_cols,
            &mut sel.chosen,
            &mut sel.accepted,
            &mut sel.refused,
        );
    }
    // What the selection leaves, tied to a temperature and made a term; then the held-out
    // veto over the model with it.
    let found = located::locate(
        design,
        base_cols,
        &sel.chosen,
        t_min,
        temps_now,
        (channel, None),
        opts,
    );
    let located_term = settle(design, base_cols, &mut sel, found, t_min, channel, opts);
    let late_term = located_term.as_ref().and_then(|first| {
        late_located(
            design,
            base_cols,
            &mut sel,
            (first, warm_up),
            (t_min, temps_now),
            channel,
            opts,
        )
    });
    (sel, located_term, late_term)
}

/// A later, smaller departure than the one the first located search took: sought in its own
/// window, the latest part of the fit ([`LATE_WINDOW_SHARE`] of the training span on), on
/// the final model (with the first located term when that is accepted), then judged and
/// settled by the same rules. A first term that is not confirmed is left out: a term judged
/// on a model the diagnosis does not keep would have held-out figures of that model, not
/// of the final one (tried as a nuisance column on the 78-h spindle run, it made the
/// "before" the first candidate's 3.4 um instead of the final model's 1.8 um).
fn late_located(
    design: &Design,
    base_cols: &[Vec<f64>],
    sel: &mut Selection,
    (first, warm_up): (&LocatedTerm, bool),
    (t_min, temps_now): (&[f64], &[(String, Vec<f64>)]),
    channel: &str,
    opts: &DisplacementOptions,
) -> Option<LocatedTerm> {
    let (&a, &b) = (design.train.first()?, design.train.last()?);
    let from_min = t_min[a] + located::LATE_WINDOW_SHARE * (t_min[b] - t_min[a]);
    let cols: Vec<Vec<f64>> = base_cols
        .iter()
        .cloned()
        .chain(first.accepted.then(|| first.x.clone()))
        .collect();
    let found = located::locate(
        design,
        &cols,
        &sel.chosen,
        t_min,
        temps_now,
        (channel, Some(from_min)),
        opts,
    )?;
    let mut late = settle(design, &cols, sel, Some(found), t_min, channel, opts)?;
    // Judged on a final model that leaves the largest departure unexplained, a later term
    // is scored against that departure's misfit as well as its own drift: name it, and the
    // recording that would judge the later term on what a model of the earlier one leaves.
    if !first.accepted && late.reason == Some(NotConfirmed::NotSupported) {
        let split = format!(
            "the final model leaves the largest departure ({}) unexplained, and its misfit is in every score of this later one: a recording whose earlier drift the model explains ({}) would judge it on what that leaves",
            first.term,
            if warm_up {
                "e.g. one that goes on steady for longer before the later drift"
            } else {
                "with the spindle speed logged, the baseline would model the warm-up"
            }
        );
        late.statement
            .push_str(&format!("; what would confirm it: {split}"));
        late.split_by = Some(split);
    }
    Some(late)
}

/// The columns of the final model beside the chosen candidates: the baseline's, and the
/// located terms' that are accepted (then every accepted term's held-out figures are
/// recomputed on that model).
fn final_columns(
    design: &Design,
    base_cols: &[Vec<f64>],
    chosen: &[usize],
    located: &[&Option<LocatedTerm>],
    accepted: &mut [Term],
) -> Vec<Vec<f64>> {
    let cols: Vec<Vec<f64>> = base_cols
        .iter()
        .cloned()
        .chain(
            located
                .iter()
                .filter_map(|l| l.as_ref().filter(|l| l.accepted))
                .map(|l| l.x.clone()),
        )
        .collect();
    heldout_figures(design, &cols, chosen, accepted);
    cols
}

/// What the final fit (`final_fit`, residuals `final_resid` at `t_min`) leaves: where it
/// departs from zero, with the temperatures `temps` that follow it and the onset of a late
/// drift; none when it does not depart.
fn unexplained_of(
    t_min: &[f64],
    final_resid: &[f64],
    temps: &[(String, Vec<f64>)],
    final_fit: &Fit,
) -> Option<Unexplained> {
    locate_departure(t_min, final_resid, temps).map(|d| Unexplained {
        ar1: final_fit.ar1,
        ljung_box_p: final_fit.ljung_box_p,
        structured: final_fit.ar1.abs() > 0.5 && final_fit.ljung_box_p < 0.01,
        from_h: t_min[d.from] / 60.0,
        to_h: t_min[d.to] / 60.0,
        mean_um: d.mean,
        drivers: d.drivers,
        onset: locate_onset(t_min, final_resid, temps),
    })
}

/// The samples at times `t_ns` kept when thinned to one per `step` ns.
fn thinned(t_ns: &[i64], step: i64) -> Vec<usize> {
    let mut keep = Vec::new();
    for (i, &t) in t_ns.iter().enumerate() {
        if keep.last().is_none_or(|&k: &usize| t - t_ns[k] >= step) {
            keep.push(i);
        }
    }
    keep
}

/// The baseline's spindle mode: the pole of [`DIAGNOSIS_TAUS_MIN`] (candidate index) whose
/// one-mode fit with the offset `ones` has the lowest training RMS.
fn spindle_mode(design: &Design, ones: &[f64]) -> Option<usize> {
    let mut best: Option<(f64, usize)> = None;
    for k in 0..DIAGNOSIS_TAUS_MIN.len() {
        let m = design.matrix(&[k], &[ones.to_vec()]);
        let (_, f) = design.fit(&m);
        if best.is_none_or(|b| f.rms_train_um < b.0) {
            best = Some((f.rms_train_um, k));
        }
    }
    best.map(|b| b.1)
}

/// The baseline's residuals `resid` on the training rows `train` by the phase of the
/// spindle program (`changes`) at their times.
fn phase_residuals(
    train: &[usize],
    times: &[i64],
    changes: &[(i64, f64)],
    resid: &[f64],
) -> Vec<PhaseResidual> {
    let mut phases: BTreeMap<&'static str, Vec<f64>> = BTreeMap::new();
    for &i in train {
        phases
            .entry(phase_of(times[i], changes))
            .or_default()
            .push(resid[i]);
    }
    phases
        .into_iter()
        .map(|(phase, v)| PhaseResidual {
            phase,
            n: v.len(),
            mean_um: v.iter().sum::<f64>() / v.len() as f64,
            rms_um: rms(v.iter().copied()),
        })
        .collect()
}

/// The periodic part of the baseline's residuals `resid` on the training rows `train`
/// (times `t_min`) in the band `opts.band_min`, and its driver among the temperatures
/// `temps` (each sensor's reading per row); none when it is not a line.
fn periodic_of(
    train: &[usize],
    t_min: &[f64],
    resid: &[f64],
    temps: &[(String, Vec<f64>)],
    opts: &DisplacementOptions,
) -> Option<Periodic> {
    let tt: Vec<f64> = train.iter().map(|&i| t_min[i]).collect();
    let band = |v: &[f64]| -> Vec<f64> {
        let tr: Vec<f64> = train.iter().map(|&i| v[i]).collect();
        let slow = moving_average(&tt, &tr, opts.band_min.1);
        tr.iter().zip(slow).map(|(a, b)| a - b).collect()
    };
    let rb = band(resid);
    let (period, amp) = strongest_period(&tt, &rb, opts.band_min);
    // A line, not the noise's highest point: a logged temperature swings with it, or it
    // stands 5 times above the band's median amplitude (white noise reaches about 4).
    let median_amp = {
        let mut a = Vec::new();
        let mut p = opts.band_min.0;
        while p <= opts.band_min.1 {
            a.push(strongest_period(&tt, &rb, (p, p)).1);
            p += 0.25;
        }
        driftwatch_core::stats::median(&a).unwrap_or(0.0)
    };
    // The driver: among the sensors that swing at the residual's period (within 20 %), the
    // one whose band correlates best with it; else the best-correlated of all, unmatched.
    let periodic = period.is_finite().then(|| {
        let mut best: Option<(bool, f64, String, f64)> = None;
        for (sensor, temp) in temps {
            let tb = band(temp);
            let r = corr(&rb, &tb);
            let p = strongest_period(&tt, &tb, opts.band_min).0;
            let matched = ((p - period) / period).abs() < 0.2 && r.abs() >= 0.3;
            if best
                .as_ref()
                .is_none_or(|b| (matched, r.abs()) > (b.0, b.1.abs()))
            {
                best = Some((matched, r, sensor.clone(), p));
            }
        }
        Periodic {
            period_min: period,
            amplitude_um: amp,
            band_rms_um: rms(rb.iter().copied()),
            matched: best.as_ref().is_some_and(|b| b.0),
            driver_r: best.as_ref().map_or(0.0, |b| b.1),
            driver_period_min: best.as_ref().map_or(f64::NAN, |b| b.3),
            driver: best.map(|b| b.2),
        }
    });
    periodic.filter(|p| p.matched || p.amplitude_um >= 5.0 * median_amp)
}

/// Transients after each speed change, on the full-rate readings of `c` (30-min smoothing),
/// with what the baseline and the final model (`preds`, on the thinned times `t_min`) make
/// of them.
fn transients(
    c: &Columns,
    t0: i64,
    t_min: &[f64],
    changes: &[(i64, f64)],
    (base_pred, final_pred): (&DVector<f64>, &DVector<f64>),
    opts: &DisplacementOptions,
) -> Vec<Transient> {
    let full_t: Vec<f64> = c.t_ns.iter().map(|t| (t - t0) as f64 / 6e10).collect();
    let ys = moving_average(&full_t, &c.y, 30.0);
    let interp = |p: &DVector<f64>| -> Vec<f64> {
        let ts = t_min;
        let raw: Vec<f64> = full_t
            .iter()
            .map(|t| {
                let k = ts.partition_point(|x| x <= t);
                match k {
                    0 => p[0],
                    k if k >= ts.len() => p[ts.len() - 1],
                    k => {
                        let w = (t - ts[k - 1]) / (ts[k] - ts[k - 1]);
                        p[k - 1] * (1.0 - w) + p[k] * w
                    }
                }
            })
            .collect();
        moving_average(&full_t, &raw, 30.0)
    };
    let (base_full, final_full) = (interp(base_pred), interp(final_pred));
    let mut transients = Vec::new();
    for (k, &(t_change, rpm)) in changes.iter().enumerate() {
        let from = if k == 0 { 0.0 } else { changes[k - 1].1 };
        let end = changes.get(k + 1).map_or(i64::MAX, |c| c.0);
        // From 15 min after the change (beyond the smoothing) to 15 min before the next,
        // at most 4 h.
        let a = t_change + 900_000_000_000;
        let b = end
            .saturating_sub(900_000_000_000)
            .min(t_change + 4 * units::NS_PER_H);
        let idx: Vec<usize> = (0..c.t_ns.len())
            .filter(|&i| c.t_ns[i] >= a && c.t_ns[i] <= b)
            .collect();
        if idx.len() < 10 {
            continue;
        }
        let ex = |v: &[f64]| excursion(&idx.iter().map(|&i| v[i]).collect::<Vec<_>>());
        let (e, at) = ex(&ys);
        if e < opts.min_overshoot_um {
            continue;
        }
        transients.push(Transient {
            at_h: units::ns_to_h(t_change - t0),
            from_rpm: from,
            to_rpm: rpm,
            excursion_um: e,
            after_min: (c.t_ns[idx[at]] - t_change) as f64 / 6e10,
            baseline_excursion_um: ex(&base_full).0,
            final_excursion_um: ex(&final_full).0,
        });
    }
    transients
}

/// What the diagnosis of one channel found, in words.
fn statements_of(
    d: &ChannelDiagnosis,
    changes: &[(i64, f64)],
    baseline_name: &str,
    opts: &DisplacementOptions,
) -> Vec<String> {
    let channel = d.channel.as_str();
    let (periodic, transients, accepted) = (&d.periodic, &d.transients, &d.accepted);
    let (unexplained, baseline, final_fit) = (&d.unexplained, &d.baseline, &d.final_fit);
    let candidates_tested = d.candidates_tested;
    let mut statements = Vec::new();
    if let Some(p) = &periodic {
        statements.push(format!(
            "{channel}: the residual of {baseline_name} has a {:.1}-min periodic part ({:.2} um amplitude, {:.2} um RMS in the {}-{} min band){}",
            p.period_min,
            p.amplitude_um,
            p.band_rms_um,
            opts.band_min.0,
            opts.band_min.1,
            match &p.driver {
                Some(d) if p.matched => format!(
                    "; {d} swings with it (band correlation {:.2}, its own strongest period {:.1} min): {}",
                    p.driver_r,
                    p.driver_period_min,
                    if p.driver_r.abs() >= 0.5 {
                        "the driver of the cycle"
                    } else {
                        "a candidate driver, weakly correlated"
                    }
                ),
                Some(d) => format!(
                    "; no logged temperature has that period (the best-correlated, {d}, r {:.2}, swings at {:.1} min)",
                    p.driver_r, p.driver_period_min
                ),
                None => String::new(),
            }
        ));
    }
    let stops: Vec<&Transient> = transients.iter().filter(|t| t.to_rpm == 0.0).collect();
    if !stops.is_empty() {
        let n_stops = changes.iter().filter(|c| c.1 == 0.0).count();
        statements.push(format!(
            "{channel}: after {} of {} stops the displacement overshoots by {} um ({} min after the stop) and comes back; one thermal mode decays monotonically and cannot make this (its excursion: {:.2} um at most), the final model makes {} um",
            stops.len(),
            n_stops,
            stops.iter().map(|t| format!("{:.1}", t.excursion_um)).collect::<Vec<_>>().join(", "),
            stops.iter().map(|t| format!("{:.0}", t.after_min)).collect::<Vec<_>>().join(", "),
            stops.iter().map(|t| t.baseline_excursion_um).fold(0.0, f64::max),
            stops.iter().map(|t| format!("{:.1}", t.final_excursion_um)).collect::<Vec<_>>().join(", "),
        ));
    }
    statements.extend(accepted.iter().map(|t| t.statement.clone()));
    if let Some(b) = d.thermal_base.as_ref().filter(|b| !b.kept) {
        statements.push(b.statement.clone());
        for (what, l) in [("", &b.located_term), ("later departure, ", &b.late_term)] {
            if let Some(l) = l {
                statements.push(format!(
                    "(on the vetoed thermal base, {what}not in the final model) {}",
                    l.statement
                ));
            }
        }
    }
    if candidates_tested == 0 {
        statements.push(format!(
            "{channel}: no candidate could be tested: every design with one was singular (an input that never changes?)"
        ));
    }
    if let Some(u) = unexplained.as_ref().filter(|u| u.structured) {
        statements.push(format!(
            "{channel}: what the final model leaves is not noise (lag-1 autocorrelation {:.2}, Ljung-Box p {:.3}); its largest departure runs from {:.1} h to {:.1} h, {:+.2} um on average{}",
            u.ar1,
            u.ljung_box_p,
            u.from_h,
            u.to_h,
            u.mean_um,
            if u.drivers.is_empty() {
                String::new()
            } else {
                format!(
                    "; the temperatures that follow it there: {}",
                    u.drivers
                        .iter()
                        .map(|(n, r)| format!("{n} (r {r:.2})"))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
        ));
    }
    // The located term is the one statement of the drift it models (accepted, it is among
    // the accepted terms above); without one, the onset is, when it stands out over no
    // change.
    if let Some(l) = d.located_term.as_ref().filter(|l| !l.accepted) {
        statements.push(l.statement.clone());
    }
    if let Some(l) = d.late_term.as_ref().filter(|l| !l.accepted) {
        statements.push(format!("(later departure) {}", l.statement));
    }
    if let Some(o) = unexplained
        .as_ref()
        .filter(|_| d.located_term.is_none())
        .and_then(|u| u.onset.as_ref())
        .filter(|o| o.delta_bic >= 10.0)
    {
        statements.push(format!(
            "{channel}: the residual is best followed by a drift from {:.1} h (between {:.1} and {:.1} h) of {:.2} um/K of {}'s change since then (delta-BIC {:.0} over no change and {:.0} over a step or ramp that follows no temperature, on {:.0} independent samples); {}",
            o.at_h,
            o.earliest_h,
            o.latest_h,
            o.gain_um_per_k,
            o.sensor,
            o.delta_bic,
            o.delta_bic_vs_shape,
            o.n_eff,
            if o.tied {
                format!("{} is told apart from every other sensor", o.sensor)
            } else {
                format!(
                    "it cannot be told apart from {}",
                    if o.delta_bic_vs_shape < 10.0 {
                        "a change that follows no temperature".to_string()
                    } else {
                        o.others
                            .iter()
                            .filter(|x| o.delta_bic - x.1 < 10.0)
                            .map(|(n, b)| format!("{n} (delta-BIC {b:.0})"))
                            .collect::<Vec<_>>()
                            .join(", ")
                    }
                )
            }
        ));
    }
    statements.push(format!(
        "{channel}: held-out RMS {:.2} um with {baseline_name}, {:.2} um with the accepted terms{}; training {:.2} -> {:.2} um",
        baseline.rms_heldout_um,
        final_fit.rms_heldout_um,
        if opts.heldout_veto {
            " (the held-out end vetoed terms that worsen it: a validation figure, not a blind test)"
        } else {
            ""
        },
        baseline.rms_train_um,
        final_fit.rms_train_um
    ));
    statements
}

/// One candidate's figures when added to the model `m` (whitened with `phi`): `cols` are the
/// model's candidates and this one, on `base_cols`; and why it is refused, if it is.
struct Judged {
    value: f64,
    sd: f64,
    t: f64,
    wins: usize,
    reason: Option<String>,
}

fn judge(
    design: &Design,
    cand: &Candidate,
    base_cols: &[Vec<f64>],
    cols: &[usize],
    m: &DMatrix<f64>,
    phi: &[f64],
    opts: &DisplacementOptions,
) -> Judged {
    judge_column(
        design,
        &cand.x,
        m,
        &design.matrix(cols, base_cols),
        phi,
        opts,
    )
}

/// The rules of [`judge`] for a column `xs` (on every row) that is the last of the model
/// `m2`, `m` being the model without it: shared by the forward selection and the located
/// term, so that both meet the same rules.
fn judge_column(
    design: &Design,
    xs: &[f64],
    m: &DMatrix<f64>,
    m2: &DMatrix<f64>,
    phi: &[f64],
    opts: &DisplacementOptions,
) -> Judged {
    let (mw2, yw2) = design.whiten(m2, phi);
    let f = lsq(&mw2, &yw2);
    let p = m2.ncols();
    let s2 = f.chi2 / yw2.len().saturating_sub(p).max(1) as f64;
    let sd = (f.cov[(p - 1, p - 1)] * s2).sqrt();
    let t = f.beta[p - 1] / sd;
    let (wins, overall) = design.blocks_improved(m, m2);
    let range = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max)
        - xs.iter().copied().fold(f64::INFINITY, f64::min);
    let footprint = (f.beta[p - 1] * range).abs();
    let reason = if t.abs() < opts.min_t {
        Some(format!("|t| {:.1} < {}", t.abs(), opts.min_t))
    } else if wins < opts.min_blocks_improved || (opts.rolling_origin && !overall) {
        Some(format!(
            "improves {wins} of {} {} (needs {}{})",
            design.blocks.len(),
            if opts.rolling_origin {
                "rolling-origin predictions"
            } else {
                "held-out blocks"
            },
            opts.min_blocks_improved,
            if opts.rolling_origin {
                ", and their sum"
            } else {
                ""
            }
        ))
    } else if footprint > opts.max_um {
        Some(format!(
            "footprint {footprint:.0} um > {} um plausible",
            opts.max_um
        ))
    } else {
        None
    };
    Judged {
        value: f.beta[p - 1],
        sd,
        t,
        wins,
        reason,
    }
}

/// What a forward selection may take and how it scores it: the whole search ([`Scope::all`])
/// or the thermal base ([`thermal_base`]).
#[derive(Debug, Clone, Copy)]
struct Scope {
    /// The noise model a candidate is scored with.
    noise: NoiseModel,
    /// Only candidates of this effect (none: every one).
    only: Option<&'static str>,
    max_terms: usize,
    /// Mixed into the surrogates' seed, so that two selections on one channel draw apart.
    seed_tag: u64,
}

impl Scope {
    /// The forward selection of the search: every candidate, the options' rules.
    fn all(opts: &DisplacementOptions) -> Scope {
        Scope {
            noise: opts.noise,
            only: None,
            max_terms: opts.max_terms,
            seed_tag: 0,
        }
    }
}

/// What the selection keeps of one channel: the chosen candidates (indices), their terms,
/// each refused candidate's last refusal, how many could be scored, the surrogate bars.
struct Selection {
    chosen: Vec<usize>,
    accepted: Vec<Term>,
    refused: Vec<RefusedTerm>,
    candidates_tested: usize,
    surrogate_bars: Vec<f64>,
}

/// Forward selection over `cands` on the baseline `base_cols` (candidate `k0` is in it),
/// backward pruning, then the held-out veto: the acceptance rules of
/// [`DisplacementOptions`].
fn select(
    design: &Design,
    base_cols: &[Vec<f64>],
    k0: Option<usize>,
    channel: &str,
    opts: &DisplacementOptions,
    scope: Scope,
) -> Selection {
    let cands = design.cands;
    let n_w = design.train.len() - design.ar_max;
    let mut scoring = DisplacementScoring {
        design,
        cands,
        base_cols,
        k0,
        channel,
        opts,
        n_w,
        scope,
        ln_n: (n_w as f64).ln(),
        m: DMatrix::zeros(0, 0),
        phis: Vec::new(),
        scored: Vec::new(),
        bar: opts.min_delta_bic,
        accepted: Vec::new(),
        refused: Vec::new(),
        candidates_tested: 0,
        surrogate_bars: Vec::new(),
    };
    let rules = Rules {
        max_terms: scope.max_terms,
        tries: 10,
        min_worth: opts.min_delta_bic,
    };
    let chosen = stepwise(&mut scoring, &rules);
    let DisplacementScoring {
        accepted,
        refused,
        candidates_tested,
        surrogate_bars,
        ..
    } = scoring;
    Selection {
        chosen,
        accepted,
        refused,
        candidates_tested,
        surrogate_bars,
    }
}

/// The final model: the located candidate `found` (searched on what the selection leaves)
/// joins it if it passes every rule and the held-out veto, applied to the model with it,
/// keeps it (a term of the selection that only the located one makes pay is not dropped
/// before the located one is tried); the veto then drops any term, the located one
/// included, that worsens the held-out end. Each term's held-out figures are those of the
/// final model without it and with it; one entry per refused candidate (its last refusal).
#[allow(clippy::too_many_arguments)]
fn settle(
    design: &Design,
    base_cols: &[Vec<f64>],
    sel: &mut Selection,
    found: Option<located::Found>,
    t_min: &[f64],
    channel: &str,
    opts: &DisplacementOptions,
) -> Option<LocatedTerm> {
    let held =
        |cols: &[usize], base: &[Vec<f64>]| design.fit(&design.matrix(cols, base)).1.rms_heldout_um;
    let veto_on = |base: &[Vec<f64>], sel: &mut Selection| {
        if opts.heldout_veto {
            veto(
                design,
                base,
                &mut sel.chosen,
                &mut sel.accepted,
                &mut sel.refused,
            );
        }
    };
    let located = found.map(|mut f| {
        let with: Vec<Vec<f64>> = base_cols.iter().cloned().chain([f.x.clone()]).collect();
        let mut trial = Selection {
            chosen: sel.chosen.clone(),
            accepted: sel.accepted.clone(),
            refused: sel.refused.clone(),
            candidates_tested: sel.candidates_tested,
            surrogate_bars: Vec::new(),
        };
        veto_on(&with, &mut trial);
        let (before, after) = (held(&trial.chosen, base_cols), held(&trial.chosen, &with));
        if located::passes_before_veto(&f) && (after <= before || !opts.heldout_veto) {
            sel.chosen = trial.chosen;
            sel.accepted = trial.accepted;
            sel.refused = trial.refused;
        } else {
            veto_on(base_cols, sel);
        }
        f.before = held(&sel.chosen, base_cols);
        f.after = held(&sel.chosen, &with);
        located::verdict(design, t_min, f, channel, opts)
    });
    if located.is_none() {
        veto_on(base_cols, sel);
    }
    // One entry per candidate: its last refusal, none for what was accepted.
    let accepted = &sel.accepted;
    let mut seen = std::collections::BTreeSet::new();
    sel.refused.reverse();
    sel.refused
        .retain(|r| !accepted.iter().any(|a| a.term == r.term) && seen.insert(r.term.clone()));
    sel.refused.reverse();
    located
}

/// The displacement search's scoring for [`stepwise`], on the training rows whitened by the
/// AR model of the current model's residuals: a candidate ranks by delta-BIC (`n ln(SSE0 /
/// SSE) - ln n`) and must reach the fixed bar and what phase-randomised candidates reach by
/// chance, then pass [`judge`]; a chosen term is worth the delta-BIC of dropping it.
struct DisplacementScoring<'d> {
    design: &'d Design<'d>,
    cands: &'d [Candidate],
    base_cols: &'d [Vec<f64>],
    k0: Option<usize>,
    channel: &'d str,
    opts: &'d DisplacementOptions,
    /// What the selection may take and how it scores it ([`Scope`]).
    scope: Scope,
    /// Whitened training rows, and `ln` of them.
    n_w: usize,
    ln_n: f64,
    /// The current forward step: its model, each candidate's AR coefficients (those it was
    /// scored with), the ranking and the bar.
    m: DMatrix<f64>,
    phis: Vec<Vec<f64>>,
    scored: Vec<(f64, usize)>,
    bar: f64,
    accepted: Vec<Term>,
    refused: Vec<RefusedTerm>,
    candidates_tested: usize,
    surrogate_bars: Vec<f64>,
}

impl DisplacementScoring<'_> {
    /// The bar of a forward step after `chosen` over the ranking `scored`, against the
    /// model of `scorer`: the fixed delta-BIC, and what the best of these candidates reaches
    /// on phase-randomised copies (only worth computing when the best real one passes the
    /// fixed bar).
    fn bar(&mut self, chosen: &[usize], scorer: &scoring::ColumnScorer) -> f64 {
        let opts = self.opts;
        let passes_fixed = self
            .scored
            .first()
            .is_some_and(|s| s.0 >= opts.min_delta_bic);
        if opts.surrogates == 0 || !passes_fixed {
            return opts.min_delta_bic;
        }
        let cols: Vec<Vec<f64>> = self
            .scored
            .iter()
            .map(|s| {
                self.design
                    .train
                    .iter()
                    .map(|&i| self.cands[s.1].x[i])
                    .collect()
            })
            .collect();
        let seed = opts.seed
            ^ self.scope.seed_tag
            ^ self.channel.bytes().fold(chosen.len() as u64, |h, b| {
                h.wrapping_mul(31).wrapping_add(b as u64)
            });
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let b = scorer.surrogate_bar(&cols, opts.surrogates, &mut rng);
        self.surrogate_bars.push(b);
        b.max(opts.min_delta_bic)
    }
}

impl Scoring for DisplacementScoring<'_> {
    fn rank(&mut self, chosen: &[usize]) -> Vec<(usize, f64)> {
        let design = self.design;
        self.m = design.matrix(chosen, self.base_cols);
        let scorer = scoring::ColumnScorer::new(design, &self.m, self.scope.noise);
        self.phis = vec![Vec::new(); self.cands.len()];
        let mut scored: Vec<(f64, usize)> = Vec::new();
        let only = self.scope.only;
        for j in (0..self.cands.len()).filter(|j| {
            Some(*j) != self.k0
                && !chosen.contains(j)
                && only.is_none_or(|e| self.cands[*j].effect == e)
        }) {
            let x: Vec<f64> = design.train.iter().map(|&i| self.cands[j].x[i]).collect();
            if let Some(s) = scorer.score(&x, 0) {
                scored.push((s.delta_bic, j));
                self.phis[j] = s.phi;
            }
        }
        scored.sort_by(|a, b| b.0.total_cmp(&a.0));
        if chosen.is_empty() {
            self.candidates_tested = scored.len();
        }
        self.scored = scored;
        self.bar = self.bar(chosen, &scorer);
        self.scored.iter().map(|&(db, j)| (j, db)).collect()
    }

    fn judge(&mut self, chosen: &[usize], j: usize, db: f64) -> Verdict {
        let (cands, opts, bar) = (self.cands, self.opts, self.bar);
        if db < bar {
            if db >= opts.min_delta_bic {
                self.refused.push(RefusedTerm {
                    effect: cands[j].effect,
                    term: cands[j].term.clone(),
                    delta_bic: db,
                    t: f64::NAN,
                    blocks_improved: 0,
                    reason: format!(
                        "delta-BIC {db:.1} below what the best of {} phase-randomised candidates reaches by chance here ({bar:.1}, the highest of {} replicates)",
                        self.scored.len(),
                        opts.surrogates
                    ),
                });
            }
            return Verdict::Stop;
        }
        let Judged {
            value,
            sd,
            t,
            wins,
            reason,
        } = judge(
            self.design,
            &cands[j],
            self.base_cols,
            &[chosen, &[j]].concat(),
            &self.m,
            &self.phis[j],
            opts,
        );
        if let Some(reason) = reason {
            self.refused.push(RefusedTerm {
                effect: cands[j].effect,
                term: cands[j].term.clone(),
                delta_bic: db,
                t,
                blocks_improved: wins,
                reason,
            });
            return Verdict::Refuse;
        }
        let ambiguous_with: Vec<String> = self
            .scored
            .iter()
            .filter(|(s, k)| *k != j && db - s < 10.0)
            .take(4)
            .map(|(_, k)| cands[*k].term.clone())
            .collect();
        let cand = &cands[j];
        self.accepted.push(Term {
            effect: cand.effect,
            term: cand.term.clone(),
            unit: cand.unit,
            value,
            sigma: sd,
            delta_bic: db,
            t,
            blocks_improved: wins,
            heldout_before_um: f64::NAN,
            heldout_after_um: f64::NAN,
            ambiguous_with,
            input: cand.input.clone(),
            // Written once the whole channel is known.
            statement: String::new(),
        });
        Verdict::Take
    }

    /// Backward pruning: a term the others have made redundant is worth little.
    fn worth(&mut self, chosen: &[usize]) -> Vec<f64> {
        let design = self.design;
        let (phi, _, _, sse) = design.whitened(&design.matrix(chosen, self.base_cols));
        (0..chosen.len())
            .map(|k| {
                let mut rest = chosen.to_vec();
                rest.remove(k);
                let (mw, yw) = design.whiten(&design.matrix(&rest, self.base_cols), &phi);
                self.n_w as f64 * (lsq(&mw, &yw).chi2 / sse).ln() - self.ln_n
            })
            .collect()
    }

    fn pruned(&mut self, _chosen: &[usize], pos: usize, db: f64) {
        let t = self.accepted.remove(pos);
        self.refused.push(RefusedTerm {
            effect: t.effect,
            term: t.term,
            delta_bic: db,
            t: t.t,
            blocks_improved: t.blocks_improved,
            reason: "pruned: the later terms make it redundant".into(),
        });
    }
}

/// The held-out veto: while dropping a term lowers the held-out RMS, drop the one whose loss
/// lowers it most (refused, with both figures).
fn veto(
    design: &Design,
    base_cols: &[Vec<f64>],
    chosen: &mut Vec<usize>,
    accepted: &mut Vec<Term>,
    refused: &mut Vec<RefusedTerm>,
) {
    let held = |cols: &[usize]| design.fit(&design.matrix(cols, base_cols)).1.rms_heldout_um;
    while !chosen.is_empty() {
        let now = held(chosen);
        let Some((without, k)) = (0..chosen.len())
            .map(|k| {
                let mut rest = chosen.clone();
                rest.remove(k);
                (held(&rest), k)
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
        else {
            break;
        };
        if without >= now {
            break;
        }
        chosen.remove(k);
        let t = accepted.remove(k);
        refused.push(RefusedTerm {
            effect: t.effect,
            term: t.term,
            delta_bic: t.delta_bic,
            t: t.t,
            blocks_improved: t.blocks_improved,
            reason: format!(
                "vetoed: worsens the held-out end ({without:.2} um without it, {now:.2} um with it)"
            ),
        });
    }
}

/// Each term's held-out figures: the final model without it and with it.
fn heldout_figures(
    design: &Design,
    base_cols: &[Vec<f64>],
    chosen: &[usize],
    accepted: &mut [Term],
) {
    let held = |cols: &[usize]| design.fit(&design.matrix(cols, base_cols)).1.rms_heldout_um;
    let now = held(chosen);
    for (k, term) in accepted.iter_mut().enumerate() {
        let mut rest = chosen.to_vec();
        rest.remove(k);
        term.heldout_before_um = held(&rest);
        term.heldout_after_um = now;
    }
}

fn statement(
    channel: &str,
    c: &Candidate,
    value: f64,
    sd: f64,
    base: Option<&Mode>,
    periodic: Option<&Periodic>,
    overshoots: bool,
) -> String {
    let v = format!("{value:.3} ± {sd:.3} {}", c.unit);
    match c.effect {
        "second_mode" => format!(
            "{channel}: a second thermal mode, {} ({v}){}",
            c.term,
            match base {
                Some(base)
                    if overshoots
                        && base.gain_um != 0.0
                        && value.signum() != base.gain_um.signum() =>
                {
                    format!(
                        ", of opposite sign to the baseline's {:.0}-min mode ({:.2} um): together they make the overshoot one mode cannot",
                        base.tau_min, base.gain_um
                    )
                }
                _ => String::new(),
            }
        ),
        "missing_temperature" | "coolant_cycle" => {
            let sensor = match &c.input {
                ModelInput::Temperature { sensor, .. } => sensor.as_str(),
                _ => "",
            };
            let carries = periodic
                .filter(|p| p.matched && p.driver.as_deref() == Some(sensor))
                .map(|p| {
                    format!(
                        "; it carries the {:.1}-min cycle of the residual (a coolant or chiller cycle)",
                        p.period_min
                    )
                })
                .unwrap_or_default();
            let what = if c.effect == "coolant_cycle" {
                "the fast swing of a logged temperature"
            } else {
                "a temperature input the baseline lacks"
            };
            format!("{channel}: {what}, {} at {v}{carries}", c.term)
        }
        "ambient" => format!("{channel}: a day cycle, {} ({v})", c.term),
        _ => format!("{channel}: {} ({v})", c.term),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    const MIN: i64 = units::NS_PER_MIN;

    /// A 40-h thermal test at one reading per minute: 4-h runs at rising speeds and 4-h
    /// stops; one 35-min spindle mode of 20 um, plus `extra(t_min, chiller)`; a chiller
    /// temperature swinging 0.5 K with a 25-min period and a room sensor that drifts.
    /// The room temperature at minute `t`: a slow swing and a half-day one, so that a drift
    /// that follows it differs from a plain ramp.
    fn room_at(t: f64) -> f64 {
        22.0 + 0.3 * (t / 600.0).sin() + 0.15 * (t / 110.0).sin()
    }

    fn recording(seed: u64, extra: impl Fn(f64, f64, f64) -> f64) -> Vec<Event> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let noise = Normal::new(0.0, 0.2).unwrap();
        let mut ev = Vec::new();
        let (mut x, mut slow) = (0.0, 0.0);
        for m in 0..2400i64 {
            let t = m as f64;
            let block = m / 240;
            let rpm = if block % 2 == 0 {
                1000.0 * (block / 2 + 1) as f64
            } else {
                0.0
            };
            let u = (rpm / 5000.0f64).powf(1.5);
            let chiller = 20.0 + 0.5 * (std::f64::consts::TAU * t / 25.0).sin();
            let room = room_at(t);
            let t_ns = m * MIN;
            ev.push(Event::Spindle { t_ns, rpm });
            for (sensor, celsius) in [("chiller", chiller), ("room", room)] {
                ev.push(Event::Temperature {
                    t_ns,
                    sensor: sensor.into(),
                    celsius,
                });
            }
            ev.push(Event::Observation {
                t_ns,
                channel: "z".into(),
                value: 20.0 * x + extra(t, chiller - 20.0, slow) + noise.sample(&mut rng),
                sigma: None,
            });
            // The input holds until the next minute.
            x += (u - x) * (1.0 - (-1.0f64 / 35.0).exp());
            slow += (u - slow) * (1.0 - (-1.0f64 / 100.0).exp());
        }
        ev
    }

    fn run(ev: &[Event]) -> ChannelDiagnosis {
        let opts = DisplacementOptions {
            n_ref_rpm: 5000.0,
            ..Default::default()
        };
        let mut d = diagnose_displacements(ev, &["z".to_string()], &opts).unwrap();
        d.channels.remove(0)
    }

    #[test]
    fn one_mode_and_noise_select_nothing() {
        for seed in 0..10 {
            let c = run(&recording(seed, |_, _, _| 0.0));
            assert_eq!(c.baseline_mode.as_ref().unwrap().tau_min, 35.0);
            assert!(c.accepted.is_empty(), "seed {seed}: {:?}", c.accepted);
            assert!(c.transients.is_empty(), "{:?}", c.transients);
            assert!(c.periodic.is_none(), "seed {seed}: {:?}", c.periodic);
        }
    }

    /// Without a spindle log the baseline is the offset alone (no column of zeros in any
    /// design), the statements say so, and a temperature still explains the readings.
    #[test]
    fn without_a_spindle_log_the_temperatures_are_tested() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.2).unwrap();
        let mut chiller = 20.0;
        let ev: Vec<Event> = recording(3, |_, _, _| 0.0)
            .into_iter()
            .filter_map(|e| match e {
                Event::Spindle { .. } => None,
                Event::Temperature {
                    ref sensor,
                    celsius,
                    ..
                } => {
                    if sensor == "chiller" {
                        chiller = celsius;
                    }
                    Some(e)
                }
                Event::Observation { t_ns, channel, .. } => Some(Event::Observation {
                    t_ns,
                    channel,
                    value: 2.0 * (chiller - 20.0) + noise.sample(&mut rng),
                    sigma: None,
                }),
            })
            .collect();
        let c = run(&ev);
        assert!(c.baseline_mode.is_none());
        assert!(
            c.accepted.iter().any(
                |t| matches!(&t.input, ModelInput::Temperature { sensor, .. } if sensor == "chiller")
            ),
            "{:?}",
            c.accepted
        );
        assert!(c.final_fit.rms_heldout_um < 0.5 * c.baseline.rms_heldout_um);
        assert!(
            c.statements
                .iter()
                .any(|s| s.contains("with the offset alone (no spindle log)")),
            "{:?}",
            c.statements
        );
    }

    /// A drift that starts late (tied to the room temperature after 25 h, nothing before)
    /// is not noise to the diagnosis: it is located in time and tied to that temperature.
    #[test]
    fn a_late_drift_is_located_and_tied_to_its_temperature() {
        let room = room_at;
        let c = run(&recording(5, |t, _, _| {
            if t > 1500.0 {
                8.0 * (room(t) - room(1500.0))
            } else {
                0.0
            }
        }));
        let u = c.unexplained.as_ref().unwrap();
        assert!(u.structured, "{u:?}");
        assert!((u.from_h - 25.0).abs() < 3.0, "{u:?}");
        assert!(u.to_h > 38.0, "{u:?}");
        assert_eq!(u.drivers[0].0, "room", "{u:?}");
        // The onset search: the drift starts near 25 h and follows the room temperature's
        // change since then, told apart from every other sensor and from a plain step or ramp.
        let o = u.onset.as_ref().unwrap();
        assert_eq!(o.sensor, "room", "{o:?}");
        assert!(o.tied, "{o:?}");
        assert!(
            o.earliest_h - 1.0 <= 25.0 && 25.0 <= o.latest_h + 1.0,
            "{o:?}"
        );
        assert!((o.gain_um_per_k - 8.0).abs() < 1.0, "{o:?}");
        assert!(
            c.statements
                .iter()
                .any(|s| s.contains("is not noise") && s.contains("room (r")),
            "{:?}",
            c.statements
        );
        // A clean recording leaves noise: nothing structured to report.
        let clean = run(&recording(5, |_, _, _| 0.0));
        assert!(!clean.unexplained.unwrap().structured);
    }

    #[test]
    fn a_chiller_cycle_is_located_named_and_modelled() {
        let c = run(&recording(7, |_, chiller, _| 1.5 * chiller));
        let p = c.periodic.as_ref().unwrap();
        assert!((p.period_min - 25.0).abs() < 1.0, "{p:?}");
        assert_eq!(p.driver.as_deref(), Some("chiller"));
        assert!(p.matched);
        let first = &c.accepted[0];
        assert!(
            matches!(&first.input, ModelInput::Temperature { sensor, .. } if sensor == "chiller"),
            "{first:?}"
        );
        assert!((first.value - 1.5).abs() < 0.1, "{first:?}");
        assert!(c.final_fit.rms_heldout_um < 0.5 * c.baseline.rms_heldout_um);
    }

    #[test]
    fn a_slow_mode_of_opposite_sign_makes_the_overshoot() {
        let c = run(&recording(11, |_, _, slow| -15.0 * slow));
        assert!(
            c.transients
                .iter()
                .any(|t| t.to_rpm == 0.0 && t.baseline_excursion_um < 0.3),
            "{:?}",
            c.transients
        );
        let opposite = c.accepted.iter().any(|t| {
            t.effect == "second_mode"
                && t.value.signum() != c.baseline_mode.as_ref().unwrap().gain_um.signum()
        });
        assert!(opposite, "{:?} {:?}", c.baseline_mode, c.accepted);
        assert!(c.final_fit.rms_heldout_um < 0.5 * c.baseline.rms_heldout_um);
    }
}
