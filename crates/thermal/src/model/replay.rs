//! Causal replay: the events run through the model as the service would run them, each
//! prediction scored against the observations, and against a simulation's truth.

use std::collections::BTreeMap;

use serde::Serialize;

use super::events::Event;
use super::features::Features;
use super::fitted::ThermalModel;
use super::guard::{GuardSummary, Served};
use super::predictor::{Prediction, Predictor};

/// One step of a causal replay.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplayStep {
    pub t_ns: i64,
    pub predictions: Vec<Prediction>,
    /// Observations used in the step (since the previous one), by channel: their last value.
    pub measured: BTreeMap<String, f64>,
}

/// Predictions against the observations of a replay, each scored before it is used.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HoldoutScore {
    pub channel: String,
    pub n: usize,
    /// The model's prediction, the channel's unit.
    pub rmse_um: f64,
    /// Holding the last observation instead.
    pub persistence_rmse_um: f64,
    /// No change: the channel's cold value (the model's offset).
    pub no_change_rmse_um: f64,
    /// What was served (the model, or its fallback).
    pub served_rmse_um: f64,
    /// The served value in its served band (with the observation's own uncertainty): RMS
    /// of z, and the shares within 1 and 2 sigma.
    pub z_rms: f64,
    pub within_1_sigma: f64,
    pub within_2_sigma: f64,
}

#[derive(Default)]
struct ScoreSums {
    n: usize,
    model: f64,
    last: f64,
    cold: f64,
    served: f64,
    z2: f64,
    within_1: usize,
    within_2: usize,
}

/// Replay `events` through the model as the daemon would live: every `step_ns` from the first
/// event, each prediction from what came before it. Observations up to `update_until_ns`
/// correct the model (except those at or before the end of its fit data, which its posterior
/// already holds); every observation from `score_from_ns` on is scored before it is used.
/// Also returns what each channel serves at the end, and why.
pub fn replay(
    model: &ThermalModel,
    events: &[Event],
    step_ns: i64,
    update_until_ns: i64,
    score_from_ns: i64,
) -> (Vec<ReplayStep>, Vec<HoldoutScore>, Vec<GuardSummary>) {
    let (Some(first), Some(last)) = (events.first(), events.last()) else {
        return (Vec::new(), Vec::new(), Vec::new());
    };
    let step_ns = step_ns.max(1);
    let features = Features::new(&model.config, &model.t_ref_c, first.t_ns());
    let mut p = Predictor::resume(
        std::sync::Arc::new(model.clone()),
        features,
        model.to_ns.max(first.t_ns()),
    );
    let mut sums: BTreeMap<String, ScoreSums> = BTreeMap::new();
    let mut steps = Vec::new();
    let mut measured = BTreeMap::new();
    // The last reading taken of each channel. Within the fit's data the predictor starts from
    // its end, so its guard's last value is the fit's last reading: a later one. There the
    // last measured value is this one, so that nothing before the end of the fit is served
    // or scored with a reading from after it.
    let mut held: BTreeMap<String, f64> = BTreeMap::new();
    let in_fit = |t: i64, mut x: Vec<Prediction>, held: &BTreeMap<String, f64>| {
        if t <= model.to_ns {
            for pr in &mut x {
                if let (Served::LastMeasured, Some(v)) = (pr.source, held.get(&pr.channel)) {
                    pr.value = *v;
                }
            }
        }
        x
    };
    let mut k = 0;
    let mut t = first.t_ns();
    while t <= last.t_ns() {
        while k < events.len() && events[k].t_ns() <= t {
            let e = &events[k];
            k += 1;
            let Event::Observation {
                channel,
                value,
                sigma,
                ..
            } = e
            else {
                p.apply(e);
                continue;
            };
            if e.t_ns() >= score_from_ns {
                let pred = in_fit(e.t_ns(), p.predict(e.t_ns()), &held)
                    .into_iter()
                    .find(|x| &x.channel == channel);
                let prev = if e.t_ns() <= model.to_ns {
                    held.get(channel).copied()
                } else {
                    p.guard(channel).and_then(|g| g.last)
                };
                if let (Some(pr), Some(prev)) = (pred, prev) {
                    let s = sums.entry(channel.clone()).or_default();
                    let obs_var = sigma
                        .filter(|x| driftwatch_core::units::positive(*x))
                        .map_or(0.0, |x| x * x);
                    let z2 = (pr.value - value).powi(2) / (pr.sigma.powi(2) + obs_var).max(1e-24);
                    s.n += 1;
                    s.model += (pr.model_value - value).powi(2);
                    s.last += (prev - value).powi(2);
                    s.cold += (pr.no_change_value - value).powi(2);
                    s.served += (pr.value - value).powi(2);
                    s.z2 += z2;
                    s.within_1 += usize::from(z2 <= 1.0);
                    s.within_2 += usize::from(z2 <= 4.0);
                }
            }
            if e.t_ns() > update_until_ns || !value.is_finite() {
                continue;
            }
            if e.t_ns() <= model.to_ns {
                // In the fit's posterior already: taken once, not twice.
                p.features.apply(e);
                measured.insert(channel.clone(), *value);
                held.insert(channel.clone(), *value);
            } else if p.apply(e) {
                measured.insert(channel.clone(), *value);
                held.insert(channel.clone(), *value);
            }
        }
        steps.push(ReplayStep {
            t_ns: t,
            predictions: in_fit(t, p.predict(t), &held),
            measured: std::mem::take(&mut measured),
        });
        t += step_ns;
    }
    let scores = sums
        .into_iter()
        .map(|(channel, s)| {
            let n = s.n as f64;
            HoldoutScore {
                channel,
                n: s.n,
                rmse_um: (s.model / n).sqrt(),
                persistence_rmse_um: (s.last / n).sqrt(),
                no_change_rmse_um: (s.cold / n).sqrt(),
                served_rmse_um: (s.served / n).sqrt(),
                z_rms: (s.z2 / n).sqrt(),
                within_1_sigma: s.within_1 as f64 / n,
                within_2_sigma: s.within_2 as f64 / n,
            }
        })
        .collect();
    (steps, scores, p.guards())
}

/// One channel of a replay against the truth (a simulated recording's `/sim/truth`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TruthScore {
    pub channel: String,
    /// Truth samples compared.
    pub samples: usize,
    /// RMS of the truth less what the NC gets: no compensation (the truth of the reference
    /// sample), the last measured value held, the served value, the model's own value.
    pub none_rms: f64,
    pub last_measured_rms: f64,
    pub served_rms: f64,
    pub model_rms: f64,
}

impl TruthScore {
    /// The share of the thermal error (the uncompensated RMS) the served values remove.
    pub fn removed(&self) -> f64 {
        1.0 - self.served_rms / self.none_rms
    }
}

/// Truth samples: time and each channel's value.
pub type TruthSeries = [(i64, BTreeMap<String, f64>)];

/// Score a replay against the truth from `from_ns` on: at each truth sample, the latest step
/// at or before it. `reference` is what no compensation leaves in place (the truth at the
/// cold start); the last measured value is every observation of `events`, held.
pub fn truth_scores(
    steps: &[ReplayStep],
    events: &[Event],
    truth: &TruthSeries,
    reference: &BTreeMap<String, f64>,
    from_ns: i64,
) -> Vec<TruthScore> {
    let mut sums: BTreeMap<String, (usize, [f64; 4])> = BTreeMap::new();
    let mut last: BTreeMap<String, f64> = reference.clone();
    let (mut k_step, mut k_ev) = (0, 0);
    for (t, values) in truth {
        while k_ev < events.len() && events[k_ev].t_ns() <= *t {
            if let Event::Observation { channel, value, .. } = &events[k_ev]
                && value.is_finite()
            {
                last.insert(channel.clone(), *value);
            }
            k_ev += 1;
        }
        while k_step + 1 < steps.len() && steps[k_step + 1].t_ns <= *t {
            k_step += 1;
        }
        let Some(step) = steps.get(k_step).filter(|s| s.t_ns <= *t) else {
            continue;
        };
        if *t < from_ns {
            continue;
        }
        for pr in &step.predictions {
            let (Some(y), Some(r), Some(l)) = (
                values.get(&pr.channel),
                reference.get(&pr.channel),
                last.get(&pr.channel),
            ) else {
                continue;
            };
            let s = sums.entry(pr.channel.clone()).or_default();
            s.0 += 1;
            for (acc, served) in s.1.iter_mut().zip([*r, *l, pr.value, pr.model_value]) {
                *acc += (y - served).powi(2);
            }
        }
    }
    sums.into_iter()
        .map(|(channel, (n, s))| {
            let rms = |x: f64| (x / n as f64).sqrt();
            TruthScore {
                channel,
                samples: n,
                none_rms: rms(s[0]),
                last_measured_rms: rms(s[1]),
                served_rms: rms(s[2]),
                model_rms: rms(s[3]),
            }
        })
        .collect()
}
