//! `bench located`: the located term's power on thermal-test data sets (a folder of
//! manifests and CSVs, `docs/thermal-sets.md`). Into each run's real readings of each
//! displacement channel, a drift that follows one temperature's change after an onset is
//! injected at 1.5, 3 and 6 um RMS ([`located_power`]), and the same run without it is the
//! null. Per run, per size: whether the located term names the injected sensor (found),
//! whether a term on it is accepted that the run alone does not have (found and modelled),
//! and any located term accepted on another sensor (on the null: any accepted at all).
//!
//! The sensor and the onset are fixed by a rule before any diagnosis is run, so the figures
//! cannot be tuned by the choice: the onset at 40 % of the channel's span, and the sensor
//! by each of two rules, both reported:
//!
//! - `range`: the temperature with the largest range over the run, the hall's or ambient one
//!   left out when its name says so (a drift that follows the room is what the grey box's
//!   inputs already carry).
//! - `separable`: the same, among the temperatures whose change since the onset the
//!   diagnosis' own confounding checks would not refuse whatever it fits: over the channel's
//!   readings from the onset on, its correlation with time and with the spindle's heat
//!   input through every pole of the baseline's grid ([`DIAGNOSIS_TAUS_MIN`]) is at most
//!   [`RAMP_R`] in magnitude. A drift of a temperature that moves with the warm-up (or as
//!   steadily as time) is refused as `confounded_with_warm_up` (or `_with_ramp`) by design,
//!   and rightly: the warm-up term would carry it as well. Under `range` the largest range
//!   is often the spindle's own heat (gv1203: the spindle motor's controller temperature on
//!   every run), whose drift is largely the warm-up's shape, so its figures say how often
//!   the diagnosis separates what cannot be separated. A run where no temperature passes is
//!   not judged under `separable`, and says so. Fixed before its figures were seen; the
//!   spindle's heat input is the diagnosis' own, `(n / n_ref)^gamma` with the options'
//!   reference speed and exponent; without a spindle log only the ramp applies (the warm-up
//!   column is then a temperature that the diagnosis chooses, unknown here).

use std::collections::BTreeMap;
use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;

use crate::calibration::{LocatedOutcome, located_power};
use anyhow::Result;
use driftwatch_core::units;
use driftwatch_diagnosis::cycles::DIAGNOSIS_TAUS_MIN;
use driftwatch_diagnosis::displacement::{DisplacementOptions, RAMP_R};
use driftwatch_thermal::model::Event;

use crate::thermal_sets::{ThermalData, load_all};

/// Injected sizes, um RMS of the injection over the channel's readings (0: the null).
pub const SIZES: [f64; 4] = [0.0, 1.5, 3.0, 6.0];
/// Runs of a set judged, the first in manifest order that are long enough: a bench, not a
/// census (each run costs four diagnoses per channel).
const MAX_RUNS: usize = 8;
/// Shortest run judged, h: with the hold-out at the last 15 % and the onset at 40 %, a
/// shorter run leaves too few readings after the onset for the rolling origins.
const MIN_RUN_H: f64 = 3.0;
/// Where the onset is, as a share of the channel's span: well inside the training part
/// (which ends at 85 %), with as much before it as after.
const ONSET_SHARE: f64 = 0.4;
/// Name parts of a hall or ambient sensor.
const AMBIENT: [&str; 4] = ["ambient", "hall", "room", "air"];

/// How the injected sensor is chosen (the module's doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum SensorRule {
    Range,
    Separable,
}

const RULES: [SensorRule; 2] = [SensorRule::Range, SensorRule::Separable];

impl SensorRule {
    fn name(self) -> &'static str {
        match self {
            SensorRule::Range => "range",
            SensorRule::Separable => "separable",
        }
    }
}

/// One channel of one run: the rule's sensor and onset, and what the diagnosis made of each
/// size (or why it could not run).
#[derive(serde::Serialize)]
struct RunRow {
    rule: SensorRule,
    set: String,
    run: String,
    channel: String,
    sensor: String,
    sensor_range_k: f64,
    span_h: f64,
    onset_h: f64,
    outcomes: Vec<LocatedOutcome>,
    error: Option<String>,
    seconds: f64,
}

/// One set at one size.
#[derive(serde::Serialize)]
struct SizeRow {
    rule: SensorRule,
    set: String,
    rms_um: f64,
    trials: usize,
    /// Runs' channels with no sensor under the rule (not judged, so not in `trials`).
    not_judged: usize,
    found: usize,
    modelled: usize,
    false_terms: usize,
    /// Why the located term on the injected sensor was not accepted, by reason: what stands
    /// between found and modelled.
    not_confirmed: BTreeMap<String, usize>,
}

/// The run's span, h (events are timed from the run's start).
fn span_h(events: &[Event]) -> f64 {
    let first = events.first().map_or(0, Event::t_ns);
    let last = events.last().map_or(0, Event::t_ns);
    units::ns_to_h(last - first)
}

/// The `range` rule's sensor: the largest range (max - min) over the run among the
/// temperatures whose name is not a hall's or an ambient one (and that `eligible` admits);
/// ties go to the first name in sorted order.
fn rule_sensor(events: &[Event], eligible: &dyn Fn(&str) -> bool) -> Option<(String, f64)> {
    let mut range: BTreeMap<&str, (f64, f64)> = BTreeMap::new();
    for e in events {
        if let Event::Temperature {
            sensor, celsius, ..
        } = e
            && celsius.is_finite()
        {
            let r = range
                .entry(sensor)
                .or_insert((f64::INFINITY, f64::NEG_INFINITY));
            *r = (r.0.min(*celsius), r.1.max(*celsius));
        }
    }
    let mut best: Option<(String, f64)> = None;
    for (s, (lo, hi)) in range {
        let lower = s.to_lowercase();
        if AMBIENT.iter().any(|a| lower.contains(a)) || !eligible(s) {
            continue;
        }
        if best.as_ref().is_none_or(|b| hi - lo > b.1) {
            best = Some((s.to_string(), hi - lo));
        }
    }
    best
}

/// Pearson correlation; NaN when either side is constant.
fn corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    if n < 2.0 {
        return f64::NAN;
    }
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    sab / (saa * sbb).sqrt()
}

/// The temperatures the `separable` rule admits for `channel` with an onset at `onset_ns`:
/// those whose change since the onset (each taken at the channel's readings from the onset
/// on, from its value at the first of them, as the injection takes it) correlates with time
/// and with the heat input `(n / n_ref)^gamma` through every pole of the diagnosis' grid
/// (exact zero-order hold between events) at most [`RAMP_R`] in magnitude. A temperature
/// that does not change after the onset is not admitted (there is nothing to inject).
fn separable_sensors(
    events: &[Event],
    channel: &str,
    onset_ns: i64,
    opts: &DisplacementOptions,
) -> Vec<String> {
    let spins = events
        .iter()
        .any(|e| matches!(e, Event::Spindle { rpm, .. } if *rpm != 0.0));
    let mut heat = 0.0;
    let mut modes = [0.0; DIAGNOSIS_TAUS_MIN.len()];
    let mut last: Option<i64> = None;
    let mut now: BTreeMap<&str, f64> = BTreeMap::new();
    let mut at_onset: Option<BTreeMap<&str, f64>> = None;
    // Per reading from the onset on: time, the modes, every sensor's change since the onset.
    let mut t = Vec::new();
    let mut m: Vec<Vec<f64>> = vec![Vec::new(); DIAGNOSIS_TAUS_MIN.len()];
    let mut change: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for e in events {
        let te = e.t_ns();
        if let Some(l) = last {
            let dt_min = (te - l) as f64 / 6e10;
            for (y, tau) in modes.iter_mut().zip(DIAGNOSIS_TAUS_MIN) {
                *y += (heat - *y) * (1.0 - (-dt_min / tau).exp());
            }
        }
        last = Some(te);
        match e {
            Event::Spindle { rpm, .. } => {
                heat = (rpm.abs() / opts.n_ref_rpm.max(1.0)).powf(opts.gamma);
            }
            Event::Temperature {
                sensor, celsius, ..
            } if celsius.is_finite() => {
                now.insert(sensor, *celsius);
            }
            Event::Observation { channel: c, .. } if c == channel && te >= onset_ns => {
                let base = at_onset.get_or_insert_with(|| now.clone());
                t.push(te as f64);
                for (k, y) in modes.iter().enumerate() {
                    m[k].push(*y);
                }
                for (s, v) in &now {
                    if let Some(v0) = base.get(s) {
                        change.entry(s).or_default().push(v - v0);
                    }
                }
            }
            _ => {}
        }
    }
    change
        .into_iter()
        .filter(|(_, c)| c.len() == t.len())
        .filter(|(_, c)| {
            let r_time = corr(c, &t);
            // A constant change (none) gives NaN: nothing to inject, not admitted.
            // A mode that is constant from the onset on (a short pole, saturated) gives NaN:
            // there is no warm-up left there to confound the drift with.
            r_time.abs() <= RAMP_R
                && (!spins
                    || m.iter().all(|mk| {
                        let r = corr(c, mk);
                        r.is_nan() || r.abs() <= RAMP_R
                    }))
        })
        .map(|(s, _)| s.to_string())
        .collect()
}

/// The channel's first and last reading, ns.
fn channel_span(events: &[Event], channel: &str) -> Option<(i64, i64)> {
    let mut t = events.iter().filter_map(|e| match e {
        Event::Observation {
            t_ns, channel: c, ..
        } if c == channel => Some(*t_ns),
        _ => None,
    });
    let first = t.next()?;
    Some((first, t.next_back().unwrap_or(first)))
}

/// One channel of one run through [`located_power`] at every size, the sensor by `rule`.
fn judge(set: &str, run: &str, events: &[Event], channel: &str, rule: SensorRule) -> RunRow {
    let wall = Instant::now();
    let mut row = RunRow {
        rule,
        set: set.to_string(),
        run: run.to_string(),
        channel: channel.to_string(),
        sensor: String::new(),
        sensor_range_k: f64::NAN,
        span_h: span_h(events),
        onset_h: f64::NAN,
        outcomes: Vec::new(),
        error: None,
        seconds: 0.0,
    };
    let Some((t0, t1)) = channel_span(events, channel) else {
        row.error = Some("no reading of the channel".into());
        return row;
    };
    let onset_ns = t0 + ((t1 - t0) as f64 * ONSET_SHARE) as i64;
    row.onset_h = units::ns_to_h(onset_ns - t0);
    let opts = DisplacementOptions {
        n_ref_rpm: super::top_speed(events),
        ..Default::default()
    };
    let admitted = match rule {
        SensorRule::Range => None,
        SensorRule::Separable => Some(separable_sensors(events, channel, onset_ns, &opts)),
    };
    let eligible = |s: &str| admitted.as_ref().is_none_or(|a| a.iter().any(|x| x == s));
    let Some((sensor, range)) = rule_sensor(events, &eligible) else {
        row.error = Some(match rule {
            SensorRule::Range => "no temperature".into(),
            SensorRule::Separable => format!(
                "no temperature whose change since the onset moves apart from time and the warm-up (|r| <= {RAMP_R} with each)"
            ),
        });
        return row;
    };
    row.sensor = sensor;
    row.sensor_range_k = range;
    match located_power(events, channel, &row.sensor, onset_ns, &SIZES, &opts) {
        Ok(o) => row.outcomes = o,
        Err(e) => row.error = Some(e.to_string()),
    }
    row.seconds = wall.elapsed().as_secs_f64();
    row
}

/// The jobs of a set: the first [`MAX_RUNS`] runs of at least [`MIN_RUN_H`], each channel,
/// under each rule.
fn jobs(set: &ThermalData) -> Vec<(usize, &str, SensorRule)> {
    RULES
        .iter()
        .flat_map(|&rule| {
            set.runs
                .iter()
                .enumerate()
                .filter(|(_, r)| span_h(&r.events) >= MIN_RUN_H)
                .take(MAX_RUNS)
                .flat_map(move |(i, _)| set.channels.iter().map(move |c| (i, c.as_str(), rule)))
        })
        .collect()
}

/// Every job of `set` on every core (the diagnosis is single-threaded and the runs are
/// independent), the rows in job order whatever order they finish in.
fn run_set(set: &ThermalData) -> Vec<RunRow> {
    super::par_map(&jobs(set), |&(i, channel, rule)| {
        let run = &set.runs[i];
        judge(&set.name, &run.name, &run.events, channel, rule)
    })
}

/// One size of one outcome, in a few words.
fn outcome_text(o: &LocatedOutcome) -> String {
    let mut s = if o.rms_um == 0.0 {
        // What the run gives of itself: the located term may already follow the rule's
        // sensor (then the sizes' "found" says less).
        match &o.located_sensor {
            Some(l) => format!("null (located {l})"),
            None => "null".to_string(),
        }
    } else if o.modelled {
        "found+modelled".to_string()
    } else if o.found {
        match o.reason {
            Some(r) => format!("found, {r:?}"),
            None if o.located_accepted => "found, accepted (run had it)".to_string(),
            None => "found".to_string(),
        }
    } else {
        match &o.located_sensor {
            Some(l) => match o.reason {
                Some(r) => format!("missed (located {l}, {r:?})"),
                None => format!("missed (located {l})"),
            },
            None => "missed".to_string(),
        }
    };
    if let Some(f) = &o.false_term {
        s.push_str(&format!(" FALSE {f}"));
    }
    s
}

/// The per-set, per-size counts of the rows of `rule`.
fn summarise(set: &str, rule: SensorRule, rows: &[RunRow]) -> Vec<SizeRow> {
    let rows: Vec<&RunRow> = rows.iter().filter(|r| r.rule == rule).collect();
    let not_judged = rows.iter().filter(|r| r.error.is_some()).count();
    SIZES
        .iter()
        .map(|&size| {
            let of: Vec<&LocatedOutcome> = rows
                .iter()
                .flat_map(|r| &r.outcomes)
                .filter(|o| o.rms_um == size)
                .collect();
            let count = |f: &dyn Fn(&LocatedOutcome) -> bool| of.iter().filter(|o| f(o)).count();
            let mut not_confirmed = BTreeMap::new();
            for o in of.iter().filter(|o| o.found && !o.located_accepted) {
                *not_confirmed
                    .entry(o.reason.map_or("none".to_string(), |r| format!("{r:?}")))
                    .or_insert(0) += 1;
            }
            SizeRow {
                rule,
                set: set.to_string(),
                rms_um: size,
                trials: of.len(),
                not_judged,
                found: count(&|o| o.found),
                modelled: count(&|o| o.modelled),
                false_terms: count(&|o| o.false_term.is_some()),
                not_confirmed,
            }
        })
        .collect()
}

fn print_run(r: &RunRow) {
    let head = format!(
        "  {:<12} {:<10} {} ({:.1} K) from {:.1} h of {:.1} h",
        r.run, r.channel, r.sensor, r.sensor_range_k, r.onset_h, r.span_h
    );
    match &r.error {
        Some(e) => println!("{head}: not judged: {e}"),
        None => {
            let sizes: Vec<String> = r
                .outcomes
                .iter()
                .map(|o| format!("{}: {}", o.rms_um, outcome_text(o)))
                .collect();
            println!("{head} [{:.0} s] | {}", r.seconds, sizes.join(" | "));
        }
    }
}

fn print_table(rows: &[SizeRow]) {
    // At size 0 "found" is the run's own located term on the rule's sensor: no injection,
    // so it is neither power nor a false term, but it tempers the found rates above it.
    if let Some(s) = rows.first() {
        println!(
            "  sensor rule {}{}",
            s.rule.name(),
            if s.not_judged > 0 {
                format!(" ({} channel-runs not judged: no sensor)", s.not_judged)
            } else {
                String::new()
            }
        );
    }
    println!(
        "  size um | trials | found | found and modelled | false located terms | found, not confirmed"
    );
    for s in rows {
        let why: Vec<String> = s
            .not_confirmed
            .iter()
            .map(|(r, n)| format!("{r} {n}"))
            .collect();
        println!(
            "  {:>7} | {:>6} | {:>5} | {:>18} | {:>19} | {}",
            s.rms_um,
            s.trials,
            s.found,
            s.modelled,
            format!(
                "{}{}",
                s.false_terms,
                if s.rms_um == 0.0 { " (null)" } else { "" }
            ),
            why.join(", ")
        );
    }
}

/// `bench located --data DIR`: every set under `dir`, its long-enough runs and channels.
pub fn located(data: &Path, json: bool) -> Result<ExitCode> {
    let wall = Instant::now();
    let sets = load_all(data)?;
    let mut runs = Vec::new();
    let mut table = Vec::new();
    for set in &sets {
        let t = Instant::now();
        let rows = run_set(set);
        let sizes: Vec<Vec<SizeRow>> = RULES
            .iter()
            .map(|&rule| summarise(&set.name, rule, &rows))
            .collect();
        if !json {
            println!(
                "{} ({} runs, {} judged; {}): {:.0} s",
                set.name,
                set.runs.len(),
                rows.iter()
                    .map(|r| r.run.as_str())
                    .collect::<std::collections::BTreeSet<_>>()
                    .len(),
                set.inputs,
                t.elapsed().as_secs_f64()
            );
            for (rule, sizes) in RULES.iter().zip(&sizes) {
                println!("  sensor rule {}:", rule.name());
                rows.iter().filter(|r| r.rule == *rule).for_each(print_run);
                print_table(sizes);
            }
        }
        runs.extend(rows);
        table.extend(sizes.into_iter().flatten());
    }
    let seconds = wall.elapsed().as_secs_f64();
    if json {
        let report = serde_json::json!({"sizes": table, "runs": runs, "seconds": seconds});
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("wall time {seconds:.0} s");
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN_NS: i64 = 60_000_000_000;

    /// A 6-h run, the spindle on from the start: a temperature that warms up with it through
    /// a 50-min lag (largest range), one that swings with a 2-h period (a coolant), one that
    /// rises as steadily as time, and one that stays put; a reading every 5 min.
    fn run() -> Vec<Event> {
        let mut ev = vec![Event::Spindle {
            t_ns: 0,
            rpm: 4000.0,
        }];
        for k in 0..=72 {
            let t_ns = k * 5 * MIN_NS;
            let h = k as f64 * 5.0 / 60.0;
            for (sensor, celsius) in [
                ("spindle_C", 20.0 + 15.0 * (1.0 - (-h * 60.0 / 50.0).exp())),
                (
                    "coolant_C",
                    20.0 + 2.0 * (std::f64::consts::TAU * h / 2.0).sin(),
                ),
                ("column_C", 20.0 + 0.5 * h),
                ("bed_C", 20.0),
            ] {
                ev.push(Event::Temperature {
                    t_ns,
                    sensor: sensor.into(),
                    celsius,
                });
            }
            ev.push(Event::Observation {
                t_ns,
                channel: "z_um".into(),
                value: 0.0,
                sigma: None,
            });
        }
        ev
    }

    /// The `separable` rule admits the swinging temperature alone: the warming one moves
    /// with the spindle's heat input through a pole of the grid, the steady one with time,
    /// the flat one not at all; the `range` rule takes the warming one.
    #[test]
    fn the_separable_rule_admits_only_what_moves_apart_from_the_warm_up_and_time() {
        let ev = run();
        let opts = DisplacementOptions {
            n_ref_rpm: 4000.0,
            ..Default::default()
        };
        let onset = (0.4 * 6.0 * 60.0) as i64 * MIN_NS;
        assert_eq!(
            separable_sensors(&ev, "z_um", onset, &opts),
            vec!["coolant_C".to_string()]
        );
        assert_eq!(
            rule_sensor(&ev, &|_| true).map(|s| s.0),
            Some("spindle_C".to_string())
        );
    }

    /// Under `separable` a run where every temperature moves with the warm-up is not judged,
    /// and the row says why; under `range` it is judged.
    #[test]
    fn a_run_without_a_separable_temperature_is_not_judged_and_says_why() {
        let ev: Vec<Event> = run()
            .into_iter()
            .filter(|e| !matches!(e, Event::Temperature { sensor, .. } if sensor == "coolant_C"))
            .collect();
        let row = judge("set", "run", &ev, "z_um", SensorRule::Separable);
        assert!(row.outcomes.is_empty());
        assert!(
            row.error
                .as_deref()
                .is_some_and(|e| e.contains("moves apart from time and the warm-up")),
            "{:?}",
            row.error
        );
        assert!(separable_sensors(&ev, "z_um", 0, &DisplacementOptions::default()).is_empty());
    }
}
