//! `bench located`: the located term's power on thermal-test data sets (a folder of
//! manifests and CSVs, `docs/thermal-sets.md`). Into each run's real readings of each
//! displacement channel, a drift that follows one temperature's change after an onset is
//! injected at 1.5, 3 and 6 um RMS ([`located_power`]), and the same run without it is the
//! null. Per run, per size: whether the located term names the injected sensor (found),
//! whether a term on it is accepted that the run alone does not have (found and modelled),
//! and any located term accepted on another sensor (on the null: any accepted at all).
//!
//! The sensor and the onset are fixed by a rule before any diagnosis is run, so the figures
//! cannot be tuned by the choice: the temperature with the largest range over the run, the
//! hall's or ambient one left out when its name says so (a drift that follows the room is
//! what the grey box's inputs already carry), and the onset at 40 % of the channel's span.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::ExitCode;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::Result;
use driftwatch_core::thermal_model::Event;
use driftwatch_core::units;
use driftwatch_diagnosis::calibration::{LocatedOutcome, located_power};
use driftwatch_diagnosis::displacement::DisplacementOptions;

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

/// One channel of one run: the rule's sensor and onset, and what the diagnosis made of each
/// size (or why it could not run).
#[derive(serde::Serialize)]
struct RunRow {
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
    set: String,
    rms_um: f64,
    trials: usize,
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

/// The rule's sensor: the largest range (max - min) over the run among the temperatures
/// whose name is not a hall's or an ambient one; ties go to the first name in sorted order.
fn rule_sensor(events: &[Event]) -> Option<(String, f64)> {
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
        if AMBIENT.iter().any(|a| lower.contains(a)) {
            continue;
        }
        if best.as_ref().is_none_or(|b| hi - lo > b.1) {
            best = Some((s.to_string(), hi - lo));
        }
    }
    best
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

/// One channel of one run through [`located_power`] at every size.
fn judge(set: &str, run: &str, events: &[Event], channel: &str) -> RunRow {
    let wall = Instant::now();
    let mut row = RunRow {
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
    let (Some((sensor, range)), Some((t0, t1))) =
        (rule_sensor(events), channel_span(events, channel))
    else {
        row.error = Some("no temperature or no reading of the channel".into());
        return row;
    };
    let onset_ns = t0 + ((t1 - t0) as f64 * ONSET_SHARE) as i64;
    row.sensor = sensor;
    row.sensor_range_k = range;
    row.onset_h = units::ns_to_h(onset_ns - t0);
    let opts = DisplacementOptions {
        n_ref_rpm: super::top_speed(events),
        ..Default::default()
    };
    match located_power(events, channel, &row.sensor, onset_ns, &SIZES, &opts) {
        Ok(o) => row.outcomes = o,
        Err(e) => row.error = Some(e.to_string()),
    }
    row.seconds = wall.elapsed().as_secs_f64();
    row
}

/// The jobs of a set: the first [`MAX_RUNS`] runs of at least [`MIN_RUN_H`], each channel.
fn jobs(set: &ThermalData) -> Vec<(usize, &str)> {
    set.runs
        .iter()
        .enumerate()
        .filter(|(_, r)| span_h(&r.events) >= MIN_RUN_H)
        .take(MAX_RUNS)
        .flat_map(|(i, _)| set.channels.iter().map(move |c| (i, c.as_str())))
        .collect()
}

/// Every job of `set` on every core (the diagnosis is single-threaded and the runs are
/// independent), the rows in job order whatever order they finish in.
fn run_set(set: &ThermalData) -> Vec<RunRow> {
    let jobs = jobs(set);
    let next = AtomicUsize::new(0);
    let done: Mutex<Vec<Option<RunRow>>> = Mutex::new((0..jobs.len()).map(|_| None).collect());
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(jobs.len().max(1));
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(i, channel)) = jobs.get(k) else {
                        break;
                    };
                    let run = &set.runs[i];
                    let row = judge(&set.name, &run.name, &run.events, channel);
                    if let Ok(mut d) = done.lock() {
                        d[k] = Some(row);
                    }
                }
            });
        }
    });
    done.into_inner()
        .unwrap_or_default()
        .into_iter()
        .flatten()
        .collect()
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

/// The per-set, per-size counts.
fn summarise(set: &str, rows: &[RunRow]) -> Vec<SizeRow> {
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
                set: set.to_string(),
                rms_um: size,
                trials: of.len(),
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
        let sizes = summarise(&set.name, &rows);
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
            rows.iter().for_each(print_run);
            print_table(&sizes);
        }
        runs.extend(rows);
        table.extend(sizes);
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
