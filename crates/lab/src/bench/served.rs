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
//!
//! With `--schedules` the service's scheduler orders the cycles instead (its phases from the
//! set's spindle, its look at the model before every reading), with the tool-tip rule and
//! without it, each next to the fixed cadence that takes as many cycles.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use driftwatch_core::error_name::ErrorName;
use driftwatch_core::recording::MachineStateKind;
use driftwatch_core::units;
use driftwatch_machine::compensation::{
    CompensationSet, PredictionPolicy, Source, ValidationLimits,
};
use driftwatch_machine::live_model::LiveModel;
use driftwatch_machine::phase::{PhaseConfig, PhaseInfo, PhaseTracker};
use driftwatch_machine::scheduler::{Decision, Reason, SchedulePolicy, SchedulerState, decide};
use driftwatch_thermal::across_runs;
use driftwatch_thermal::families::{Family, Grid, grid, rms};
use driftwatch_thermal::model::{
    Event, Prediction, Served, TemperatureInput, beyond_chance, default_temperature_taus,
};
use serde::Serialize;

use crate::thermal_sets::{Run, ThermalData, load_all};

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
    /// The served value's largest error.
    pub served_max: f64,
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

#[derive(Default)]
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

/// When a replay takes its cycles.
#[derive(Debug, Clone)]
pub enum Cycles {
    /// A cycle every this many ns from each run's start.
    Every(i64),
    /// When the service's scheduler orders one: its phases from the set's spindle, its look
    /// at the live model before every reading. The machine counts as idle whenever a reading
    /// comes (the bench measures at any moment, as the fixed cadence does; a plant's cycles
    /// wait for a stop).
    Schedule(SchedulePolicy, PhaseConfig),
}

/// What one replay of a set gave.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Replayed {
    pub rows: Vec<ServedRow>,
    /// The cycles taken (one cycle reads every channel that updates within a grid step of
    /// its start), and how many of them each scheduler rule ordered.
    pub cycles: usize,
    pub reasons: BTreeMap<&'static str, usize>,
    pub runs: usize,
    /// When each cycle started, h on the replay's clock (the runs one a day), and why (the
    /// scheduler's reason; none on a fixed cadence).
    pub starts: Vec<(f64, Option<&'static str>)>,
}

/// The rule a scheduled cycle started for, as a key.
fn reason_key(r: &Reason) -> &'static str {
    match r {
        Reason::WarmUp => "warm_up",
        Reason::AfterStop { .. } => "after_stop",
        Reason::Steady => "steady",
        Reason::Stale => "stale",
        Reason::Uncertain { .. } => "uncertain_error",
        Reason::TipUncertain { .. } => "tip",
        Reason::Operator { .. } => "operator",
        Reason::Retry => "retry",
        Reason::NotIdle(_) | Reason::TooSoon | Reason::NothingDue | Reason::CycleOpen { .. } => {
            "other"
        }
    }
}

/// One run laid out for a replay: its span and grids, and every updated reading of every
/// channel in time order (channel order within a time): (time, channel, grid index).
struct RunLayout<'a> {
    run: &'a Run,
    t0: i64,
    t1: i64,
    grids: Vec<Option<Grid>>,
    readings: Vec<(i64, usize, usize)>,
}

fn lay_out<'a>(set: &'a ThermalData, step_ns: i64) -> Vec<RunLayout<'a>> {
    set.runs
        .iter()
        .filter_map(|run| {
            let ev = &run.events;
            let (t0, t1) = (ev.first()?.t_ns(), ev.last()?.t_ns());
            let grids: Vec<Option<Grid>> =
                set.channels.iter().map(|c| grid(ev, c, step_ns)).collect();
            let mut readings: Vec<(i64, usize, usize)> = grids
                .iter()
                .enumerate()
                .filter_map(|(c, g)| g.as_ref().map(|g| (c, g)))
                .flat_map(|(c, g)| {
                    (0..g.len())
                        .filter(|&k| g.fresh[k])
                        .map(move |k| (g.t_ns[k], c, k))
                })
                .collect();
            readings.sort_by_key(|r| r.0);
            Some(RunLayout {
                run,
                t0,
                t1,
                grids,
                readings,
            })
        })
        .collect()
}

/// The cycles the channels wait for. A cycle started at `from` reads each channel's first
/// update up to `from + step_ns` (a later start takes the channels over); it is taken when it
/// reads at least one.
struct Windows {
    open: Vec<Option<(i64, usize)>>,
    step_ns: i64,
    opened: usize,
    taken: std::collections::BTreeSet<usize>,
    /// Each start: its cycle, its time on the replay's clock and the scheduler's rule.
    starts: Vec<(usize, i64, Option<&'static str>)>,
}

impl Windows {
    fn new(channels: usize, step_ns: i64) -> Self {
        Windows {
            open: vec![None; channels],
            step_ns,
            opened: 0,
            taken: Default::default(),
            starts: Vec::new(),
        }
    }

    fn start(&mut self, from: i64, clock_ns: i64, why: Option<&'static str>) -> usize {
        self.opened += 1;
        let w = Some((from + self.step_ns, self.opened));
        self.open.iter_mut().for_each(|o| *o = w);
        self.starts.push((self.opened, clock_ns, why));
        self.opened
    }

    /// A fixed cadence's starts up to `t`: every `every_ns` from `*next` on.
    fn planned(&mut self, next: &mut i64, every_ns: i64, t: i64, shift: i64) {
        while *next <= t {
            self.start(*next, *next + shift, None);
            *next += every_ns.max(1);
        }
    }

    /// Whether channel `c`'s reading at `t` is a cycle's (then the channel waits no more).
    fn take(&mut self, c: usize, t: i64) -> bool {
        match self.open[c] {
            Some((until, cycle)) if t <= until => {
                self.open[c] = None;
                self.taken.insert(cycle);
                true
            }
            _ => false,
        }
    }

    /// Each taken cycle's start, h on the replay's clock, and its rule.
    fn taken_starts(&self) -> Vec<(f64, Option<&'static str>)> {
        self.starts
            .iter()
            .filter(|(c, ..)| self.taken.contains(c))
            .map(|&(_, t, why)| (t as f64 / units::NS_PER_H as f64, why))
            .collect()
    }
}

/// The runs one a day: each run's shift onto the replay's clock.
fn shifts(layout: &[RunLayout]) -> Vec<i64> {
    let mut start = 0i64;
    layout
        .iter()
        .map(|r| {
            let shift = start - r.t0;
            start += r.t1 - r.t0 + units::h_to_ns(NIGHT_H);
            shift
        })
        .collect()
}

/// The cycles a fixed cadence of `every_ns` takes over the runs (no model needed).
fn fixed_count(layout: &[RunLayout], channels: usize, step_ns: i64, every_ns: i64) -> usize {
    let mut w = Windows::new(channels, step_ns);
    for (r, shift) in layout.iter().zip(shifts(layout)) {
        w.open.iter_mut().for_each(|o| *o = None);
        let mut next = r.t0;
        for &(t, c, _) in &r.readings {
            w.planned(&mut next, every_ns, t, shift);
            w.take(c, t);
        }
    }
    w.taken.len()
}

/// The longest whole-minute cadence that takes at least `n` cycles over the runs (a cycle
/// planned at each run's start, then every so many minutes; one that reads no channel is
/// not taken).
fn as_many(layout: &[RunLayout], channels: usize, step_ns: i64, n: usize) -> f64 {
    let count = |min: i64| fixed_count(layout, channels, step_ns, units::min_to_ns(min as f64));
    let longest = layout
        .iter()
        .map(|r| (r.t1 - r.t0) / units::min_to_ns(1.0) + 1)
        .max()
        .unwrap_or(1);
    // The count falls as the cadence grows, not always strictly where readings are
    // missing: search down from the longest that plans as many.
    let planned = |min: i64| -> usize {
        let every = units::min_to_ns(min as f64);
        layout
            .iter()
            .map(|r| ((r.t1 - r.t0) / every) as usize + 1)
            .sum()
    };
    let (mut lo, mut hi) = (1i64, longest.max(1));
    while lo < hi {
        let mid = (lo + hi + 1) / 2;
        if planned(mid) >= n {
            lo = mid
        } else {
            hi = mid - 1
        }
    }
    while lo > 1 && count(lo) < n {
        lo -= 1;
    }
    lo as f64
}

/// The live model, the scheduler and the channels of one replay.
struct Replay<'a> {
    policy: &'a PredictionPolicy,
    model: LiveModel,
    names: Vec<String>,
    sens: BTreeMap<String, [f64; 3]>,
    sched: SchedulerState,
    phase: Option<PhaseTracker>,
    chans: Vec<Channel>,
    windows: Windows,
    reasons: BTreeMap<&'static str, usize>,
}

/// Replay every run of `set` through one live model, the cycles taken as `cycles` says: at
/// each reading time, first any cycle that starts then (the scheduler looks at the model
/// before it), then the cycles' readings (judged, then learnt from), then every other
/// updated reading scored against what is served then.
fn replay(
    set: &ThermalData,
    layout: &[RunLayout],
    policy: &PredictionPolicy,
    step_ns: i64,
    cycles: &Cycles,
) -> Result<Replayed> {
    let names = stand_ins(&set.channels);
    let mut rp = Replay {
        policy,
        model: LiveModel::new(policy_for(set, policy.clone())),
        // The channels' own directions are unknown: the "tool tip" of a set is the root sum
        // of squares of its channels' bands.
        sens: names.iter().map(|n| (n.clone(), [1.0, 0.0, 0.0])).collect(),
        names,
        sched: SchedulerState::default(),
        phase: match cycles {
            Cycles::Schedule(_, cfg) => Some(PhaseTracker::new(cfg.clone())?),
            Cycles::Every(_) => None,
        },
        chans: (0..set.channels.len())
            .map(|_| Channel::default())
            .collect(),
        windows: Windows::new(set.channels.len(), step_ns),
        reasons: BTreeMap::new(),
    };
    let mut rows = Vec::new();
    for (r, shift) in layout.iter().zip(shifts(layout)) {
        rp.run(r, shift, cycles)?;
        for (c, ch) in rp.chans.iter().enumerate() {
            if !ch.errors[0].is_empty() {
                let at = (
                    set.name.as_str(),
                    r.run.name.as_str(),
                    set.channels[c].as_str(),
                );
                rows.push(row_of(at, ch, policy.model.min_scored));
            }
        }
    }
    Ok(Replayed {
        rows,
        cycles: rp.windows.taken.len(),
        reasons: rp.reasons,
        runs: layout.len(),
        starts: rp.windows.taken_starts(),
    })
}

impl Replay<'_> {
    /// One run, `shift` onto the replay's clock.
    fn run(&mut self, r: &RunLayout, shift: i64, cycles: &Cycles) -> Result<()> {
        for ch in self.chans.iter_mut() {
            *ch = Channel {
                record: std::mem::take(&mut ch.record),
                fitted: ch.fitted.take(),
                ..Channel::default()
            };
        }
        self.windows.open.iter_mut().for_each(|o| *o = None);
        let mut inputs = r
            .run
            .events
            .iter()
            .filter(|e| !matches!(e, Event::Observation { .. }))
            .peekable();
        let mut planned = r.t0;
        let mut i = 0;
        while i < r.readings.len() {
            let t = r.readings[i].0;
            let j = i + r.readings[i..].partition_point(|x| x.0 == t);
            while let Some(e) = inputs.next_if(|e| e.t_ns() <= t) {
                let e = shifted(e, shift);
                if let (Some(ph), Event::Spindle { t_ns, rpm }) = (self.phase.as_mut(), &e) {
                    ph.on_spindle(*t_ns, *rpm)?;
                }
                self.model.input(e);
            }
            match cycles {
                Cycles::Every(every) => self.windows.planned(&mut planned, *every, t, shift),
                Cycles::Schedule(p, _) => self.ask(p, t, shift),
            }
            self.at(r, &r.readings[i..j], t + shift);
            i = j;
        }
        Ok(())
    }

    /// The scheduler's look at the model at `t` (the run's clock), and the cycle it starts.
    fn ask(&mut self, policy: &SchedulePolicy, t: i64, shift: i64) {
        let Some(ph) = &self.phase else { return };
        let now = t + shift;
        let predictions = self.model.predict(now);
        self.model
            .look(&mut self.sched, predictions.as_deref(), &self.sens, now);
        let info = PhaseInfo {
            state: MachineStateKind::Idle,
            cutting: false,
            ..ph.phase(now)
        };
        if let Decision::Start { reason } = decide(policy, &info, &self.sched, now) {
            let why = reason_key(&reason);
            let id = self.windows.start(t, now, Some(why));
            self.sched.started(id as i64, now);
            self.sched.finished(true, now);
            *self.reasons.entry(why).or_default() += 1;
        }
    }

    /// The readings of one time (`now` on the replay's clock): the cycles' first, one
    /// validated cycle of the channels they read, then the others scored.
    fn at(&mut self, r: &RunLayout, readings: &[(i64, usize, usize)], now: i64) {
        let mut cycle = vec![false; readings.len()];
        let (mut errors, mut sigma) = (BTreeMap::new(), BTreeMap::new());
        for (is, &(t, c, k)) in cycle.iter_mut().zip(readings) {
            let Some(g) = &r.grids[c] else { continue };
            if !self.windows.take(c, t) {
                continue;
            }
            *is = true;
            let ch = &mut self.chans[c];
            let y = g.y[k];
            errors.insert(self.names[c].clone(), y);
            sigma.insert(self.names[c].clone(), CYCLE_SIGMA_UM);
            ch.record.push(g, k, ch.last.is_none());
            ch.fitted = ch.record.regression();
            ch.last = Some((k, y));
            ch.cycles += 1;
        }
        if !errors.is_empty() {
            // As the machine loop does: judged before it learns from the cycle.
            if let Some(set) = measured_set(&errors, now) {
                self.model
                    .judge(&set, now, now, &ValidationLimits::default());
            }
            self.model.observe(now, &errors, &sigma);
        }
        // Only where a reading is scored (a channel with a cycle behind it): a prediction
        // moves the model's filters on.
        let scored: Vec<(usize, usize)> = cycle
            .iter()
            .zip(readings)
            .filter(|&(is, &(_, c, _))| !*is && self.chans[c].last.is_some())
            .map(|(_, &(_, c, k))| (c, k))
            .collect();
        if scored.is_empty() {
            return;
        }
        let predictions = self.model.predict(now);
        for (c, k) in scored {
            let Some(g) = &r.grids[c] else { continue };
            score(
                &mut self.chans[c],
                g,
                k,
                &self.names[c],
                predictions.as_deref(),
                &self.model,
                self.policy,
            );
        }
    }
}

/// Score channel `ch`'s reading `k` of grid `g` (stand-in `name`): what the service serves
/// then (`predictions`, through its gates), the last cycle held, least squares on the cycles
/// so far and the model's own value, each against the reading. Nothing before its first cycle.
fn score(
    ch: &mut Channel,
    g: &Grid,
    k: usize,
    name: &str,
    predictions: Option<&[Prediction]>,
    model: &LiveModel,
    policy: &PredictionPolicy,
) {
    let Some((c, held)) = ch.last else { return };
    let p = predictions.and_then(|ps| ps.iter().find(|p| p.channel == name));
    // The service's gates: a suspect model, or a band wider than the policy serves, leaves
    // the last set in place.
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
            .map(|(&j, b)| b * (g.inputs[j][k] - g.inputs[j][c]))
            .sum::<f64>()
    });
    let model_value = p.map_or(held, |p| p.value);
    for (e, v) in ch
        .errors
        .iter_mut()
        .zip([served, held, regression, model_value])
    {
        e.push(v - g.y[k]);
    }
    ch.gap.push(ch.cycles);
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
        served_max: ch.errors[0].iter().fold(0.0, |m, e| m.max(e.abs())),
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

/// The schedules `bench served --schedules` compares: the service's policy with its tool-tip
/// rule on (`policy.tip_sigma_um` > 0) and with the rule off (the minute offsets), each
/// against a fixed cadence with as many cycles.
pub struct Schedules {
    pub policy: SchedulePolicy,
    pub phase: PhaseConfig,
}

/// `bench served`: a cycle every `cycle_every_min`, or with `schedules` the service's
/// schedules against fixed cadences.
pub fn served(
    data: &Path,
    policy: PredictionPolicy,
    step_min: Option<f64>,
    cycle_every_min: f64,
    schedules: Option<Schedules>,
    json: bool,
) -> Result<ExitCode> {
    anyhow::ensure!(
        cycle_every_min > 0.0,
        "--cycle-every-min must be positive, got {cycle_every_min}"
    );
    if let Some(s) = &schedules {
        s.policy.validate()?;
        s.phase.validate()?;
        anyhow::ensure!(
            s.policy.tip_sigma_um > 0.0,
            "the schedules compared need the tool-tip rule on (--tip-sigma > 0)"
        );
    }
    let sets = load_all(data)?;
    let mut all = Vec::new();
    let mut summary = Vec::new();
    for set in &sets {
        let step_ns = super::thermal::step_ns_of(set, step_min);
        if let Some(s) = &schedules {
            let lines = compare_schedules(set, &policy, step_ns, s)?;
            if !json {
                print_schedules(set, &lines, s.policy.tip_sigma_um);
            }
            summary.push(serde_json::json!({"set": set.name, "schedules": lines}));
            continue;
        }
        let every = Cycles::Every(units::min_to_ns(cycle_every_min));
        let rows = replay(set, &lay_out(set, step_ns), &policy, step_ns, &every)?.rows;
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

/// One schedule's replay of a set in a line.
#[derive(Debug, Clone, Serialize)]
pub struct ScheduleLine {
    pub schedule: String,
    /// The fixed cadence's interval, min.
    pub every_min: Option<f64>,
    pub cycles: usize,
    /// Cycles per run (the bench replays one run a day).
    pub cycles_per_day: f64,
    /// Medians over the channel-runs of the served value's RMSE, of the live model's own
    /// value's, and of the served value's largest error; the largest error of all.
    pub median_served: f64,
    pub median_model: f64,
    pub median_max: f64,
    pub largest: f64,
    /// Channel-runs where the served value is worse than the better baseline beyond chance.
    pub worse_beyond_chance: usize,
    /// The scheduler's rules and the cycles each ordered.
    pub reasons: BTreeMap<&'static str, usize>,
    /// Each cycle's start, h on the replay's clock, and its rule.
    pub starts: Vec<(f64, Option<&'static str>)>,
}

impl ScheduleLine {
    fn of(schedule: String, every_min: Option<f64>, r: &Replayed) -> Self {
        let m = |f: &dyn Fn(&ServedRow) -> f64| super::thermal::median(r.rows.iter().map(f));
        ScheduleLine {
            schedule,
            every_min,
            cycles: r.cycles,
            cycles_per_day: r.cycles as f64 / r.runs.max(1) as f64,
            median_served: m(&|x| x.served_rmse),
            median_model: m(&|x| x.model_rmse),
            median_max: m(&|x| x.served_max),
            largest: r.rows.iter().map(|x| x.served_max).fold(0.0, f64::max),
            worse_beyond_chance: r
                .rows
                .iter()
                .filter(|x| x.worse_beyond_chance.is_some())
                .count(),
            reasons: r.reasons.clone(),
            starts: r.starts.clone(),
        }
    }
}

/// The service's schedule with the tool-tip rule and without it, each next to the fixed
/// cadence with as many cycles.
fn compare_schedules(
    set: &ThermalData,
    policy: &PredictionPolicy,
    step_ns: i64,
    s: &Schedules,
) -> Result<Vec<ScheduleLine>> {
    let offsets = SchedulePolicy {
        tip_sigma_um: 0.0,
        ..s.policy.clone()
    };
    let layout = lay_out(set, step_ns);
    let mut out = Vec::new();
    for (name, p) in [
        ("minute offsets".to_string(), offsets),
        (
            format!("tool tip {} um", s.policy.tip_sigma_um),
            s.policy.clone(),
        ),
    ] {
        let scheduled = replay(
            set,
            &layout,
            policy,
            step_ns,
            &Cycles::Schedule(p, s.phase.clone()),
        )?;
        let every = as_many(&layout, set.channels.len(), step_ns, scheduled.cycles);
        let fixed = replay(
            set,
            &layout,
            policy,
            step_ns,
            &Cycles::Every(units::min_to_ns(every)),
        )?;
        out.push(ScheduleLine::of(name.clone(), None, &scheduled));
        out.push(ScheduleLine::of(
            format!("fixed, as {name}"),
            Some(every),
            &fixed,
        ));
    }
    Ok(out)
}

fn print_schedules(set: &ThermalData, lines: &[ScheduleLine], tip: f64) {
    println!(
        "\n{} ({} runs, one a day; {}): the service's schedules, the tool-tip rule at {tip} um on the root sum of squares of the channels' bands, against a fixed cadence with as many cycles; RMSE and largest error um on the updated readings between cycles",
        set.name,
        set.runs.len(),
        set.inputs
    );
    println!(
        "  {:<30} {:>7} {:>8} {:>8} {:>8} {:>9} {:>8} {:>6}  cycles ordered by",
        "schedule", "cycles", "per day", "served", "model", "max (med)", "largest", "worse"
    );
    for l in lines {
        let name = match l.every_min {
            Some(m) => format!("{} ({m} min)", l.schedule),
            None => l.schedule.clone(),
        };
        println!(
            "  {:<30} {:>7} {:>8.2} {:>8.2} {:>8.2} {:>9.2} {:>8.2} {:>6}  {}",
            name,
            l.cycles,
            l.cycles_per_day,
            l.median_served,
            l.median_model,
            l.median_max,
            l.largest,
            l.worse_beyond_chance,
            l.reasons
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
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
    use super::{Windows, worse_by_gap};

    /// A cycle reads each channel's first update within a step of its start, is counted once
    /// however many channels it reads, and is not taken when none updates in time.
    #[test]
    fn a_cycle_reads_each_channel_once_within_a_step_of_its_start() {
        let mut w = Windows::new(2, 10);
        let first = w.start(100, 100, None);
        assert!(w.take(0, 100) && !w.take(0, 105), "the first update only");
        assert!(w.take(1, 110), "up to a step after the start");
        // Nothing updates within a step of the second start: not taken.
        w.start(200, 200, None);
        assert!(!w.take(0, 211) && !w.take(1, 211));
        // A later start takes over a channel still waiting.
        w.start(300, 300, None);
        let last = w.start(305, 305, Some("tip"));
        assert!(w.take(1, 312));
        assert_eq!(w.taken.iter().copied().collect::<Vec<_>>(), [first, last]);
        let h = |ns: f64| ns / driftwatch_core::units::NS_PER_H as f64;
        assert_eq!(
            w.taken_starts(),
            [(h(100.0), None), (h(305.0), Some("tip"))]
        );
    }

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
