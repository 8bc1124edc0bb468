//! The diagnosis on simulated recordings: injection and recovery of concealed effects
//! (docs/physics.md 4.8). Every recording is three production days with a cycle every 30 min and
//! 0.5-um noise; the last day is the held-out part.

use std::collections::BTreeMap;

use driftwatch_core::identify::SolveOptions;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::thermal::Channel;
use driftwatch_diagnosis::cycles::{
    DiagnoseOptions, Diagnosis, Inputs, detection_rows, diagnose, screen_outliers,
};
use driftwatch_sim::scenario::{FeedChange, Scenario};
use driftwatch_thermal::model::ModelInput;

/// Three production days (the two-shift program of `ambient_swing` each day), a cycle every
/// 30 min, 0.5-um noise, the hall at a constant 20 C (logged), no thermal truth (each case
/// adds its own).
fn three_days(seed: u64) -> Scenario {
    three_days_on("table_bc", seed)
}

/// As [`three_days`], on another machine family with its own plan (the virtual machine's
/// default thermal story drives that family's own errors).
fn three_days_on(machine: &str, seed: u64) -> Scenario {
    Scenario::load("ambient_swing").unwrap().diagnosis_days(
        machine,
        &Kinematics::load(machine).unwrap().config.plan,
        seed,
    )
}

fn channel(toml_text: &str) -> Channel {
    toml::from_str(toml_text).unwrap()
}

/// The recording of a scenario, optionally without the spindle messages of the cycles' own
/// spins (a log that only has the production program).
fn record(scn: &Scenario, strip_spins: bool) -> Inputs {
    let k = Kinematics::load(&scn.machine).unwrap();
    let p = Plan::build(&k, &PlanConfig::load(&scn.plan).unwrap()).unwrap();
    let sim = driftwatch_sim::simulator::simulate(scn, &k, &p).unwrap();
    let mut rec = sim.recording();
    if strip_spins {
        let windows: Vec<(i64, i64)> = sim
            .cycles
            .iter()
            .map(|c| {
                let end = c
                    .detections
                    .iter()
                    .map(|d| d.t_ns)
                    .max()
                    .unwrap_or(c.start_ns);
                (c.start_ns, end + 60_000_000_000)
            })
            .collect();
        rec.spindle
            .retain(|m| !windows.iter().any(|(a, b)| m.t_ns >= *a && m.t_ns <= *b));
    }
    Inputs::of(&rec)
}

fn diagnose_inputs(scn: &Scenario, inputs: &Inputs) -> Diagnosis {
    let k = Kinematics::load(&scn.machine).unwrap();
    let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
    diagnose(
        &rows,
        &inputs.spindle,
        &inputs.temperatures,
        &DiagnoseOptions::new(0.5),
    )
    .unwrap()
}

/// A reading's place: its cycle, what it measured, and which pass of that measurement in the
/// cycle (the time-symmetric plan makes each twice).
type Place = (i64, String, usize);

fn places(cycles: &[i64], steps: &[String]) -> Vec<Place> {
    let mut seen: BTreeMap<(i64, &str), usize> = BTreeMap::new();
    cycles
        .iter()
        .zip(steps)
        .map(|(c, s)| {
            let n = seen.entry((*c, s.as_str())).or_default();
            *n += 1;
            (*c, s.clone(), *n)
        })
        .collect()
}

/// Each reading of a recording with its place, its time and its deviation (um).
fn placed(scn: &Scenario, inputs: &Inputs) -> Vec<(Place, i64, f64)> {
    let k = Kinematics::load(&scn.machine).unwrap();
    let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
    let cycles: Vec<i64> = rows.rows.iter().map(|r| r.cycle).collect();
    let steps: Vec<String> = rows.rows.iter().map(|r| r.step.clone()).collect();
    places(&cycles, &steps)
        .into_iter()
        .zip(&rows.rows)
        .map(|(p, r)| (p, r.t_ns, r.deviation_um))
        .collect()
}

/// Each reading's place by its time: a diagnosis that screened some readings out keeps the
/// places of the rest.
fn places_by_time(scn: &Scenario, inputs: &Inputs) -> BTreeMap<i64, Place> {
    placed(scn, inputs)
        .into_iter()
        .map(|(p, t, _)| (t, p))
        .collect()
}

/// Each reading's deviation by its place, um.
fn deviations(scn: &Scenario, inputs: &Inputs) -> BTreeMap<Place, f64> {
    placed(scn, inputs)
        .into_iter()
        .map(|(p, _, d)| (p, d))
        .collect()
}

enum Expect {
    /// Named (or in the named term's ambiguity group), amplitude within 20 %, held-out error
    /// against the noise-free readings down by 30 % or more.
    Found,
    /// Listed as not identifiable, and nothing selected.
    NotIdentifiable,
}

struct Case {
    effect: &'static str,
    concealment: &'static str,
    /// Conditions of the recording (the hall, the cycles' speeds and feeds) ...
    setup: fn(&mut Scenario),
    /// ... and the effect itself.
    inject: fn(&mut Scenario),
    strip_spins: bool,
    expect: Expect,
}

fn swing(scn: &mut Scenario) {
    scn.ambient.amplitude_k = 1.5;
}
fn swing_unlogged(scn: &mut Scenario) {
    scn.ambient.amplitude_k = 1.5;
    scn.ambient.logged = false;
    // The spindle-head sensor also sees the hall: no temperature at all is logged.
    scn.truth.unlogged = vec!["spindle_head".into()];
}
fn alternate_speed(scn: &mut Scenario) {
    scn.cycles.rpm_sequence = vec![20000.0, 8000.0];
}
fn raise_feed(scn: &mut Scenario) {
    scn.cycles.feed_changes = vec![FeedChange {
        at_min: 1440.0,
        feed_mm_min: 200.0,
    }];
}
fn alternate_speed_wide(scn: &mut Scenario) {
    scn.cycles.rpm_sequence = vec![20000.0, 4000.0];
}
fn nothing(_: &mut Scenario) {}
/// The patent's sequential order: every pose reached from one sense of B only.
fn sequential(scn: &mut Scenario) {
    scn.plan = "patent_sequential".into();
}

fn cases() -> Vec<Case> {
    vec![
        Case {
            effect: "setter_drift",
            concealment: "a: 0.3 um/K over +-1.5 K, under one reading's noise",
            setup: swing,
            inject: |s| {
                s.truth.channels.insert(
                    "setter_z".into(),
                    channel("ambient = [{ gain = 0.3, tau_min = 60.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "setter_drift",
            concealment: "c: the hall temperature that drives it is not logged",
            setup: swing_unlogged,
            inject: |s| {
                s.truth.channels.insert(
                    "setter_z".into(),
                    channel("ambient = [{ gain = 0.6, tau_min = 60.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "ambient",
            concealment: "a: EZ0B 0.33 um/K over +-1.5 K (60-min lag), under 0.5 um",
            setup: swing,
            inject: |s| {
                s.truth.channels.insert("EZ0B".into(), channel("spindle = [{ gain = 48.0, tau_min = 120.0 }]\nambient = [{ gain = 0.33, tau_min = 60.0 }]"));
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "ambient",
            concealment: "c: EX0B 1 um/K, the hall temperature not logged",
            setup: swing_unlogged,
            inject: |s| {
                s.truth.channels.insert("EX0B".into(), channel("spindle = [{ gain = 22.0, tau_min = 60.0 }]\nambient = [{ gain = 1.0, tau_min = 180.0 }]"));
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "skip_latency",
            concealment: "b: 2.4 ms beyond the calibration, the feed raised from 100 to 200 mm/min on day 2; cancels in the patent's sums",
            setup: raise_feed,
            inject: |s| s.skip.latency_ms = 2.4,
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "skip_latency",
            concealment: "d: 2.4 ms at one feed, the same as the setter's calibration",
            setup: nothing,
            inject: |s| s.skip.latency_ms = 2.4,
            strip_spins: false,
            expect: Expect::NotIdentifiable,
        },
        Case {
            effect: "radius_speed",
            concealment: "b: 1 um at 20000 min^-1, cycles alternating with 8000; cancels in the sums",
            setup: alternate_speed,
            inject: |s| {
                s.truth
                    .channels
                    .insert("radius".into(), channel("instant = 1.0"));
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "speed_shift",
            concealment: "a: -0.49 um at 20000 min^-1, cycles alternating with 4000",
            setup: alternate_speed_wide,
            inject: |s| {
                s.truth.channels.insert(
                    "sz".into(),
                    channel("instant = -0.49\nspindle = [{ gain = -41.0, tau_min = 11.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "speed_shift",
            concealment: "d: -3 um, every cycle at one speed",
            setup: nothing,
            inject: |s| {
                s.truth.channels.insert(
                    "sz".into(),
                    channel("instant = -3.0\nspindle = [{ gain = -41.0, tau_min = 11.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::NotIdentifiable,
        },
        Case {
            effect: "spindle_axial_growth",
            concealment: "d: 10 um more tool growth with a 25-min lag, the same as EZ0B",
            setup: nothing,
            inject: |s| {
                s.truth.channels.insert("sz".into(), channel("spindle = [{ gain = -41.0, tau_min = 11.0 }, { gain = -10.0, tau_min = 25.0 }]"));
            },
            strip_spins: false,
            expect: Expect::NotIdentifiable,
        },
        Case {
            effect: "scale_expansion",
            concealment: "a: X scale 6 ppm/K over +-1.5 K",
            setup: swing,
            inject: |s| {
                s.truth.channels.insert(
                    "kx".into(),
                    channel("ambient = [{ gain = 6.0, tau_min = 120.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "squareness",
            concealment: "a: XZ squareness following the hall, 3.5 urad/K over +-1.5 K (120-min lag)",
            setup: swing,
            inject: |s| {
                s.truth.channels.insert(
                    "sxz".into(),
                    channel("ambient = [{ gain = 3.5, tau_min = 120.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "rotary_backlash",
            concealment: "a: 20 urad of B backlash, 0.4 um on the readings it moves",
            setup: nothing,
            inject: |s| s.rotary.backlash_urad = vec![20.0],
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "slow_mode",
            concealment: "a: EZ0B 8 um with a 1500-min lag; all but 0.06 um RMS of it is absorbed by the baseline's 600-min lag",
            setup: nothing,
            inject: |s| {
                s.truth.channels.insert("EZ0B".into(), channel("spindle = [{ gain = 48.0, tau_min = 120.0 }, { gain = 8.0, tau_min = 1500.0 }]"));
            },
            strip_spins: false,
            expect: Expect::Found,
        },
        Case {
            effect: "measurement_heating",
            concealment: "c: the spindle log has only the production program, not the cycles' spins",
            setup: nothing,
            inject: nothing,
            strip_spins: true,
            expect: Expect::Found,
        },
        Case {
            effect: "radius_speed",
            concealment: "d: 1 um at 20000 min^-1, every cycle at one speed",
            setup: nothing,
            inject: |s| {
                s.truth
                    .channels
                    .insert("radius".into(), channel("instant = 1.0"));
            },
            strip_spins: false,
            expect: Expect::NotIdentifiable,
        },
        Case {
            effect: "rotary_backlash",
            concealment: "b: 20 urad of B backlash, each pose reached from one sense only (sequential order)",
            setup: sequential,
            inject: |s| s.rotary.backlash_urad = vec![20.0],
            strip_spins: false,
            expect: Expect::Found,
        },
    ]
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// Run one case; `Ok(summary)` when it passes, `Err(why)` when not.
fn check(case: &Case, seed: u64) -> Result<String, String> {
    check_on("table_bc", case, seed)
}

fn check_on(machine: &str, case: &Case, seed: u64) -> Result<String, String> {
    let mut bare = three_days_on(machine, seed);
    (case.setup)(&mut bare);
    let mut scn = bare.clone();
    (case.inject)(&mut scn);
    let inputs = record(&scn, case.strip_spins);
    let d = diagnose_inputs(&scn, &inputs);
    let named: Vec<String> = d
        .accepted
        .iter()
        .map(|a| {
            let g: Vec<&str> = a
                .ambiguity_group
                .iter()
                .map(|m| m.effect.as_str())
                .collect();
            let p: Vec<String> = a
                .parameters
                .iter()
                .map(|p| format!("{:.3}+-{:.3} {}", p.value, p.sigma, p.unit))
                .collect();
            format!(
                "{} {} [{}] = {p:?} (dBIC {:.0}) group {:?}",
                a.effect,
                a.term,
                if a.named { "named" } else { "not named" },
                a.delta_bic,
                g
            )
        })
        .collect();
    // One verdict per effect: none accepted (named or in a group) and listed as not
    // identifiable; no advice to do what the plan already does.
    for n in &d.not_identifiable {
        let accepted = d.accepted.iter().any(|a| {
            a.effect == n.effect || a.ambiguity_group.iter().any(|g| g.effect == n.effect)
        });
        if accepted {
            return Err(format!("{} accepted and not identifiable", n.effect));
        }
    }
    let has_two_feeds = inputs
        .detections
        .iter()
        .map(|r| r.msg.feed_mm_min.round() as i64)
        .collect::<std::collections::BTreeSet<_>>()
        .len()
        >= 2;
    let advice = d
        .not_identifiable
        .iter()
        .map(|n| n.split_by.as_str())
        .chain(d.accepted.iter().map(|a| a.split_by.as_str()));
    for a in advice {
        if has_two_feeds && a.starts_with("probe at two feeds") {
            return Err(format!("advised \"{a}\" on a plan with two feeds"));
        }
    }
    match case.expect {
        Expect::NotIdentifiable => {
            let listed = d.not_identifiable.iter().find(|n| n.effect == case.effect);
            match listed {
                Some(n) if d.accepted.is_empty() => Ok(format!(
                    "not identifiable: {} ({})",
                    n.confounded_with, n.reason
                )),
                Some(_) => Err(format!("listed, but selected {named:?}")),
                None => Err(format!(
                    "not listed as not identifiable; selected {named:?}"
                )),
            }
        }
        Expect::Found => {
            let hit: Vec<&driftwatch_diagnosis::cycles::Accepted> = d
                .accepted
                .iter()
                .filter(|a| {
                    a.effect == case.effect
                        || a.ambiguity_group.iter().any(|m| m.effect == case.effect)
                })
                .collect();
            if hit.is_empty() {
                return Err(format!(
                    "not named; selected {named:?}; drivers {:?}; refused {:?}",
                    &d.drivers[..3],
                    d.refused
                ));
            }
            // No term without a cause: every accepted term is the injected effect's, or has it
            // in its group (a look-alike, or a term that coincides with it in time and was
            // kept on the held-out blocks).
            if hit.len() < d.accepted.len() {
                return Err(format!("terms unrelated to the injection: {named:?}"));
            }
            // What the thermal model can take over: terms on a location error driven by the
            // spindle or a logged temperature; measurement-model effects never.
            for h in &hit {
                let carried = h.model_input != ModelInput::None;
                let expected = match h.effect.as_str() {
                    "slow_mode" => true,
                    "ambient" => !h.term.contains("Fourier"),
                    "setter_drift" | "skip_latency" | "radius_speed" | "scale_expansion"
                    | "squareness" | "rotary_backlash" => false,
                    _ => carried,
                };
                if carried != expected {
                    return Err(format!("{}: model input {:?}", h.term, h.model_input));
                }
            }
            // The true footprint: the noise-free readings with and without the effect.
            let mut clean = scn.clone();
            clean.noise.sigma_um = 0.0;
            let with = deviations(&clean, &record(&clean, false));
            // (For the spindle log without the cycles' spins the effect is in the log, not in
            // the machine: only the fit against the noise-free readings is compared.)
            bare.noise.sigma_um = 0.0;
            let without = deviations(&bare, &record(&bare, false));
            let s = &d.series;
            let place_at = places_by_time(&scn, &inputs);
            let place: Vec<Place> = s.t_ns.iter().map(|t| place_at[t].clone()).collect();
            let truth_foot: Vec<f64> = (0..s.t_ns.len())
                .map(|i| {
                    let key = &place[i];
                    with[key] - without.get(key).copied().unwrap_or(with[key])
                })
                .collect();
            let fitted: Vec<f64> = (0..s.t_ns.len())
                .map(|i| {
                    s.footprints
                        .iter()
                        .zip(&d.accepted)
                        .filter(|(_, a)| hit.iter().any(|h| h.term == a.term))
                        .map(|(f, _)| f.1[i])
                        .sum()
                })
                .collect();
            // Held-out error against the noise-free readings.
            let idx: Vec<usize> = (0..s.t_ns.len()).filter(|i| s.heldout[*i]).collect();
            let err = |pred: &[f64]| -> f64 {
                let e: Vec<f64> = idx.iter().map(|&i| with[&place[i]] - pred[i]).collect();
                rms(&e)
            };
            let (before, after) = (err(&s.heldout_baseline_um), err(&s.heldout_final_um));
            let gain = 1.0 - after / before;
            let amp_ok = if case.strip_spins {
                true
            } else {
                // Compare what the data can tell: the parts beyond the baseline (what the
                // baseline shares with an effect it absorbs).
                let (a_true, a_fit) = (
                    rms(&s.beyond_baseline(&truth_foot)),
                    rms(&s.beyond_baseline(&fitted)),
                );
                (a_fit / a_true - 1.0).abs() <= 0.2
            };
            let (a_true, a_fit) = (rms(&truth_foot), rms(&fitted));
            let (b_true, b_fit) = (
                rms(&s.beyond_baseline(&truth_foot)),
                rms(&s.beyond_baseline(&fitted)),
            );
            let peak = truth_foot.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            let summary = format!(
                "named {named:?}; true peak {peak:.2} um; footprint rms true {a_true:.3} fitted {a_fit:.3} um, beyond the baseline {b_true:.3} / {b_fit:.3} um; held-out error vs noise-free {before:.3} -> {after:.3} um ({:.0} %); observed held-out rms {:.3} -> {:.3}",
                100.0 * gain,
                d.baseline.rms_heldout_um,
                d.final_fit.rms_heldout_um
            );
            if !amp_ok {
                return Err(format!("amplitude off: {summary}"));
            }
            if gain < 0.3 {
                return Err(format!("held-out gain under 30 %: {summary}"));
            }
            Ok(summary)
        }
    }
}

/// Recordings with nothing injected (seeds `from..from + 10`): the selections made.
fn null_selections(from: u64) -> Vec<String> {
    null_selections_on("table_bc", from, 10)
}

fn null_selections_on(machine: &str, from: u64, n: u64) -> Vec<String> {
    let mut out = Vec::new();
    for seed in from..from + n {
        let scn = three_days_on(machine, seed);
        let d = diagnose_inputs(&scn, &record(&scn, false));
        assert!(
            d.baseline.chi2_dof <= 1.2,
            "seed {seed}: {}",
            d.baseline.chi2_dof
        );
        // Three days: the held-out day is within what the training days showed.
        assert!(
            !d.baseline.heldout_extrapolates,
            "seed {seed}: {:?}",
            d.baseline
        );
        let periodic: Vec<f64> = d
            .unexplained
            .iter()
            .filter_map(|u| u.periodic.as_ref().map(|p| p.period_min))
            .collect();
        assert!(periodic.is_empty(), "seed {seed}: periodic {periodic:?}");
        // Judged over all its channels, a clean recording is flagged at 0.1 %.
        assert!(
            d.unexplained.is_empty(),
            "seed {seed}: flagged unexplained {:?}",
            d.unexplained
        );
        println!(
            "seed {seed}: baseline chi2/dof {:.3}, held-out {:.3} um, {} outliers listed of {} readings, selected {:?}",
            d.baseline.chi2_dof,
            d.baseline.rms_heldout_um,
            d.outliers.len(),
            d.readings + d.outliers.len(),
            d.accepted.iter().map(|a| &a.term).collect::<Vec<_>>()
        );
        out.extend(
            d.accepted
                .iter()
                .map(|a| format!("seed {seed}: {}", a.term)),
        );
    }
    out
}

// Forty clean recordings in four tests (they run in parallel); at most two selections in all
// is the acceptance bar, so each quarter may make at most two and the sum is checked by the
// command (`cargo test --release --test it diagnosis::clean -- --nocapture`).
#[test]
fn clean_recordings_select_nothing_1() {
    let s = null_selections(1000);
    assert!(s.len() <= 2, "{s:?}");
}
#[test]
fn clean_recordings_select_nothing_2() {
    let s = null_selections(1010);
    assert!(s.len() <= 2, "{s:?}");
}
#[test]
fn clean_recordings_select_nothing_3() {
    let s = null_selections(1020);
    assert!(s.len() <= 2, "{s:?}");
}
#[test]
fn clean_recordings_select_nothing_4() {
    let s = null_selections(1030);
    assert!(s.len() <= 2, "{s:?}");
}

#[test]
fn injected_concealed_effects_are_named_sized_and_improve_the_held_out_fit() {
    let mut failures = Vec::new();
    for (i, case) in cases().iter().enumerate() {
        match check(case, 100 + i as u64) {
            Ok(s) => println!("PASS {} ({}): {s}", case.effect, case.concealment),
            Err(e) => {
                println!("FAIL {} ({}): {e}", case.effect, case.concealment);
                failures.push(case.effect);
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// A clean recording as a plant's log has it: a cycle lost whole every so often, one aborted
/// halfway, and touches that did not trip and were retried a few seconds later. None of it
/// is an effect: nothing is accepted and nothing flagged unexplained.
#[test]
fn lost_aborted_and_retried_cycles_make_no_term_and_no_flag() {
    use driftwatch_core::recording::DetectionStatus;
    let scn = three_days(4000);
    let mut inputs = record(&scn, false);
    let cycles: Vec<i64> = {
        let mut c: Vec<i64> = inputs.detections.iter().map(|d| d.msg.cycle).collect();
        c.dedup();
        c
    };
    // Every 11th cycle lost; the 20th aborted after half its touches.
    let lost: Vec<i64> = cycles.iter().copied().skip(5).step_by(11).collect();
    let aborted = cycles[20];
    let in_aborted = inputs
        .detections
        .iter()
        .filter(|d| d.msg.cycle == aborted)
        .count();
    let mut seen_aborted = 0;
    let mut out = Vec::new();
    for (i, d) in inputs.detections.iter().enumerate() {
        if lost.contains(&d.msg.cycle) {
            continue;
        }
        if d.msg.cycle == aborted {
            seen_aborted += 1;
            if seen_aborted > in_aborted / 2 {
                continue;
            }
        }
        // Every 37th touch first misses (no trip) and is retried 3 s later.
        if i % 37 == 0 {
            let mut miss = d.clone();
            miss.msg.status = Some(DetectionStatus::NoTrip);
            out.push(miss);
            let mut retry = d.clone();
            retry.t_ns += 3_000_000_000;
            out.push(retry);
            continue;
        }
        out.push(d.clone());
    }
    assert!(out.len() < inputs.detections.len());
    inputs.detections = out;
    let d = diagnose_inputs(&scn, &inputs);
    let accepted: Vec<&str> = d.accepted.iter().map(|a| a.term.as_str()).collect();
    assert!(accepted.is_empty(), "{accepted:?}");
    assert!(d.unexplained.is_empty(), "{:?}", d.unexplained);
    assert!(
        d.cycles < cycles.len() - lost.len() + 1,
        "{} cycles",
        d.cycles
    );
}

/// The advice is checked by doing it: for each effect the plan cannot identify and whose
/// advice is a change the plan's own readings can show (two feeds, two spindle speeds), the
/// same truth and seed with that change made is diagnosed again, and the effect is then
/// accepted and named, and the new plan shows the feature the advice asked for.
#[test]
fn the_advice_to_split_an_effect_names_it_once_followed() {
    use driftwatch_diagnosis::effects::{PlanFeature, effect};
    let follow = |f: PlanFeature| -> Option<fn(&mut Scenario)> {
        match f {
            PlanFeature::TwoFeeds => Some(raise_feed),
            PlanFeature::TwoSpeeds => Some(alternate_speed_wide),
            _ => None,
        }
    };
    let mut checked = 0;
    for (i, case) in cases().iter().enumerate() {
        if !matches!(case.expect, Expect::NotIdentifiable) {
            continue;
        }
        let Some(e) = effect(case.effect) else {
            continue;
        };
        let Some((feature, change)) = e.splits.iter().find_map(|f| Some((*f, follow(*f)?))) else {
            continue;
        };
        let seed = 100 + i as u64;
        let mut scn = three_days(seed);
        (case.setup)(&mut scn);
        (case.inject)(&mut scn);
        let d = diagnose_inputs(&scn, &record(&scn, false));
        let listed = d.not_identifiable.iter().find(|n| n.effect == case.effect);
        assert_eq!(
            listed.map(|n| n.split_by.as_str()),
            Some(e.split_by),
            "{}: {:?}",
            case.effect,
            d.not_identifiable
        );
        change(&mut scn);
        let inputs = record(&scn, false);
        let d = diagnose_inputs(&scn, &inputs);
        let k = Kinematics::load(&scn.machine).unwrap();
        let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
        assert!(feature.shown_by(&rows).is_some(), "{feature:?}");
        let named: Vec<(&str, bool)> = d
            .accepted
            .iter()
            .map(|a| (a.effect.as_str(), a.named))
            .collect();
        println!("{} after the advice ({feature:?}): {named:?}", case.effect);
        assert!(
            named.contains(&(case.effect, true)),
            "{}: the advice followed, still {named:?}; not identifiable {:?}",
            case.effect,
            d.not_identifiable
        );
        checked += 1;
    }
    assert!(checked >= 3, "{checked}");
}

/// The diagnosis on every other machine family: its effect library and signatures come from
/// the exact trip model of the machine at hand, so the same concealed effects are found, and a
/// clean recording selects nothing.
#[test]
fn the_diagnosis_works_on_every_machine_family() {
    // table_bc's concealed setter drift as it is, and its ambient case on each family's own
    // second tilt error.
    let setter = cases()
        .into_iter()
        .find(|c| c.effect == "setter_drift" && c.concealment.starts_with("a:"))
        .expect("the setter drift case");
    let cases = [
        setter,
        Case {
            effect: "ambient",
            concealment: "a: the tilting axis' second error 0.33 um/K over +-1.5 K, under 0.5 um",
            setup: swing,
            inject: |s| {
                let k = Kinematics::load(&s.machine).unwrap();
                s.truth.channels.insert(
                    k.identify_names()[1].clone(),
                    channel("spindle = [{ gain = 48.0, tau_min = 120.0 }]\nambient = [{ gain = 0.33, tau_min = 60.0 }]"),
                );
            },
            strip_spins: false,
            expect: Expect::Found,
        },
    ];
    let mut failures = Vec::new();
    let mut nulls = Vec::new();
    for (f, m) in [
        "head_b_table_c",
        "table_d45_c",
        "head_d45_table_c",
        "trunnion_ac",
    ]
    .into_iter()
    .enumerate()
    {
        for (i, case) in cases.iter().enumerate() {
            match check_on(m, case, 300 + 10 * f as u64 + i as u64) {
                Ok(s) => println!("PASS {m} {} ({}): {s}", case.effect, case.concealment),
                Err(e) => {
                    println!("FAIL {m} {} ({}): {e}", case.effect, case.concealment);
                    failures.push(format!("{m} {}", case.effect));
                }
            }
        }
        nulls.extend(null_selections_on(m, 2000 + 10 * f as u64, 2));
    }
    // Eight clean recordings: at most one false selection, the table_bc bar of 2 in 40 at this
    // size (twenty per family in release: 1 in 80, `clean_recordings_of_every_family...`).
    if nulls.len() > 1 {
        failures.push(format!("clean recordings selected {nulls:?}"));
    }
    assert!(failures.is_empty(), "{failures:?}");
}

// ---------------------------------------------------------------------------------------
// Robust screening: the false-outlier share on clean recordings, and early trips found.

/// The readings that are outliers by construction: where the recording differs from the same
/// scenario without outliers and without noise by more than 3 um (6 sigma; an outlier is 5 um
/// or more).
fn injected_outliers(scn: &Scenario, inputs: &Inputs) -> Vec<Place> {
    let mut clean = scn.clone();
    clean.noise.sigma_um = 0.0;
    clean.noise.outlier_rate = 0.0;
    let truth = deviations(&clean, &record(&clean, false));
    deviations(scn, inputs)
        .into_iter()
        .filter(|(k, v)| (v - truth[k]).abs() > 3.0)
        .map(|(k, _)| k)
        .collect()
}

/// Listed outliers on clean recordings (seeds `from..from + 10`) and with 2 % of readings
/// tripping 5-30 um early: `(readings, listed)` clean, `(injected, found, falsely listed)`.
fn screening(from: u64) -> ((usize, usize), (usize, usize, usize)) {
    let (mut readings, mut listed) = (0, 0);
    let (mut injected, mut found, mut false_listed) = (0, 0, 0);
    let mut at = [0usize; 2];
    for seed in from..from + 10 {
        let scn = three_days(seed);
        let inputs = record(&scn, false);
        let d = diagnose_inputs(&scn, &inputs);
        readings += d.readings + d.outliers.len();
        listed += d.outliers.len();
        // The calibration below the threshold: the shares beyond 3 and 4 sigma.
        let k = Kinematics::load(&scn.machine).unwrap();
        let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
        let model = DiagnoseOptions::new(0.5).model;
        for (a, ks) in at.iter_mut().zip([3.0, 4.0]) {
            *a += screen_outliers(&rows, &inputs.spindle, &model, 0.5, ks).len();
        }
        let mut scn = three_days(seed);
        scn.noise.outlier_rate = 0.02;
        scn.noise.outlier_um = [5.0, 30.0];
        scn.noise.outlier_sense = driftwatch_sim::scenario::OutlierSense::Early;
        let inputs = record(&scn, false);
        let truth = injected_outliers(&scn, &inputs);
        let d = diagnose_inputs(&scn, &inputs);
        // A listed outlier's place, found by its time among the recording's readings.
        let place_at = places_by_time(&scn, &inputs);
        let listed_keys: Vec<Place> = d
            .outliers
            .iter()
            .map(|o| place_at[&o.t_ns].clone())
            .collect();
        let hit = truth.iter().filter(|k| listed_keys.contains(k)).count();
        let wrong = listed_keys.iter().filter(|k| !truth.contains(k)).count();
        println!(
            "seed {seed}: clean {} listed; early trips: {} injected, {hit} found, {wrong} falsely listed; selected {:?}",
            listed,
            truth.len(),
            d.accepted.iter().map(|a| &a.term).collect::<Vec<_>>()
        );
        assert!(
            d.accepted.is_empty(),
            "seed {seed}: the outliers made a selection"
        );
        injected += truth.len();
        found += hit;
        false_listed += wrong;
    }
    let expect = |k: f64| 2.0 * normal_tail(k) * readings as f64;
    println!(
        "clean, beyond 3 sigma: {} (Gaussian {:.1}); beyond 4 sigma: {} (Gaussian {:.2})",
        at[0],
        expect(3.0),
        at[1],
        expect(4.0)
    );
    // Calibrated: the share beyond 3 sigma within 4 binomial sigma of the Gaussian's.
    let e3 = expect(3.0);
    assert!(
        (at[0] as f64 - e3).abs() < 4.0 * e3.sqrt(),
        "{} beyond 3 sigma against {e3:.1}",
        at[0]
    );
    ((readings, listed), (injected, found, false_listed))
}

/// `P(Z > k)` of a standard normal (Abramowitz-Stegun 26.2.17, error under 1e-7).
fn normal_tail(k: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.2316419 * k);
    let poly = t
        * (0.319381530
            + t * (-0.356563782 + t * (1.781477937 + t * (-1.821255978 + t * 1.330274429))));
    (-k * k / 2.0).exp() / (2.0 * std::f64::consts::PI).sqrt() * poly
}

#[test]
fn robust_screening_lists_the_early_trips_and_no_good_reading() {
    let ((readings, listed), (injected, found, false_listed)) = screening(3000);
    // At 5 sigma of a leave-one-out residual the expected false share is 2 Phi(-5) = 5.7e-7:
    // under 0.03 over these readings.
    println!(
        "clean: {listed} listed of {readings} readings (share {:.1e}, expected 5.7e-7); 2 % early trips of 5-30 um: {found} of {injected} found, {false_listed} good readings listed",
        listed as f64 / readings as f64
    );
    assert!(listed <= 1, "{listed} of {readings}");
    assert_eq!(found, injected);
    assert!(false_listed <= 1, "{false_listed}");
}

// ---------------------------------------------------------------------------------------
// Confounded physics: each case named, in the right ambiguity group or unexplained, never a
// confident wrong label.

enum Honest {
    /// An accepted term of one of these effects, named or not (then with its group), or one
    /// of them explaining an accepted term comparably (in its group); or listed as not
    /// identifiable with nothing accepted.
    Effect(&'static [&'static str]),
    /// A periodic residual reported as unexplained, at this period or an alias of it.
    UnexplainedPeriodic(f64),
}

struct Confounded {
    name: &'static str,
    setup: fn(&mut Scenario),
    strip_spins: bool,
    expect: Honest,
}

fn confounded_cases() -> Vec<Confounded> {
    vec![
        Confounded {
            name: "skip latency step at one feed (+2.4 ms from day 2, 10:00)",
            setup: |s| {
                s.skip.changes = vec![driftwatch_sim::scenario::LatencyChange {
                    at_min: 1440.0 + 240.0,
                    latency_ms: 2.4,
                }];
            },
            strip_spins: false,
            expect: Honest::Effect(&["skip_latency"]),
        },
        Confounded {
            name: "near-isotropic scale expansion (kx 6, ky 5.5 ppm/K, +-1.5 K)",
            setup: |s| {
                swing(s);
                s.truth.channels.insert(
                    "kx".into(),
                    channel("ambient = [{ gain = 6.0, tau_min = 120.0 }]"),
                );
                s.truth.channels.insert(
                    "ky".into(),
                    channel("ambient = [{ gain = 5.5, tau_min = 120.0 }]"),
                );
            },
            strip_spins: false,
            expect: Honest::Effect(&["scale_expansion"]),
        },
        Confounded {
            name: "C indexing error (200 urad first harmonic, 100 urad second)",
            setup: |s| {
                s.rotary.index_urad = vec![vec![], vec![[1.0, 200.0, 0.0], [2.0, 0.0, 100.0]]];
            },
            strip_spins: false,
            expect: Honest::Effect(&["c_indexing"]),
        },
        Confounded {
            name: "20-min periodic tool-tip disturbance (sz, 1 um), outside the library",
            setup: |s| {
                s.truth.periodic = vec![driftwatch_sim::scenario::PeriodicTerm {
                    channel: "sz".into(),
                    amplitude: 1.0,
                    period_min: 20.0,
                    phase_deg: 0.0,
                }];
            },
            strip_spins: false,
            expect: Honest::UnexplainedPeriodic(20.0),
        },
        Confounded {
            name: "measurement spins missing from the spindle log",
            setup: nothing,
            strip_spins: true,
            expect: Honest::Effect(&["measurement_heating"]),
        },
    ]
}

/// The outcome of one case: `Ok(summary)` when honest, `Err(summary)` when not.
fn honest(case: &Confounded, seed: u64) -> Result<String, String> {
    let mut scn = three_days(seed);
    (case.setup)(&mut scn);
    let d = diagnose_inputs(&scn, &record(&scn, case.strip_spins));
    let terms: Vec<String> = d
        .accepted
        .iter()
        .map(|a| {
            let mut g: Vec<&str> = a
                .ambiguity_group
                .iter()
                .filter(|m| m.comparable)
                .map(|m| m.effect.as_str())
                .collect();
            g.dedup();
            format!(
                "{} {} [{}]{}",
                a.effect,
                a.term,
                if a.named { "named" } else { "not named" },
                if g.is_empty() {
                    String::new()
                } else {
                    format!(" group {g:?}")
                }
            )
        })
        .collect();
    let periodic: Vec<String> = d
        .unexplained
        .iter()
        .filter_map(|u| u.periodic.as_ref())
        .map(|p| {
            format!(
                "unexplained periodic {:.1} min (aliases {:?}), {:.2} um RMS",
                p.period_min, p.aliases_min, p.amplitude_rms_um
            )
        })
        .collect();
    let ni: Vec<&str> = d
        .not_identifiable
        .iter()
        .map(|n| n.effect.as_str())
        .collect();
    let summary = format!("accepted {terms:?}; {periodic:?}; not identifiable {ni:?}");
    let (wrong, right) = match case.expect {
        Honest::Effect(ok) => {
            let wrong = d
                .accepted
                .iter()
                .any(|a| a.named && !ok.contains(&a.effect.as_str()));
            // The effect accepted, or an alternative that explains the data comparably.
            let right = d.accepted.iter().any(|a| {
                ok.contains(&a.effect.as_str())
                    || a.ambiguity_group
                        .iter()
                        .any(|m| m.comparable && ok.contains(&m.effect.as_str()))
            }) || (d.accepted.is_empty() && ok.iter().any(|e| ni.contains(e)));
            (wrong, right)
        }
        Honest::UnexplainedPeriodic(period) => {
            let wrong = d.accepted.iter().any(|a| a.named);
            let right = d
                .unexplained
                .iter()
                .filter_map(|u| u.periodic.as_ref())
                .any(|p| {
                    // The cadence aliases a period: any of the reported ones near the truth's
                    // or one of its aliases at a 30-min cadence.
                    let f0 = 1.0 / period;
                    let fs = 1.0 / 30.0;
                    std::iter::once(p.period_min)
                        .chain(p.aliases_min.iter().copied())
                        .any(|q| {
                            let f = 1.0 / q;
                            (-3..=3).any(|k| {
                                let a = (f0 + f64::from(k) * fs).abs();
                                (f - a).abs() < 0.02 * a
                            })
                        })
                });
            (wrong, right)
        }
    };
    if wrong || !right {
        Err(summary)
    } else {
        Ok(summary)
    }
}

#[test]
fn confounded_physics_is_named_grouped_or_unexplained_never_wrongly_named() {
    let mut failures = Vec::new();
    for (i, case) in confounded_cases().iter().enumerate() {
        for seed in [200 + 2 * i as u64, 201 + 2 * i as u64] {
            match honest(case, seed) {
                Ok(s) => println!("PASS {} (seed {seed}): {s}", case.name),
                Err(s) => {
                    println!("FAIL {} (seed {seed}): {s}", case.name);
                    failures.push(format!("{} seed {seed}", case.name));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// One confounded case in detail (`CASE=i SEED=s cargo test --release --test it
/// diagnosis::debug_confounded -- --ignored --nocapture`): every group member with its reason.
#[test]
#[ignore]
fn debug_confounded() {
    let i: usize = std::env::var("CASE").unwrap().parse().unwrap();
    let seed: u64 = std::env::var("SEED").unwrap().parse().unwrap();
    let case = &confounded_cases()[i];
    let mut scn = three_days(seed);
    (case.setup)(&mut scn);
    let inputs = record(&scn, case.strip_spins);
    let k = Kinematics::load(&scn.machine).unwrap();
    let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
    println!("params {:?} locations {:?}", rows.params, rows.locations);
    let d = diagnose_inputs(&scn, &inputs);
    for a in &d.accepted {
        println!(
            "{} {} named {} dbic {:.0} t {:.1}",
            a.effect, a.term, a.named, a.delta_bic, a.t
        );
        for g in &a.ambiguity_group {
            println!(
                "   {} {} comparable {}: {}",
                g.effect, g.term, g.comparable, g.reason
            );
        }
    }
    for r in &d.refused {
        println!(
            "refused {} {} dbic {:.1} t {:.1}: {}",
            r.effect, r.term, r.delta_bic, r.t, r.reason
        );
    }
    println!("drivers {:?}", d.drivers);
}

/// One injected case over a few seeds (`CASE=measurement_heating SEEDS=119,120 cargo test
/// --test it diagnosis::debug_injected -- --ignored --nocapture`), with every accepted term's
/// group.
#[test]
#[ignore]
fn debug_injected() {
    let name = std::env::var("CASE").unwrap_or_else(|_| "measurement_heating".into());
    let seeds: Vec<u64> = std::env::var("SEEDS")
        .unwrap_or_else(|_| "119".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    for case in cases().iter().filter(|c| c.effect == name) {
        for &seed in &seeds {
            println!("seed {seed}: {:?}", check(case, seed));
            let mut scn = three_days(seed);
            (case.setup)(&mut scn);
            (case.inject)(&mut scn);
            let d = diagnose_inputs(&scn, &record(&scn, case.strip_spins));
            println!("  {} outliers listed", d.outliers.len());
            for a in &d.accepted {
                println!(
                    "  {} {} named {} dbic {:.0} held-out {:.3} -> {:.3} ({} of {} blocks)",
                    a.effect,
                    a.term,
                    a.named,
                    a.delta_bic,
                    a.heldout_rms_before_um,
                    a.heldout_rms_after_um,
                    a.blocks_improved,
                    a.blocks
                );
                for g in &a.ambiguity_group {
                    println!(
                        "     {} {} comparable {}: {}",
                        g.effect, g.term, g.comparable, g.reason
                    );
                }
            }
        }
    }
}

/// Twenty clean recordings per family (80 diagnoses: slow in a debug build, so not in the
/// default run): the false-selection rate of each family against the bar of the table_bc
/// nulls (at most 2 in 40). Run with
/// `cargo test --release --test it diagnosis::clean_recordings_of_every_family -- --ignored --nocapture`.
#[test]
#[ignore = "80 diagnoses: run in release with --ignored"]
fn clean_recordings_of_every_family_select_at_most_one_in_twenty() {
    let mut over = Vec::new();
    for (f, m) in [
        "head_b_table_c",
        "table_d45_c",
        "head_d45_table_c",
        "trunnion_ac",
    ]
    .into_iter()
    .enumerate()
    {
        let null = null_selections_on(m, 5000 + 100 * f as u64, 20);
        println!("{m}: {} selections in 20: {null:?}", null.len());
        if null.len() > 1 {
            over.push(format!("{m}: {null:?}"));
        }
    }
    assert!(over.is_empty(), "{over:?}");
}

/// A round trip: a static X-Z squareness in the virtual machine is blamed on
/// `squareness` by the diagnosis of its setter cycles, measured independently by the laser
/// step diagonal (the seed's set-up, mirror tilts and all), the two agree within their
/// uncertainties, and once the measured geometry is the machine's the diagnosis of the same
/// recording no longer finds it.
#[test]
fn a_squareness_is_blamed_measured_by_the_step_diagonal_and_gone_once_loaded() {
    use driftwatch_core::linear_axes::LinearGeometry;
    use driftwatch_linear::axis_errors::AxisErrors;
    use driftwatch_linear::step_diagonal::{Setup, robust, simulate};
    use rand::SeedableRng;
    const SXZ_URAD: f64 = 40.0;
    let mut scn = three_days(19);
    scn.truth
        .channels
        .insert("sxz".into(), channel(&format!("offset = {SXZ_URAD}")));
    let inputs = record(&scn, false);
    let k = Kinematics::load(&scn.machine).unwrap();
    let run = |k: &Kinematics| {
        let rows = detection_rows(k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
        diagnose(
            &rows,
            &inputs.spindle,
            &inputs.temperatures,
            &DiagnoseOptions::new(0.5),
        )
        .unwrap()
    };
    let sxz_terms = |d: &Diagnosis| -> Vec<(String, f64, f64)> {
        d.accepted
            .iter()
            .filter(|a| a.effect == "squareness" && a.term.contains("sxz"))
            .flat_map(|a| {
                a.parameters
                    .iter()
                    .map(|p| (a.term.clone(), p.value, p.sigma))
            })
            .collect()
    };
    let before = run(&k);
    let blamed = sxz_terms(&before);
    println!("diagnosis before: {blamed:?}");
    let constant = blamed
        .iter()
        .find(|(t, _, _)| t.contains("constant"))
        .unwrap_or_else(|| {
            panic!(
                "no constant sxz term; accepted {:?}",
                before.accepted.iter().map(|a| &a.term).collect::<Vec<_>>()
            )
        });
    // The step diagonal on the same truth (its linear errors), the seed's set-up.
    let truth = driftwatch_core::kinematics::LinearErrors {
        sxz: SXZ_URAD * 1e-6,
        ..Default::default()
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(19);
    let setup = Setup::seed(150.0, &mut rng);
    let (runs, pos) = simulate(&AxisErrors::from_linear(&truth, 120.0), &setup, &mut rng);
    let measured = robust(&runs, &pos, &setup).unwrap();
    let (m, ms) = (
        measured.squareness_urad[1],
        measured.squareness_sigma_urad[1],
    );
    println!(
        "step diagonal: sxz {m:.2} +- {ms:.2} urad; diagnosis {:.2} +- {:.2} urad; truth {SXZ_URAD}",
        constant.1, constant.2
    );
    assert!(
        (m - SXZ_URAD).abs() < 3.0 * ms,
        "step diagonal off the truth"
    );
    let combined = ms.hypot(constant.2);
    assert!(
        (m - constant.1).abs() < 3.0 * combined,
        "the two disagree: {m} vs {}",
        constant.1
    );
    // The measured geometry becomes the machine's: the same recording, diagnosed again.
    let g = LinearGeometry::of(&measured.linear_errors(120.0));
    let loaded = k.clone().with_geometry(&g, "step diagonal (test)").unwrap();
    let after = run(&loaded);
    println!("diagnosis after: {:?}", sxz_terms(&after));
    assert!(
        sxz_terms(&after).is_empty(),
        "still blamed after the geometry was loaded"
    );
}

/// One effect of the power curve: the plan that shows it, the candidate term whose threshold
/// the diagnosis states, and the injection at an amplitude in that term's unit (the simulator's
/// parameter in the same unit and, for lags, at the same lag as the candidate).
struct PowerCase {
    effect: &'static str,
    term: &'static str,
    setup: fn(&mut Scenario),
    inject: fn(&mut Scenario, f64),
}

fn put(s: &mut Scenario, name: &str, toml_text: String) {
    s.truth.channels.insert(name.into(), channel(&toml_text));
}

fn power_cases() -> Vec<PowerCase> {
    vec![
        PowerCase {
            effect: "setter_drift",
            term: "setter_z x ambient lag 60 min",
            setup: swing,
            inject: |s, a| {
                put(
                    s,
                    "setter_z",
                    format!("ambient = [{{ gain = {a}, tau_min = 60.0 }}]"),
                )
            },
        },
        PowerCase {
            effect: "ambient",
            term: "EZ0B x ambient lag 60 min",
            setup: swing,
            inject: |s, a| {
                put(
                    s,
                    "EZ0B",
                    format!(
                        "spindle = [{{ gain = 48.0, tau_min = 120.0 }}]\nambient = [{{ gain = {a}, tau_min = 60.0 }}]"
                    ),
                )
            },
        },
        PowerCase {
            effect: "skip_latency",
            term: "latency x feed",
            setup: raise_feed,
            inject: |s, a| s.skip.latency_ms = a,
        },
        PowerCase {
            effect: "radius_speed",
            term: "radius x (n/n_ref)^2",
            setup: alternate_speed,
            inject: |s, a| put(s, "radius", format!("instant = {a}")),
        },
        PowerCase {
            effect: "speed_shift",
            term: "sz x (n/n_ref)^2",
            setup: alternate_speed_wide,
            inject: |s, a| {
                put(
                    s,
                    "sz",
                    format!("instant = {a}\nspindle = [{{ gain = -41.0, tau_min = 11.0 }}]"),
                )
            },
        },
        PowerCase {
            effect: "scale_expansion",
            term: "kx x ambient lag 120 min",
            setup: swing,
            inject: |s, a| {
                put(
                    s,
                    "kx",
                    format!("ambient = [{{ gain = {a}, tau_min = 120.0 }}]"),
                )
            },
        },
        PowerCase {
            effect: "squareness",
            term: "sxz x ambient lag 120 min",
            setup: swing,
            inject: |s, a| {
                put(
                    s,
                    "sxz",
                    format!("ambient = [{{ gain = {a}, tau_min = 120.0 }}]"),
                )
            },
        },
        PowerCase {
            effect: "rotary_backlash",
            // The term is half the backlash: each sense is off by half of it.
            term: "angle_B x B approach sense",
            setup: nothing,
            inject: |s, a| s.rotary.backlash_urad = vec![2.0 * a],
        },
        PowerCase {
            effect: "slow_mode",
            term: "EZ0B x spindle lag 1200 min",
            setup: nothing,
            inject: |s, a| {
                put(
                    s,
                    "EZ0B",
                    format!(
                        "spindle = [{{ gain = 48.0, tau_min = 120.0 }}, {{ gain = {a}, tau_min = 1200.0 }}]"
                    ),
                )
            },
        },
    ]
}

/// The power case of `effect`.
fn power_case(effect: &str) -> PowerCase {
    power_cases()
        .into_iter()
        .find(|c| c.effect == effect)
        .unwrap_or_else(|| panic!("no power case for {effect}"))
}

/// The detection threshold the diagnosis states for `term` on the clean recording `scn`.
fn stated_threshold(scn: &Scenario, term: &str) -> f64 {
    diagnose_inputs(scn, &record(scn, false))
        .thresholds
        .iter()
        .find(|t| t.term == term)
        .unwrap_or_else(|| panic!("no threshold for {term}"))
        .amplitude
}

/// [`stated_threshold`] of a case's term on a clean recording of its plan (seed 5000).
fn case_threshold(case: &PowerCase) -> f64 {
    let mut scn = three_days(5000);
    (case.setup)(&mut scn);
    stated_threshold(&scn, case.term)
}

/// What one injected recording gave: the effect accepted (named or in a group), accepted and
/// named, the number of accepted terms unrelated to it, and of terms named as another effect
/// (a confident wrong label).
#[derive(Default, Clone, Copy)]
struct Power {
    found: usize,
    named: usize,
    unrelated: usize,
    wrong: usize,
    runs: usize,
}

/// The power curve (physics 4.3): each effect injected at 0.5, 1, 2, 4 and 8 times the
/// threshold the diagnosis states for its candidate term on that plan (read from a clean
/// recording of the same plan), over `POWER_SEEDS` seeds (default 12), on each case's plan or
/// on `POWER_PLAN` (a built-in name or a path) where given. Run with
/// `cargo test --release --test it diagnosis::power_curve -- --ignored --nocapture`.
#[test]
#[ignore = "about 550 diagnoses: run in release with --ignored"]
fn power_curve_at_half_one_and_two_thresholds() {
    let n: u64 = std::env::var("POWER_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(12);
    let factors = [0.5, 1.0, 2.0, 4.0, 8.0];
    let plan = std::env::var("POWER_PLAN").ok();
    let on_plan = |scn: &mut Scenario| {
        if let Some(p) = &plan {
            scn.plan = p.clone();
        }
    };
    let cases = power_cases();
    // The stated threshold of each case's term, from a clean recording of its plan.
    let thresholds: Vec<f64> = cases
        .iter()
        .map(|c| {
            let mut scn = three_days(5000);
            (c.setup)(&mut scn);
            on_plan(&mut scn);
            stated_threshold(&scn, c.term)
        })
        .collect();
    let jobs: Vec<(usize, usize, u64)> = (0..cases.len())
        .flat_map(|c| (0..factors.len()).flat_map(move |f| (0..n).map(move |s| (c, f, s))))
        .collect();
    let run = |&(c, f, s): &(usize, usize, u64)| -> Power {
        let case = &cases[c];
        let mut scn = three_days(5100 + s);
        (case.setup)(&mut scn);
        on_plan(&mut scn);
        (case.inject)(&mut scn, factors[f] * thresholds[c]);
        let d = diagnose_inputs(&scn, &record(&scn, false));
        let of_it = |a: &driftwatch_diagnosis::cycles::Accepted| {
            a.effect == case.effect || a.ambiguity_group.iter().any(|m| m.effect == case.effect)
        };
        let found = d.accepted.iter().filter(|a| of_it(a)).count();
        Power {
            found: usize::from(found > 0),
            named: usize::from(
                d.accepted
                    .iter()
                    .any(|a| a.named && a.effect == case.effect),
            ),
            unrelated: d.accepted.len() - found,
            wrong: d
                .accepted
                .iter()
                .filter(|a| a.named && a.effect != case.effect)
                .count(),
            runs: 1,
        }
    };
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get());
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results: Vec<(usize, Power)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..workers)
            .map(|_| {
                scope.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(job) = jobs.get(i) else { break };
                        out.push((i, run(job)));
                    }
                    out
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap())
            .collect()
    });
    let mut table = vec![[Power::default(); 5]; cases.len()];
    for (i, p) in results {
        let (c, f, _) = jobs[i];
        let t = &mut table[c][f];
        t.found += p.found;
        t.named += p.named;
        t.unrelated += p.unrelated;
        t.wrong += p.wrong;
        t.runs += p.runs;
    }
    println!(
        "| effect | term | threshold | found (named) at 0.5x | 1x | 2x | 4x | 8x | unrelated terms | named as another effect |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut weak = Vec::new();
    for (c, case) in cases.iter().enumerate() {
        let cell = |p: &Power| format!("{}/{} ({})", p.found, p.runs, p.named);
        let unrelated: usize = table[c].iter().map(|p| p.unrelated).sum();
        let wrong: usize = table[c].iter().map(|p| p.wrong).sum();
        let cells: Vec<String> = table[c].iter().map(cell).collect();
        println!(
            "| {} | {} | {:.4} | {} | {unrelated} | {wrong} |",
            case.effect,
            case.term,
            thresholds[c],
            cells.join(" | ")
        );
        // Twice the threshold is found on most seeds, power does not fall with amplitude, and
        // no term is named as an effect that was not injected.
        let [half, one, two, four, eight] = table[c];
        if 2 * two.found < two.runs
            || half.found > two.found
            || one.found > two.found
            || four.found < two.found
            || eight.found < two.found
            || wrong > 0
        {
            weak.push(case.effect);
        }
    }
    // For each effect not always named at twice the threshold: its group on the first seed
    // where it was found unnamed, with each member's cosine and the plan change that splits it.
    for (c, case) in cases.iter().enumerate() {
        if table[c][2].named == table[c][2].runs {
            continue;
        }
        for s in 0..n {
            let mut scn = three_days(5100 + s);
            (case.setup)(&mut scn);
            on_plan(&mut scn);
            (case.inject)(&mut scn, 2.0 * thresholds[c]);
            let d = diagnose_inputs(&scn, &record(&scn, false));
            let Some(a) = d.accepted.iter().find(|a| {
                !a.named
                    && (a.effect == case.effect
                        || a.ambiguity_group.iter().any(|m| m.effect == case.effect))
            }) else {
                continue;
            };
            let members: Vec<String> = a
                .ambiguity_group
                .iter()
                .map(|m| {
                    let mark = if m.comparable { ", comparable" } else { "" };
                    format!("{}: {} (cos {:.3}{mark})", m.effect, m.term, m.cos)
                })
                .collect();
            println!(
                "{} at 2x, seed {}: accepted {}: {}; group [{}]; split by: {}",
                case.effect,
                5100 + s,
                a.effect,
                a.term,
                members.join("; "),
                a.split_by
            );
            break;
        }
    }
    assert!(weak.is_empty(), "{weak:?}");
}

/// Two effects at once, each at twice the threshold the diagnosis states for it on the plan
/// that shows both (from a clean recording of that plan): both are accepted (named, or in a
/// group), and nothing else is. The pairs join effects of different drivers (feed, speed,
/// approach sense, the hall, the spindle's slow heat).
#[test]
fn two_effects_at_once_are_both_found_and_nothing_else() {
    let cases = power_cases();
    let by = |e: &str| cases.iter().position(|c| c.effect == e).unwrap();
    let pairs = [
        (by("skip_latency"), by("squareness")),
        (by("radius_speed"), by("setter_drift")),
        (by("speed_shift"), by("scale_expansion")),
        (by("rotary_backlash"), by("ambient")),
        (by("slow_mode"), by("skip_latency")),
    ];
    // More seeds for the closing note's figure: `PAIR_SEEDS=10 cargo test --release --test it
    // diagnosis::two_effects -- --nocapture`.
    let seeds: u64 = std::env::var("PAIR_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let mut failures = Vec::new();
    for (p, &(a, b)) in pairs.iter().enumerate() {
        for s in 0..seeds {
            let (ca, cb) = (&cases[a], &cases[b]);
            let plan = |seed: u64| {
                let mut scn = three_days(seed);
                (ca.setup)(&mut scn);
                (cb.setup)(&mut scn);
                scn
            };
            let clean = plan(6000 + p as u64 + 10 * s);
            let (ta, tb) = (
                stated_threshold(&clean, ca.term),
                stated_threshold(&clean, cb.term),
            );
            let mut scn = plan(6100 + p as u64 + 10 * s);
            (ca.inject)(&mut scn, 2.0 * ta);
            (cb.inject)(&mut scn, 2.0 * tb);
            let d = diagnose_inputs(&scn, &record(&scn, false));
            let of = |e: &str, x: &driftwatch_diagnosis::cycles::Accepted| {
                x.effect == e || x.ambiguity_group.iter().any(|m| m.effect == e)
            };
            let terms: Vec<String> = d
                .accepted
                .iter()
                .map(|x| format!("{} {} (named {})", x.effect, x.term, x.named))
                .collect();
            let found_a = d.accepted.iter().any(|x| of(ca.effect, x));
            let found_b = d.accepted.iter().any(|x| of(cb.effect, x));
            let unrelated = d
                .accepted
                .iter()
                .filter(|x| !of(ca.effect, x) && !of(cb.effect, x))
                .count();
            println!(
                "{} ({ta:.4}) + {} ({tb:.4}) at 2x: {terms:?}",
                ca.effect, cb.effect
            );
            if !found_a || !found_b || unrelated > 0 {
                failures.push(format!("{} + {}: {terms:?}", ca.effect, cb.effect));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// A term the diagnosis does not name states the amplitude at which it would be: B backlash
/// at twice its threshold sits in a group with a static XZ squareness (cos about 0.98); the
/// factor the diagnosis states is checked by injecting 0.6 and 1.5 times that amplitude on the
/// same seeds: not named below it, named above it.
#[test]
fn a_term_not_named_is_named_at_the_amplitude_it_states() {
    let case = &power_case("rotary_backlash");
    let threshold = case_threshold(case);
    let named_at = |seed: u64, amplitude: f64| {
        let mut scn = three_days(seed);
        (case.setup)(&mut scn);
        (case.inject)(&mut scn, amplitude);
        let d = diagnose_inputs(&scn, &record(&scn, false));
        let a = d
            .accepted
            .iter()
            .find(|a| a.effect == case.effect)
            .unwrap_or_else(|| panic!("seed {seed}: not accepted: {:?}", d.accepted));
        (a.named, a.named_at, a.statement.clone())
    };
    let (mut below, mut above) = (0, 0);
    for seed in 5100..5103 {
        let amplitude = 2.0 * threshold;
        let (named, f, statement) = named_at(seed, amplitude);
        assert!(!named, "seed {seed}: named at twice the threshold");
        let f = f.unwrap_or_else(|| panic!("seed {seed}: no factor: {statement}"));
        assert!(f > 1.05, "seed {seed}: {f}");
        assert!(statement.contains("would be named at about"), "{statement}");
        below += usize::from(!named_at(seed, 0.6 * f * amplitude).0);
        above += usize::from(named_at(seed, 1.5 * f * amplitude).0);
        println!("seed {seed}: named at {f:.2} x; {statement}");
    }
    assert!(below >= 2 && above >= 2, "below {below}/3, above {above}/3");
}

/// A squareness that follows the hall has a static part the baseline does not hold, while a
/// location error following the hall gets its static part free from the baseline: judged
/// against the squareness without its static part, EX0B was named on this seed at five times
/// the squareness threshold. With the static part beside it, the squareness is a fair rival and
/// nothing is named as an effect that was not injected.
#[test]
fn a_squareness_following_the_hall_is_not_named_as_a_location_error() {
    let case = &power_case("squareness");
    let threshold = case_threshold(case);
    let mut scn = three_days(5101);
    (case.setup)(&mut scn);
    (case.inject)(&mut scn, 5.0 * threshold);
    let d = diagnose_inputs(&scn, &record(&scn, false));
    let terms: Vec<(&str, &str, bool)> = d
        .accepted
        .iter()
        .map(|a| (a.effect.as_str(), a.term.as_str(), a.named))
        .collect();
    assert!(
        d.accepted.iter().any(|a| a.effect == "squareness"
            || a.ambiguity_group.iter().any(|m| m.effect == "squareness")),
        "{terms:?}"
    );
    assert!(
        !d.accepted
            .iter()
            .any(|a| a.named && a.effect != "squareness"),
        "{terms:?}"
    );
}

/// An effect that no amplitude names on one plan is named on the plan its advice asks for: a
/// setter mount drift and an EZ0B following the hall, at four times their threshold, are
/// accepted on `patent` in a group whose combination of scales, squarenesses and location
/// errors carries them whatever their size (`named_at` null) and are advised to be touched from
/// both sides of the beam; the same truth and seeds on `patent_both_sides` name them.
#[test]
fn an_effect_no_amplitude_names_is_named_on_the_plan_its_advice_asks_for() {
    use driftwatch_diagnosis::effects::{PlanFeature, effect};
    for name in ["setter_drift", "ambient"] {
        let case = &power_case(name);
        let e = effect(name).expect("in the catalogue");
        assert!(e.splits.contains(&PlanFeature::BothSides), "{name}");
        let threshold = case_threshold(case);
        for seed in 5100..5102 {
            let mut scn = three_days(seed);
            (case.setup)(&mut scn);
            (case.inject)(&mut scn, 4.0 * threshold);
            let d = diagnose_inputs(&scn, &record(&scn, false));
            let of_it: Vec<&driftwatch_diagnosis::cycles::Accepted> = d
                .accepted
                .iter()
                .filter(|a| a.effect == name || a.ambiguity_group.iter().any(|m| m.effect == name))
                .collect();
            assert!(!of_it.is_empty(), "{name} seed {seed}: {:?}", d.accepted);
            for a in &of_it {
                assert!(
                    !a.named && a.named_at.is_none(),
                    "{name} seed {seed}: {a:?}"
                );
                assert!(
                    a.split_by.contains(e.split_by),
                    "{name} seed {seed}: {}",
                    a.split_by
                );
            }
            scn.plan = "patent_both_sides".into();
            let inputs = record(&scn, false);
            let k = Kinematics::load(&scn.machine).unwrap();
            let rows = detection_rows(&k, &inputs.detections, &SolveOptions::new(0.5)).unwrap();
            assert!(PlanFeature::BothSides.shown_by(&rows).is_some());
            let d = diagnose_inputs(&scn, &inputs);
            let named: Vec<(&str, bool)> = d
                .accepted
                .iter()
                .map(|a| (a.effect.as_str(), a.named))
                .collect();
            println!("{name} seed {seed} on patent_both_sides: {named:?}");
            assert!(
                named.contains(&(name, true)),
                "{name} seed {seed}: {named:?}"
            );
        }
    }
}
