//! `bench served`: the service's live model (the one machine loop keeps) replayed on
//! thermal-test data sets, as the service would run beside that machine: the runs one after
//! another, one a day; every input as it was logged; a validated cycle every
//! `--cycle-every-min` from each run's start (the channel's reading then, when the sensor
//! updated within a grid step of it); at every other updated reading, what the service
//! serves then is scored against it, next to what the same cycles give a textbook user:
//! - the last cycle held (what the NC keeps without a model),
//! - least squares on every input fitted on the cycles of every day so far (an offset per
//!   day: the inputs as changes since each day's first cycle), anchored at the last cycle.
//!
//! Before the model's first fit, while it is suspect (a cycle it predicted outside its band,
//! `LiveModel::judge`) and where its band is wider than the policy serves, the service keeps
//! the last set: here the last cycle. (The service also limits each step of a served value;
//! that is left out here.)

use std::collections::BTreeMap;
use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use driftwatch_core::error_name::ErrorName;
use driftwatch_core::units;
use driftwatch_machine::compensation::{
    CompensationSet, PredictionPolicy, Source, ValidationLimits,
};
use driftwatch_machine::live_model::LiveModel;
use driftwatch_thermal::across_runs;
use driftwatch_thermal::families::{Family, Grid, grid, rms};
use driftwatch_thermal::model::{
    Event, Served, TemperatureInput, beyond_chance, default_temperature_taus,
};
use serde::Serialize;

use crate::thermal_sets::{ThermalData, load_all};

/// Rest between one run's end and the next one's start (the machine off overnight).
const NIGHT_H: f64 = 12.0;
/// Stated uncertainty of a replayed cycle's reading, um.
const CYCLE_SIGMA_UM: f64 = 0.3;

#[derive(Debug, Clone, Serialize)]
pub struct ServedRow {
    pub set: String,
    pub run: String,
    pub channel: String,
    pub cycles: usize,
    pub scored: usize,
    /// What the service serves (the live model's value through the service's gates).
    pub served_rmse: f64,
    /// The live model's value (its guard's choice) wherever it has one, gates or not.
    pub model_rmse: f64,
    pub last_cycle_rmse: f64,
    pub regression_rmse: f64,
    /// Scored points served by the model, the last measured value, no change, the
    /// regression; and the last cycle kept: before the first fit or while the model is
    /// suspect, and where the band was wider than the policy serves.
    pub sources: [usize; 6],
    pub ratio_to_better: f64,
    /// The served value against the better baseline of the channel-run (the one with the
    /// smaller RMSE): the one-sided paired test of the service's fallbacks on the mean
    /// difference of squared errors of each gap between cycles (one value per gap: within
    /// a gap the errors share their anchor and are far from independent), judged from
    /// `min_scored` gaps on as the service judges. The statistic when served was worse
    /// beyond chance, and the gaps it had.
    pub worse_beyond_chance: Option<f64>,
    pub gaps: usize,
}

/// One scored point or one cycle of a channel, in time order.
struct Moment {
    t_ns: i64,
    cycle: bool,
    channel: usize,
    k: usize,
}

/// The cycles and the scored points of a run's channels: a cycle at every `cycle_ns` from the
/// run's start (the first fresh reading within a grid step), every other fresh reading scored
/// once the run has had its first cycle.
fn moments(grids: &[Option<Grid>], t0: i64, t1: i64, cycle_ns: i64, step_ns: i64) -> Vec<Moment> {
    let mut out = Vec::new();
    for (c, g) in grids.iter().enumerate() {
        let Some(g) = g else { continue };
        let mut cycles = Vec::new();
        let mut t = t0;
        while t <= t1 {
            let k = g.index_at(t);
            if let Some(k) = (k..g.len())
                .take_while(|&k| g.t_ns[k] <= t + step_ns)
                .find(|&k| g.fresh[k])
            {
                cycles.push(k);
            }
            t += cycle_ns;
        }
        cycles.dedup();
        let Some(&first) = cycles.first() else {
            continue;
        };
        for k in first..g.len() {
            let cycle = cycles.contains(&k);
            if cycle || g.fresh[k] {
                out.push(Moment {
                    t_ns: g.t_ns[k],
                    cycle,
                    channel: c,
                    k,
                });
            }
        }
    }
    // Cycles before scores at the same time: a cycle's result is known when it is served.
    out.sort_by_key(|m| (m.t_ns, !m.cycle));
    out
}

/// The live model's policy for a set: the service's, with every temperature of the set an
/// input with the default lags and the spindle's reference speed the fastest the set ran.
fn policy_for(set: &ThermalData, mut policy: PredictionPolicy) -> PredictionPolicy {
    let sensors = set
        .runs
        .first()
        .map(|r| driftwatch_thermal::model::sensors_of(&r.events))
        .unwrap_or_default();
    policy.model.temperatures = sensors
        .into_iter()
        .map(|sensor| TemperatureInput {
            sensor,
            taus_min: default_temperature_taus(),
        })
        .collect();
    let top = set
        .runs
        .iter()
        .flat_map(|r| &r.events)
        .filter_map(|e| match e {
            Event::Spindle { rpm, .. } => Some(rpm.abs()),
            _ => None,
        })
        .fold(0.0, f64::max);
    if top > 0.0 {
        policy.model.n_ref_rpm = top;
    }
    policy
}

/// What each channel's cycles taught a textbook user: a grid of the cycles of each day.
#[derive(Default)]
struct CycleRecord {
    days: Vec<Grid>,
}

impl CycleRecord {
    fn push(&mut self, g: &Grid, k: usize, new_day: bool) {
        if new_day || self.days.is_empty() {
            self.days.push(Grid {
                channel: g.channel.clone(),
                t_ns: Vec::new(),
                y: Vec::new(),
                names: g.names.clone(),
                inputs: vec![Vec::new(); g.names.len()],
                fresh: Vec::new(),
            });
        }
        if let Some(d) = self.days.last_mut() {
            d.t_ns.push(g.t_ns[k]);
            d.y.push(g.y[k]);
            d.fresh.push(true);
            for (j, col) in d.inputs.iter_mut().enumerate() {
                col.push(g.inputs[j][k]);
            }
        }
    }

    /// Least squares with an offset per day on every cycle so far (`None` until it has more
    /// cycles than inputs).
    fn regression(&self) -> Option<across_runs::RunsFitted> {
        let days: Vec<&Grid> = self
            .days
            .iter()
            .filter(|d| d.names == self.days[0].names)
            .collect();
        let all: Vec<usize> = (0..days.first()?.names.len()).collect();
        across_runs::fit(Family::Regression, &days, &all)
    }
}

struct Channel {
    record: CycleRecord,
    fitted: Option<across_runs::RunsFitted>,
    /// The last cycle: its grid index in the current run and value.
    last: Option<(usize, f64)>,
    errors: [Vec<f64>; 4],
    /// The gap between cycles each scored point lies in (the cycles before it).
    gap: Vec<usize>,
    sources: [usize; 6],
    cycles: usize,
}

/// Replay every run of `set` through one live model.
fn replay(
    set: &ThermalData,
    policy: &PredictionPolicy,
    step_ns: i64,
    cycle_ns: i64,
) -> Vec<ServedRow> {
    let mut model = LiveModel::new(policy_for(set, policy.clone()));
    let names = stand_ins(&set.channels);
    let mut rows = Vec::new();
    let mut chans: Vec<Channel> = Vec::new();
    let mut start = 0i64;
    for run in &set.runs {
        let ev = &run.events;
        let (Some(t0), Some(t1)) = (ev.first().map(Event::t_ns), ev.last().map(Event::t_ns)) else {
            continue;
        };
        let shift = start - t0;
        start += t1 - t0 + units::h_to_ns(NIGHT_H);
        let grids: Vec<Option<Grid>> = set.channels.iter().map(|c| grid(ev, c, step_ns)).collect();
        chans.resize_with(set.channels.len(), || Channel {
            record: CycleRecord::default(),
            fitted: None,
            last: None,
            errors: Default::default(),
            gap: Vec::new(),
            sources: [0; 6],
            cycles: 0,
        });
        for ch in chans.iter_mut() {
            ch.last = None;
            ch.errors = Default::default();
            ch.gap.clear();
            ch.sources = [0; 6];
            ch.cycles = 0;
        }
        let mut inputs = ev
            .iter()
            .filter(|e| !matches!(e, Event::Observation { .. }))
            .peekable();
        let mut feed = |model: &mut LiveModel, until: i64| {
            while let Some(e) = inputs.next_if(|e| e.t_ns() <= until) {
                model.input(shifted(e, shift));
            }
        };
        let ms = moments(&grids, t0, t1, cycle_ns, step_ns);
        let mut i = 0;
        while i < ms.len() {
            let t = ms[i].t_ns;
            feed(&mut model, t);
            // Every cycle at this time, one validated cycle of the channels it read.
            let (mut errors, mut sigma) = (BTreeMap::new(), BTreeMap::new());
            while i < ms.len() && ms[i].t_ns == t && ms[i].cycle {
                let m = &ms[i];
                let (Some(g), ch) = (&grids[m.channel], &mut chans[m.channel]) else {
                    i += 1;
                    continue;
                };
                let y = g.y[m.k];
                errors.insert(names[m.channel].clone(), y);
                sigma.insert(names[m.channel].clone(), CYCLE_SIGMA_UM);
                ch.record.push(g, m.k, ch.last.is_none());
                ch.fitted = ch.record.regression();
                ch.last = Some((m.k, y));
                ch.cycles += 1;
                i += 1;
            }
            if !errors.is_empty() {
                // As the machine loop does: judged before it learns from the cycle.
                if let Some(set) = measured_set(&errors, t + shift) {
                    model.judge(&set, t + shift, t + shift, &ValidationLimits::default());
                }
                model.observe(t + shift, &errors, &sigma);
            }
            let predictions = if i < ms.len() && ms[i].t_ns == t {
                model.predict(t + shift)
            } else {
                None
            };
            while i < ms.len() && ms[i].t_ns == t {
                let m = &ms[i];
                i += 1;
                let (Some(g), ch) = (&grids[m.channel], &mut chans[m.channel]) else {
                    continue;
                };
                let Some((c, held)) = ch.last else { continue };
                let name = &names[m.channel];
                let p = predictions
                    .as_ref()
                    .and_then(|ps| ps.iter().find(|p| &p.channel == name));
                // The service's gates: a suspect model, or a band wider than the policy
                // serves, leaves the last set in place.
                let served = match p {
                    Some(p) if model.suspect().is_none() && p.sigma <= policy.max_sigma_um => {
                        ch.sources[match p.source {
                            Served::Model => 0,
                            Served::LastMeasured => 1,
                            Served::NoChange => 2,
                            Served::Regression => 3,
                        }] += 1;
                        p.value
                    }
                    Some(_) if model.suspect().is_none() => {
                        ch.sources[5] += 1;
                        held
                    }
                    _ => {
                        ch.sources[4] += 1;
                        held
                    }
                };
                let same = ch.record.days.first().is_some_and(|d| d.names == g.names);
                let regression = ch.fitted.as_ref().filter(|_| same).map_or(held, |f| {
                    held + f
                        .inputs
                        .iter()
                        .zip(&f.coef)
                        .map(|(&j, b)| b * (g.inputs[j][m.k] - g.inputs[j][c]))
                        .sum::<f64>()
                });
                let model_value = p.map_or(held, |p| p.value);
                for (e, v) in ch
                    .errors
                    .iter_mut()
                    .zip([served, held, regression, model_value])
                {
                    e.push(v - g.y[m.k]);
                }
                ch.gap.push(ch.cycles);
            }
        }
        for (c, ch) in chans.iter().enumerate() {
            if !ch.errors[0].is_empty() {
                let at = (
                    set.name.as_str(),
                    run.name.as_str(),
                    set.channels[c].as_str(),
                );
                rows.push(row_of(at, ch, policy.model.min_scored));
            }
        }
    }
    rows
}

/// A channel-run's row from what its replay scored (`at`: set, run, channel).
fn row_of((set, run, channel): (&str, &str, &str), ch: &Channel, min_scored: usize) -> ServedRow {
    let [s, l, r, mv] = [0, 1, 2, 3].map(|j| rms(&ch.errors[j]));
    let better = if l <= r { 1 } else { 2 };
    let (gaps, worse) = worse_by_gap(&ch.errors[0], &ch.errors[better], &ch.gap);
    ServedRow {
        set: set.to_string(),
        run: run.to_string(),
        channel: channel.to_string(),
        cycles: ch.cycles,
        scored: ch.errors[0].len(),
        served_rmse: s,
        model_rmse: mv,
        last_cycle_rmse: l,
        regression_rmse: r,
        sources: ch.sources,
        ratio_to_better: s / l.min(r),
        // As the service: no verdict on fewer gaps than it needs to judge a fallback.
        worse_beyond_chance: worse.filter(|_| gaps >= min_scored),
        gaps,
    }
}

/// Whether the errors `served` are worse than `base`'s beyond chance: the paired differences
/// of squared errors averaged over each gap (`gap`, non-decreasing), tested one-sided as the
/// service's fallbacks are ([`beyond_chance`]). The gaps, and the statistic when worse.
fn worse_by_gap(served: &[f64], base: &[f64], gap: &[usize]) -> (usize, Option<f64>) {
    let mut means = Vec::new();
    let mut i = 0;
    while i < gap.len() {
        let j = i + gap[i..].partition_point(|&g| g == gap[i]);
        let d = (i..j).map(|k| served[k].powi(2) - base[k].powi(2));
        means.push(d.sum::<f64>() / (j - i) as f64);
        i = j;
    }
    let (sum, sum2) = means
        .iter()
        .fold((0.0, 0.0), |(a, b), d| (a + d, b + d * d));
    (means.len(), beyond_chance(means.len(), sum, sum2))
}

/// The model's name of each channel: a position error's (`EX0A`, `EY0A`, ... `EZ0D`), so that
/// the service's own check of a prediction against each cycle (`LiveModel::judge`, in um
/// and um/min) applies; past twelve channels, the channel's own name (not checked).
fn stand_ins(channels: &[String]) -> Vec<String> {
    let errors = ['A', 'B', 'C', 'D']
        .into_iter()
        .flat_map(|axis| ['X', 'Y', 'Z'].map(|d| format!("E{d}0{axis}")));
    channels
        .iter()
        .zip(errors.map(Some).chain(std::iter::repeat(None)))
        .map(|(c, e)| e.unwrap_or_else(|| c.clone()))
        .collect()
}

/// A cycle's readings as the measured set the service would judge its model by (`None`
/// when no channel has a stand-in error name).
fn measured_set(errors: &BTreeMap<String, f64>, t_ns: i64) -> Option<CompensationSet> {
    let named: BTreeMap<ErrorName, f64> = errors
        .iter()
        .filter_map(|(k, v)| ErrorName::parse(k).ok().map(|e| (e, *v)))
        .collect();
    (!named.is_empty()).then(|| CompensationSet {
        version: 0,
        valid_from_ns: t_ns,
        source: Source::Measured,
        cycle: None,
        sigma: named.keys().map(|e| (*e, CYCLE_SIGMA_UM)).collect(),
        errors: named,
        offsets: BTreeMap::new(),
        reason: String::new(),
    })
}

fn shifted(e: &Event, shift: i64) -> Event {
    let mut e = e.clone();
    match &mut e {
        Event::Spindle { t_ns, .. }
        | Event::Temperature { t_ns, .. }
        | Event::Observation { t_ns, .. } => *t_ns += shift,
    }
    e
}

/// `bench served`.
pub fn served(
    data: &Path,
    policy: PredictionPolicy,
    step_min: Option<f64>,
    cycle_every_min: f64,
    json: bool,
) -> Result<ExitCode> {
    anyhow::ensure!(
        cycle_every_min > 0.0,
        "--cycle-every-min must be positive, got {cycle_every_min}"
    );
    let sets = load_all(data)?;
    let mut all = Vec::new();
    let mut summary = Vec::new();
    for set in &sets {
        let step_ns = super::thermal::step_ns_of(set, step_min);
        let rows = replay(set, &policy, step_ns, units::min_to_ns(cycle_every_min));
        if !json {
            println!(
                "\n{} ({} runs, one a day; {}; a cycle every {cycle_every_min} min; RMSE um on the updated readings between cycles)",
                set.name,
                set.runs.len(),
                set.inputs
            );
            println!(
                "{:<10} {:<10} {:>6} {:>7} {:>8} {:>8} {:>10} {:>10} {:>6}  served from (model/last/cold/regression; last cycle kept: no model or suspect/wide band)",
                "run",
                "channel",
                "cycles",
                "scored",
                "served",
                "model",
                "last cycle",
                "regression",
                "ratio"
            );
            for r in &rows {
                println!(
                    "{:<10} {:<10} {:>6} {:>7} {:>8.2} {:>8.2} {:>10.2} {:>10.2} {:>6.2}  {:?}",
                    r.run,
                    r.channel,
                    r.cycles,
                    r.scored,
                    r.served_rmse,
                    r.model_rmse,
                    r.last_cycle_rmse,
                    r.regression_rmse,
                    r.ratio_to_better,
                    r.sources
                );
            }
        }
        if !rows.is_empty() {
            let (line, value) = summarise(&set.name, &rows);
            if !json {
                println!("{line}");
            }
            summary.push(value);
        }
        all.extend(rows);
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({"rows": all, "summary": summary}))?
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn summarise(name: &str, rows: &[ServedRow]) -> (String, serde_json::Value) {
    let n = rows.len();
    let m = |f: &dyn Fn(&ServedRow) -> f64| super::thermal::median(rows.iter().map(f));
    let (ms, ml, mr, mm) = (
        m(&|r| r.served_rmse),
        m(&|r| r.last_cycle_rmse),
        m(&|r| r.regression_rmse),
        m(&|r| r.model_rmse),
    );
    let beats_last = rows
        .iter()
        .filter(|r| r.served_rmse < r.last_cycle_rmse)
        .count();
    let beats_reg = rows
        .iter()
        .filter(|r| r.served_rmse < r.regression_rmse)
        .count();
    let over = rows.iter().filter(|r| r.ratio_to_better > 1.5).count();
    let worse = rows
        .iter()
        .filter(|r| r.worse_beyond_chance.is_some())
        .count();
    let line = format!(
        "  {name}: {n} channel-runs; median RMSE served {ms:.2} (the live model's value, gates or not, {mm:.2}), last cycle held {ml:.2}, least squares on the cycles so far {mr:.2}; served beats the last cycle in {beats_last} of {n}, least squares in {beats_reg}; {over} over 1.5x the better baseline; worse than the better baseline beyond chance (paired over the gaps between cycles) in {worse}"
    );
    (
        line,
        serde_json::json!({"set": name, "channel_runs": n, "median_served": ms, "median_model": mm,
            "median_last_cycle": ml, "median_regression": mr, "beats_last_cycle": beats_last,
            "beats_regression": beats_reg, "over_1_5": over, "worse_beyond_chance": worse}),
    )
}

#[cfg(test)]
mod tests {
    use super::worse_by_gap;

    /// One value per gap: a series worse in every gap is worse beyond chance however many
    /// points each gap has; the same series against itself, or against a worse one, is not.
    #[test]
    fn served_is_judged_worse_by_the_gaps_between_cycles() {
        let gap: Vec<usize> = (0..40).map(|i| i / 4).collect();
        let base: Vec<f64> = (0..40).map(|i| (i % 3) as f64 - 1.0).collect();
        let worse: Vec<f64> = base
            .iter()
            .enumerate()
            .map(|(i, b)| b + 1.0 + 0.1 * (i % 4) as f64)
            .collect();
        let (gaps, t) = worse_by_gap(&worse, &base, &gap);
        assert_eq!(gaps, 10);
        assert!(t.is_some_and(|t| t > 1.645), "{t:?}");
        assert_eq!(worse_by_gap(&base, &base, &gap).1, None);
        assert_eq!(worse_by_gap(&base, &worse, &gap).1, None);
        // A single gap is no evidence either way.
        assert_eq!(worse_by_gap(&worse[..4], &base[..4], &gap[..4]), (1, None));
    }
}
