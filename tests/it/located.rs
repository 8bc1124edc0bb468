//! The located term on real data (fl-thermal, MIT; tests/data/fl-thermal): what the forward
//! selection leaves is located, tied to a temperature, made a term and judged on the
//! held-out end. A late drift that follows one temperature after an onset, injected into the
//! real readings, is modelled and the held-out error falls; the recording as it is gets no
//! located term that worsens its held-out end; a drift that follows a temperature rising
//! as steadily as time is reported as confounded with a ramp. The power table over sizes,
//! onsets, sensors and channels: `cargo test --test it -- located:: --ignored --nocapture`.

use driftwatch_diagnosis::displacement::{
    ChannelDiagnosis, DisplacementOptions, NotConfirmed, diagnose_displacements,
};
use driftwatch_lab::calibration::{LocatedOutcome, located_power, worsening_terms};
use driftwatch_lab::null_recordings::with_temperature_effect;
use driftwatch_thermal::model::Event;

const H: i64 = 3_600_000_000_000;

use crate::common::fl_thermal as fl;

fn events() -> Vec<Event> {
    fl::events(true, &fl::CHANNELS)
}

fn opts() -> DisplacementOptions {
    DisplacementOptions {
        n_ref_rpm: 5000.0,
        ..Default::default()
    }
}

fn one(ev: &[Event], channel: &str) -> ChannelDiagnosis {
    diagnose_displacements(ev, &[channel.to_string()], &opts())
        .unwrap()
        .channels
        .remove(0)
}

/// 3 um RMS of t11_C's change since 25 h added to fl-thermal's ch1: the drift is located
/// on the training part, tied to t11_C, modelled as a term and accepted; the held-out error
/// falls, and the one statement of it says so.
#[test]
fn a_late_drift_in_real_data_is_modelled_and_the_held_out_error_falls() {
    let ev = with_temperature_effect(&events(), "ch1_um", "t11_C", 3.0, Some(25 * H));
    let c = one(&ev, "ch1_um");
    let l = c.located_term.as_ref().unwrap();
    println!("{}", l.statement);
    assert_eq!(l.sensor, "t11_C", "{l:?}");
    let onset = l.onset_h.unwrap();
    assert!((15.0..=27.0).contains(&onset), "{l:?}");
    assert!(l.accepted, "{l:?}");
    assert!(l.reason.is_none() && l.rule.is_none(), "{l:?}");
    assert!(
        l.heldout_after_um < 0.8 * l.heldout_before_um,
        "{} -> {}",
        l.heldout_before_um,
        l.heldout_after_um
    );
    assert!(l.delta_bic >= l.bar && l.t.abs() >= 4.0, "{l:?}");
    // It is a term of the final model, whose held-out figure is the one with it.
    assert!(
        c.accepted
            .iter()
            .any(|t| t.effect == "onset_drift" && t.term == l.term)
    );
    assert!((c.final_fit.rms_heldout_um - l.heldout_after_um).abs() < 1e-9);
    // One statement of it, saying it was accepted.
    let of_it: Vec<&String> = c
        .statements
        .iter()
        .filter(|s| s.contains("located:"))
        .collect();
    assert_eq!(of_it.len(), 1, "{:?}", c.statements);
    assert!(
        of_it[0].contains("accepted into the final model"),
        "{of_it:?}"
    );
}

/// On fl-thermal as it is, a located term is judged like any other: none that is accepted
/// worsens the held-out end, and a channel's final held-out RMS is never above its
/// baseline's.
#[test]
fn on_real_data_no_located_term_worsens_the_held_out_end() {
    let channels: Vec<String> = (1..=5).map(|i| format!("ch{i}_um")).collect();
    let d = diagnose_displacements(&events(), &channels, &opts()).unwrap();
    assert!(worsening_terms(&d).is_empty(), "{:?}", worsening_terms(&d));
    for c in &d.channels {
        if let Some(l) = &c.located_term {
            println!("{}", l.statement);
            assert!(
                !l.accepted || l.heldout_after_um <= l.heldout_before_um,
                "{l:?}"
            );
            // Accepted or not confirmed, never both.
            assert_eq!(l.accepted, l.reason.is_none(), "{l:?}");
        }
        assert!(c.final_fit.rms_heldout_um <= c.baseline.rms_heldout_um);
    }
}

/// fl-thermal with one more sensor, a hall that swings until 20 h and then rises as steadily
/// as time (0.2 K/h); a drift of its change since 20 h added to ch1. Whatever fits it, a
/// ramp from 20 h fits as well: the located term is reported as confounded with a ramp,
/// with the recording that would split them, and not accepted.
///
/// Ignored: it fails today. The onset search (unwhitened, lag 0) ties the residual to
/// another sensor (t16_C from 16 h, or t3_C from 27 h at 4 um) rather than the hall, so the
/// ramp rule is never reached for the hall; see the report of this change.
#[test]
#[ignore]
fn a_drift_that_follows_a_steady_ramp_is_confounded_with_it() {
    let mut ev = events();
    let end = ev.last().map_or(0, Event::t_ns);
    let mut t = 0;
    while t <= end {
        let h = t as f64 / H as f64;
        // Before 20 h it swings (and the readings do not follow it there, so the hall
        // itself is a poor term); from 20 h it climbs steadily.
        let celsius = if h < 20.0 {
            22.0 + 1.5 * (std::f64::consts::TAU * h / 8.0).sin()
        } else {
            22.0 + 0.2 * (h - 20.0) + 0.05 * (std::f64::consts::TAU * h / 3.0).sin()
        };
        ev.push(Event::Temperature {
            t_ns: t,
            sensor: "hall_C".into(),
            celsius,
        });
        t += H / 12;
    }
    ev.sort_by_key(Event::t_ns);
    let ev = with_temperature_effect(&ev, "ch1_um", "hall_C", 10.0, Some(20 * H));
    let c = one(&ev, "ch1_um");
    println!("{:?}", c.statements);
    let l = c.located_term.as_ref().unwrap();
    assert_eq!(l.sensor, "hall_C", "{}", l.statement);
    assert!(l.ramp_r.abs() > 0.95, "{l:?}");
    assert_eq!(l.reason, Some(NotConfirmed::ConfoundedWithRamp), "{l:?}");
    assert!(!l.accepted);
    assert!(
        l.split_by
            .as_ref()
            .unwrap()
            .contains("do not move together")
    );
    assert!(
        l.statement.contains("confounded with a ramp"),
        "{}",
        l.statement
    );
    assert!(!c.accepted.iter().any(|t| t.term == l.term));
}

/// The power table: a drift of 1.5, 3 and 6 um RMS that follows one temperature's change
/// after an onset, injected into each of fl-thermal's five channels (four sensors, three
/// onsets), diagnosed with the default hold-out (the last 15 %); and the same recordings
/// without it. Prints the rate found (the located term names the sensor), found and
/// modelled (a term on it accepted that the recording without it does not have) by size,
/// the reasons when it is not confirmed, and the false located terms.
#[test]
#[ignore]
fn located_power_on_fl_thermal() {
    let ev = events();
    let sizes = [0.0, 1.5, 3.0, 6.0];
    let mut all: Vec<LocatedOutcome> = Vec::new();
    for ch in 1..=5 {
        for sensor in ["t2_C", "t8_C", "t11_C", "t14_C"] {
            for onset_h in [15, 20, 25] {
                let o = located_power(
                    &ev,
                    &format!("ch{ch}_um"),
                    sensor,
                    onset_h * H,
                    &sizes,
                    &opts(),
                )
                .unwrap();
                for x in &o {
                    println!(
                        "{} {} {:>2} h {:>3} um: located {:?} at {:?} accepted {} reason {:?} rule {:?} found {} modelled {} false {:?} held-out {:?}",
                        x.channel,
                        x.sensor,
                        x.onset_h,
                        x.rms_um,
                        x.located_sensor,
                        x.located_onset_h.map(|h| (h * 10.0).round() / 10.0),
                        x.located_accepted,
                        x.reason,
                        x.rule,
                        x.found,
                        x.modelled,
                        x.false_term,
                        x.located_heldout_um
                    );
                }
                all.extend(o);
            }
        }
    }
    println!(
        "size | trials | found | found and modelled | not confirmed by reason | false located terms"
    );
    for &size in &sizes {
        let of: Vec<&LocatedOutcome> = all.iter().filter(|o| o.rms_um == size).collect();
        let count = |f: &dyn Fn(&LocatedOutcome) -> bool| of.iter().filter(|o| f(o)).count();
        let mut reasons = std::collections::BTreeMap::new();
        for o in of.iter().filter(|o| o.found && !o.located_accepted) {
            *reasons.entry(format!("{:?}", o.reason)).or_insert(0) += 1;
        }
        println!(
            "{size} | {} | {} | {} | {reasons:?} | {}",
            of.len(),
            count(&|o| o.found),
            count(&|o| o.modelled),
            count(&|o| o.false_term.is_some())
        );
    }
}

/// Two drifts in fl-thermal's ch1: 6 um RMS of t8_C's change since 6 h and 3 um of t11_C's
/// since 28 h. The first located search takes the largest departure; the later one is
/// sought in its own window, the last part of the fit, and is located there on t11_C near
/// 28 h, modelled, its held-out figures shown before and after (the held-out error falls),
/// and not confirmed with the rule it failed and the reason, in one statement.
#[test]
fn a_later_smaller_drift_is_located_in_its_own_window() {
    let ev = with_temperature_effect(&events(), "ch1_um", "t8_C", 6.0, Some(6 * H));
    let ev = with_temperature_effect(&ev, "ch1_um", "t11_C", 3.0, Some(28 * H));
    let c = one(&ev, "ch1_um");
    assert!(c.located_term.is_some());
    let l = c.late_term.as_ref().unwrap();
    println!("{}", l.statement);
    assert_eq!(l.sensor, "t11_C", "{l:?}");
    let onset = l.onset_h.unwrap();
    assert!((26.0..=30.0).contains(&onset), "{l:?}");
    assert!(
        l.heldout_after_um < l.heldout_before_um,
        "{} -> {}",
        l.heldout_before_um,
        l.heldout_after_um
    );
    // The held-out end's ranking of the same term on each sensor is shown beside the tie.
    assert_eq!(l.heldout_by_sensor.len(), 16, "{l:?}");
    assert!(l.statement.contains("the same term on each sensor instead"));
    // Not confirmed here: the rule and the reason are named, and it is not in the model.
    assert!(
        !l.accepted && l.rule.is_some() && l.reason.is_some(),
        "{l:?}"
    );
    assert!(!c.accepted.iter().any(|t| t.term == l.term));
    let of_it: Vec<&String> = c
        .statements
        .iter()
        .filter(|s| s.starts_with("(later departure)"))
        .collect();
    assert_eq!(of_it.len(), 1, "{:?}", c.statements);
}
