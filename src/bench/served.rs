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
//! Before the model's first fit the service serves the last cycle, as it does.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use driftwatch_core::across_runs;
use driftwatch_core::families::{Family, Grid, grid, rms};
use driftwatch_core::thermal_model::{Event, Served, TemperatureInput, default_temperature_taus};
use driftwatch_core::units;
use driftwatch_machine::compensation::PredictionPolicy;
use driftwatch_machine::live_model::LiveModel;
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
    pub served_rmse: f64,
    pub last_cycle_rmse: f64,
    pub regression_rmse: f64,
    /// Scored points served by the model, the last measured value, no change, the
    /// regression, and the last cycle (before the first fit, or while the model is suspect).
    pub sources: [usize; 5],
    pub ratio_to_better: f64,
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
        .map(|r| driftwatch_core::thermal_model::sensors_of(&r.events))
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
    errors: [Vec<f64>; 3],
    sources: [usize; 5],
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
            sources: [0; 5],
            cycles: 0,
        });
        for ch in chans.iter_mut() {
            ch.last = None;
            ch.errors = Default::default();
            ch.sources = [0; 5];
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
                errors.insert(set.channels[m.channel].clone(), y);
                sigma.insert(set.channels[m.channel].clone(), CYCLE_SIGMA_UM);
                ch.record.push(g, m.k, ch.last.is_none());
                ch.fitted = ch.record.regression();
                ch.last = Some((m.k, y));
                ch.cycles += 1;
                i += 1;
            }
            if !errors.is_empty() {
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
                let name = &set.channels[m.channel];
                let p = predictions
                    .as_ref()
                    .and_then(|ps| ps.iter().find(|p| &p.channel == name));
                let served = match p {
                    Some(p) if model.suspect().is_none() => {
                        ch.sources[match p.source {
                            Served::Model => 0,
                            Served::LastMeasured => 1,
                            Served::NoChange => 2,
                            Served::Regression => 3,
                        }] += 1;
                        p.value
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
                for (e, v) in ch.errors.iter_mut().zip([served, held, regression]) {
                    e.push(v - g.y[m.k]);
                }
            }
        }
        for (c, ch) in chans.iter().enumerate() {
            if ch.errors[0].is_empty() {
                continue;
            }
            let [s, l, r] = [0, 1, 2].map(|j| rms(&ch.errors[j]));
            rows.push(ServedRow {
                set: set.name.clone(),
                run: run.name.clone(),
                channel: set.channels[c].clone(),
                cycles: ch.cycles,
                scored: ch.errors[0].len(),
                served_rmse: s,
                last_cycle_rmse: l,
                regression_rmse: r,
                sources: ch.sources,
                ratio_to_better: s / l.min(r),
            });
        }
    }
    rows
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
                "{:<10} {:<10} {:>6} {:>7} {:>8} {:>10} {:>10} {:>6}  served from (model/last/cold/regression/cycle)",
                "run", "channel", "cycles", "scored", "served", "last cycle", "regression", "ratio"
            );
            for r in &rows {
                println!(
                    "{:<10} {:<10} {:>6} {:>7} {:>8.2} {:>10.2} {:>10.2} {:>6.2}  {:?}",
                    r.run,
                    r.channel,
                    r.cycles,
                    r.scored,
                    r.served_rmse,
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
    let (ms, ml, mr) = (
        m(&|r| r.served_rmse),
        m(&|r| r.last_cycle_rmse),
        m(&|r| r.regression_rmse),
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
    let line = format!(
        "  {name}: {n} channel-runs; median RMSE served {ms:.2}, last cycle held {ml:.2}, least squares on the cycles so far {mr:.2}; served beats the last cycle in {beats_last} of {n}, least squares in {beats_reg}; {over} over 1.5x the better baseline"
    );
    (
        line,
        serde_json::json!({"set": name, "channel_runs": n, "median_served": ms,
            "median_last_cycle": ml, "median_regression": mr, "beats_last_cycle": beats_last,
            "beats_regression": beats_reg, "over_1_5": over}),
    )
}
