//! `bench thermal`: every model family against the textbook baselines on thermal-test data
//! sets (a folder of manifests and CSVs, `docs/thermal-sets.md`) and the simulated
//! scenarios, as a new user would run them:
//! - **within a run**: fit on the first share of each run (or its first hours), predict the
//!   rest freely with no reading after the cut, scored on the readings the sensor updated;
//!   what is served is what `fit` and `predict` serve (the choice, the hand-over to the grey
//!   box where the choice says so);
//! - **across runs**: each run from the second on predicted whole, from its first reading,
//!   by what was learnt on the runs before it (forward chaining), next to pooled least
//!   squares and holding the first reading.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use driftwatch_core::units;
use driftwatch_thermal::across_runs;
use driftwatch_thermal::families::{
    self, ChannelChoice, Family, Grid, describe_served, grey_box, grey_box_config, grid, rms,
};
use driftwatch_thermal::model::Event;

use crate::thermal_sets::{Run, ThermalData, load_all};

/// Days of each simulated scenario, its fit span and the sensor noise.
const SIM_DAYS: usize = 3;
const SIM_TRAIN_H: f64 = 40.0;
const SIM_SIGMA: f64 = 0.5;

/// The simulated scenarios as a test rig sees them (`strategies::sensor_view`): every
/// identified error that moves by more than ten times the sensor noise is a channel.
fn simulated_sets() -> Result<Vec<ThermalData>> {
    let mut out = Vec::new();
    for (name, _) in crate::strategies::BENCH_SCENARIOS {
        let events = crate::strategies::sensor_view(name, SIM_DAYS, SIM_SIGMA)?;
        let mut range: std::collections::BTreeMap<&str, (f64, f64)> = Default::default();
        for e in &events {
            if let Event::Observation { channel, value, .. } = e {
                let r = range
                    .entry(channel)
                    .or_insert((f64::INFINITY, f64::NEG_INFINITY));
                *r = (r.0.min(*value), r.1.max(*value));
            }
        }
        let channels = range
            .iter()
            .filter(|(_, (lo, hi))| hi - lo > 10.0 * SIM_SIGMA)
            .map(|(c, _)| c.to_string())
            .collect();
        out.push(ThermalData {
            name: format!("simulated {name}, {SIM_DAYS} days"),
            source: "driftwatch's simulator".into(),
            licence: String::new(),
            description: String::new(),
            runs: vec![Run {
                name: "run".into(),
                events: events.clone(),
            }],
            channels,
            inputs: "spindle + logged temperatures; EA0C, EB0C in urad, the rest in um".into(),
            fit_share: 0.55,
            fit_h: Some(SIM_TRAIN_H),
            step_min: Some(5.0),
        });
    }
    Ok(out)
}

/// One channel-run within a run: every baseline's hold-out RMSE and what is served.
#[derive(serde::Serialize)]
struct WithinRow {
    set: String,
    run: String,
    channel: String,
    fit_h: f64,
    predict_h: f64,
    served: String,
    served_rmse: f64,
    why: String,
    persistence: f64,
    regression: f64,
    key_regression: f64,
    arx: f64,
    grey_box: f64,
    /// Served over the better of persistence and regression on every input.
    ratio_to_better: f64,
    families: Vec<families::FamilyScore>,
}

/// One run predicted whole from what the runs before it taught.
#[derive(serde::Serialize)]
struct AcrossRow {
    set: String,
    run: String,
    channel: String,
    served: String,
    served_rmse: f64,
    why: String,
    persistence: f64,
    regression: f64,
    key_regression: f64,
    arx: f64,
    /// The share of the uncompensated error (holding the first reading) removed.
    served_removed: f64,
    regression_removed: f64,
    /// Where the run left the changes the earlier runs taught (input, h), if it did.
    leaves: Option<String>,
}

/// The grid step for a set: given, or the rows' median spacing but at least a 400th of the
/// shortest run.
pub(super) fn step_ns_of(set: &ThermalData, step_min: Option<f64>) -> i64 {
    if let Some(m) = step_min.or(set.step_min) {
        return units::min_to_ns(m);
    }
    let runs: Vec<&[Event]> = set.runs.iter().map(|r| r.events.as_slice()).collect();
    families::default_step_ns(&runs)
}

/// What is served on the hold-out of a channel whose family was chosen on `0..n_train`, as
/// `predict` serves it, and its sources in words.
fn served_holdout(
    events: &[Event],
    g: &Grid,
    n_train: usize,
    c: &ChannelChoice,
) -> Option<(Vec<f64>, String)> {
    let n = g.len();
    let (grey, prev) = if c.needs_grey() {
        let gb = grey_box(events, &grey_box_config(g), g, n_train - 1, n)?;
        (gb[1..].to_vec(), gb[0])
    } else {
        (vec![f64::NAN; n - n_train], f64::NAN)
    };
    let served = c.serve(g, n_train, n, &grey, prev);
    let desc = describe_served(&served, g, n_train);
    Some((served.into_iter().map(|s| s.0).collect(), desc))
}

/// RMSE of `p` against the fresh readings of `g` from `from` on.
fn fresh_rmse(p: &[f64], g: &Grid, from: usize) -> f64 {
    let e: Vec<f64> = p
        .iter()
        .enumerate()
        .filter(|(i, _)| g.fresh[from + i])
        .map(|(i, v)| v - g.y[from + i])
        .collect();
    if e.is_empty() { f64::NAN } else { rms(&e) }
}

/// Every channel of every run of `set`, within the run.
fn within(set: &ThermalData, step_ns: i64, json: bool) -> Vec<WithinRow> {
    let mut rows = Vec::new();
    for run in &set.runs {
        let ev = &run.events;
        let (Some(t0), Some(t1)) = (ev.first().map(Event::t_ns), ev.last().map(Event::t_ns)) else {
            continue;
        };
        let cut = match set.fit_h {
            Some(h) => t0 + units::h_to_ns(h),
            None => t0 + ((t1 - t0) as f64 * set.fit_share) as i64,
        };
        for ch in &set.channels {
            let Some(g) = grid(ev, ch, step_ns) else {
                continue;
            };
            let n_train = g.index_at(cut);
            if n_train < 16 || n_train + 2 > g.len() {
                continue;
            }
            let horizon = g.len() - n_train;
            let grey = grey_box_config(&g);
            let Some(c) = families::choose(ev, &g, cut, &Family::ALL, &grey, None, horizon) else {
                continue;
            };
            let Some((p, desc)) = served_holdout(ev, &g, n_train, &c) else {
                continue;
            };
            let served = fresh_rmse(&p, &g, n_train);
            let by = |f: Family| {
                c.scores
                    .iter()
                    .find(|s| s.family == f.as_str())
                    .map_or(f64::NAN, |s| s.holdout_rmse)
            };
            let better = by(Family::Persistence).min(by(Family::Regression));
            let row = WithinRow {
                set: set.name.clone(),
                run: run.name.clone(),
                channel: ch.clone(),
                fit_h: units::ns_to_h(cut - t0),
                predict_h: units::ns_to_h(t1 - cut),
                served: desc,
                served_rmse: served,
                why: c.choice.as_ref().map_or(String::new(), |x| x.why.clone()),
                persistence: by(Family::Persistence),
                regression: by(Family::Regression),
                key_regression: by(Family::KeyRegression),
                arx: by(Family::Arx),
                grey_box: by(Family::GreyBox),
                ratio_to_better: served / better,
                families: c.scores.clone(),
            };
            if !json {
                println!(
                    "{:<10} {:<8} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>6.2}  {}",
                    row.run,
                    row.channel,
                    row.served_rmse,
                    row.persistence,
                    row.regression,
                    row.key_regression,
                    row.arx,
                    row.grey_box,
                    row.ratio_to_better,
                    row.served
                );
            }
            rows.push(row);
        }
    }
    rows
}

/// Every run from the second on, predicted whole from what the runs before it taught.
fn across(set: &ThermalData, step_ns: i64, json: bool) -> Vec<AcrossRow> {
    let mut rows = Vec::new();
    for ch in &set.channels {
        let grids: Vec<(&str, Grid)> = set
            .runs
            .iter()
            .filter_map(|r| grid(&r.events, ch, step_ns).map(|g| (r.name.as_str(), g)))
            .filter(|(_, g)| g.len() >= 4)
            .collect();
        if grids.len() < 2 || grids.iter().any(|(_, g)| g.names != grids[0].1.names) {
            continue;
        }
        let refs: Vec<&Grid> = grids.iter().map(|(_, g)| g).collect();
        for i in 1..refs.len() {
            let Some(c) = across_runs::choose(&refs[..i]) else {
                continue;
            };
            let g = refs[i];
            let all: Vec<usize> = (0..g.names.len()).collect();
            let fam = |f: Family| {
                across_runs::fit(f, &refs[..i], &all).map_or(f64::NAN, |m| {
                    fresh_rmse(&across_runs::predict(&m, g)[1..], g, 1)
                })
            };
            let served = fresh_rmse(&across_runs::predict(&c.fitted, g)[1..], g, 1);
            let (persistence, regression) = (fam(Family::Persistence), fam(Family::Regression));
            let removed = |e: f64| 1.0 - (e / persistence).powi(2);
            let leaves = across_runs::leaves_changes(&c, g).map(|(k, j, d)| {
                format!(
                    "{} changed by {d:.2} at {:.2} h",
                    g.names[j],
                    units::ns_to_h(g.t_ns[k] - g.t_ns[0])
                )
            });
            let row = AcrossRow {
                set: set.name.clone(),
                run: grids[i].0.to_string(),
                channel: ch.clone(),
                served: c.family.as_str().into(),
                served_rmse: served,
                why: c.why.clone(),
                persistence,
                regression,
                key_regression: fam(Family::KeyRegression),
                arx: fam(Family::Arx),
                served_removed: removed(served),
                regression_removed: removed(regression),
                leaves,
            };
            if !json {
                println!(
                    "{:<10} {:<8} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>7.0}% {:>7.0}%  {}{}",
                    row.run,
                    row.channel,
                    row.served_rmse,
                    row.persistence,
                    row.regression,
                    row.key_regression,
                    row.arx,
                    100.0 * row.served_removed,
                    100.0 * row.regression_removed,
                    row.served,
                    row.leaves
                        .as_ref()
                        .map_or(String::new(), |l| format!("; beyond the earlier runs: {l}"))
                );
            }
            rows.push(row);
        }
    }
    rows
}

pub(super) fn median(v: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = v.filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// The acceptance figures of a set within its runs.
fn within_summary(name: &str, rows: &[&WithinRow]) -> (String, serde_json::Value) {
    let n = rows.len();
    let beats = rows
        .iter()
        .filter(|r| r.served_rmse < r.persistence)
        .count();
    let worst = rows
        .iter()
        .map(|r| r.ratio_to_better)
        .filter(|x| x.is_finite())
        .fold(0.0f64, f64::max);
    let over = rows.iter().filter(|r| r.ratio_to_better > 1.5).count();
    let m_served = median(rows.iter().map(|r| r.served_rmse));
    let m_reg = median(rows.iter().map(|r| r.regression));
    let m_pers = median(rows.iter().map(|r| r.persistence));
    let line = format!(
        "  {name}, within runs: {n} channel-runs; median RMSE served {m_served:.2}, regression on every input {m_reg:.2}, persistence {m_pers:.2} (served/regression {:.2}); served beats persistence in {beats} of {n} ({:.0} %); worst served/better baseline {worst:.2}, {over} over 1.5",
        m_served / m_reg,
        100.0 * beats as f64 / n.max(1) as f64
    );
    (
        line,
        serde_json::json!({"set": name, "channel_runs": n, "median_served": m_served,
        "median_regression": m_reg, "median_persistence": m_pers, "beats_persistence": beats,
        "worst_ratio_to_better": worst, "over_1_5": over}),
    )
}

fn across_summary(name: &str, rows: &[&AcrossRow]) -> (String, serde_json::Value) {
    let n = rows.len();
    let m = |f: &dyn Fn(&AcrossRow) -> f64| median(rows.iter().map(|r| f(r)));
    let (ms, mr, mp) = (
        m(&|r| r.served_rmse),
        m(&|r| r.regression),
        m(&|r| r.persistence),
    );
    let (rs, rr) = (m(&|r| r.served_removed), m(&|r| r.regression_removed));
    let worse = rows
        .iter()
        .filter(|r| r.served_rmse > r.regression * 1.0001)
        .count();
    let fails = rows.iter().filter(|r| r.served_removed < 0.0).count();
    let flagged = rows.iter().filter(|r| r.leaves.is_some()).count();
    let line = format!(
        "  {name}, across runs: {n} channel-runs predicted whole from the runs before; median RMSE served {ms:.2}, pooled regression {mr:.2}, first reading held {mp:.2}; median share of the uncompensated error removed: served {:.0} %, pooled regression {:.0} %; served worse than pooled regression on {worse}, worse than holding the first reading on {fails}; {flagged} runs went beyond the earlier runs' changes",
        100.0 * rs,
        100.0 * rr
    );
    (
        line,
        serde_json::json!({"set": name, "channel_runs": n, "median_served": ms,
        "median_regression": mr, "median_persistence": mp, "median_removed_served": rs,
        "median_removed_regression": rr, "worse_than_regression": worse,
        "worse_than_persistence": fails, "beyond_earlier_runs": flagged}),
    )
}

/// `bench thermal`.
pub fn thermal(
    data: &Path,
    step_min: Option<f64>,
    json: bool,
    simulated: bool,
) -> Result<ExitCode> {
    let mut sets = load_all(data)?;
    if simulated {
        sets.extend(simulated_sets()?);
    }
    let mut within_rows = Vec::new();
    let mut across_rows = Vec::new();
    for set in &sets {
        let step_ns = step_ns_of(set, step_min);
        if !json {
            println!(
                "\n{} ({} runs; {}; {:.2}-min grid){}",
                set.name,
                set.runs.len(),
                set.inputs,
                units::ns_to_min(step_ns),
                if set.licence.is_empty() {
                    String::new()
                } else {
                    format!(
                        "\n  source: {}; licence: {}\n  {}",
                        set.source, set.licence, set.description
                    )
                }
            );
            println!(
                "within each run: fit on {}, predict the rest freely; hold-out RMSE on the updated readings",
                set.fit_h.map_or(
                    format!("the first {:.0} %", 100.0 * set.fit_share),
                    |h| format!("the first {h} h")
                )
            );
            println!(
                "{:<10} {:<8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>6}  what is served",
                "run",
                "channel",
                "served",
                "persist",
                "regress",
                "key reg",
                "arx",
                "grey box",
                "ratio"
            );
        }
        within_rows.extend(within(set, step_ns, json));
        if set.runs.len() >= 2 {
            if !json {
                println!(
                    "across runs: each run predicted whole from its first reading by what the runs before it taught"
                );
                println!(
                    "{:<10} {:<8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}  served",
                    "run",
                    "channel",
                    "served",
                    "persist",
                    "regress",
                    "key reg",
                    "arx",
                    "served%",
                    "regress%"
                );
            }
            across_rows.extend(across(set, step_ns, json));
        }
    }
    if !json {
        println!("\nsummary:");
    }
    let mut summary = Vec::new();
    for set in &sets {
        let w: Vec<&WithinRow> = within_rows.iter().filter(|r| r.set == set.name).collect();
        let a: Vec<&AcrossRow> = across_rows.iter().filter(|r| r.set == set.name).collect();
        let lines = [
            (!w.is_empty()).then(|| within_summary(&set.name, &w)),
            (!a.is_empty()).then(|| across_summary(&set.name, &a)),
        ];
        for (line, value) in lines.into_iter().flatten() {
            if !json {
                println!("{line}");
            }
            summary.push(value);
        }
    }
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "within": within_rows, "across": across_rows, "summary": summary
            }))?
        );
    }
    Ok(ExitCode::SUCCESS)
}
