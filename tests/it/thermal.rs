//! The thermal model on real data from another lab (fl-thermal, MIT; tests/data/fl-thermal):
//! 46 h of a spindle thermal test. Fit on 0-40 h, predict 40-46.3 h without corrections.
//! No accuracy goal yet: the figures are printed (`cargo test --test it -- thermal:: --nocapture`)
//! and the assertions check what must hold whatever the numbers.

use driftwatch_thermal::model::{Event, HoldoutScore, ModelConfig, TemperatureInput, fit, replay};

const H: i64 = 3_600_000_000_000;

/// ch1 and ch3 with the spindle log and all 16 temperatures.
fn events() -> Vec<Event> {
    fl_thermal(true, &["ch1_um", "ch3_um"])
}

use crate::common::fl_thermal as fl;

/// fl-thermal imported with or without its spindle column, all 16 temperatures and `channels`.
fn fl_thermal(spindle: bool, channels: &[&str]) -> Vec<Event> {
    fl::events(spindle, channels)
}

fn spindle_only() -> ModelConfig {
    ModelConfig {
        n_ref_rpm: 5000.0,
        ..Default::default()
    }
}

fn holdout(cfg: &ModelConfig, ev: &[Event]) -> (Vec<HoldoutScore>, f64) {
    let m = fit(cfg, ev, Some(40 * H)).unwrap();
    let train: f64 = m.channels.iter().map(|c| c.rms_um).sum();
    let (_, scores, _) = replay(&m, ev, 600_000_000_000, 40 * H, 40 * H + 1);
    (scores, train)
}

#[test]
fn fl_thermal_fit_on_40_h_predicts_the_last_6_h() {
    let ev = events();
    let end = ev.last().unwrap().t_ns();
    assert!((end as f64 / H as f64 - 46.31).abs() < 0.01);

    let (spindle, train_spindle) = holdout(&spindle_only(), &ev);
    let with_t = ModelConfig {
        temperatures: (1..=16)
            .map(|i| TemperatureInput {
                sensor: format!("t{i}_C"),
                taus_min: vec![0.0, 60.0, 240.0],
            })
            .collect(),
        ..spindle_only()
    };
    let (temps, train_temps) = holdout(&with_t, &ev);
    // Single time constant, chosen on the training data alone (blocked cross-validation).
    let mut best: Option<(f64, f64)> = None;
    for tau in [5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0] {
        let cfg = ModelConfig {
            taus_min: vec![tau],
            ..spindle_only()
        };
        let m = fit(&cfg, &ev, Some(40 * H)).unwrap();
        let cv: f64 = m.channels.iter().map(|c| c.cv_rmse_um).sum();
        if best.is_none_or(|b| cv < b.1) {
            best = Some((tau, cv));
        }
    }
    let tau = best.unwrap().0;
    let (single, _) = holdout(
        &ModelConfig {
            taus_min: vec![tau],
            ..spindle_only()
        },
        &ev,
    );

    println!("hold-out 40-46.3 h, RMSE um (no corrections after 40 h)");
    println!(
        "channel  persistence  single lag ({tau} min)  spindle basis  spindle + 16 temperatures"
    );
    for i in 0..2 {
        println!(
            "{:<8} {:>11.2} {:>21.2} {:>14.2} {:>26.2}",
            spindle[i].channel,
            spindle[i].persistence_rmse_um,
            single[i].rmse_um,
            spindle[i].rmse_um,
            temps[i].rmse_um
        );
    }
    // What is served (the model, or the fallback the guard chose on the fit's held-out
    // tail), against no compensation: real data the guard was not designed on.
    println!("channel  served: spindle basis / + temperatures   no change / + temperatures");
    for i in 0..2 {
        println!(
            "{:<8} {:>14.2} {:>16.2} {:>13.2} {:>16.2}",
            spindle[i].channel,
            spindle[i].served_rmse_um,
            temps[i].served_rmse_um,
            spindle[i].no_change_rmse_um,
            temps[i].no_change_rmse_um
        );
    }
    // On these real readings (every 15 s, none used after 40 h) the guard must not hold a
    // last value for six hours because it predicted the next reading 15 s ahead well: what is
    // served is within 5 % of the better of the model and persistence.
    for s in spindle.iter().chain(&temps) {
        let best = s.rmse_um.min(s.persistence_rmse_um);
        assert!(s.served_rmse_um <= 1.05 * best, "{s:?}");
    }
    // Every hold-out reading of both channels is scored, by each model.
    for s in [&spindle, &temps, &single] {
        let names: Vec<&str> = s.iter().map(|x| x.channel.as_str()).collect();
        assert_eq!(names, ["ch1_um", "ch3_um"]);
        assert!(
            s.iter().all(|x| x.n == 1480 && x.rmse_um.is_finite()),
            "{s:?}"
        );
    }
    // More inputs fit the training data better.
    assert!(
        train_temps < train_spindle,
        "{train_temps} vs {train_spindle}"
    );
}

#[test]
fn the_replay_is_causal() {
    let ev = events();
    let m = fit(&spindle_only(), &ev, Some(40 * H)).unwrap();
    let (a, _, _) = replay(&m, &ev, 600_000_000_000, i64::MAX, i64::MAX);
    // Change everything after 30 h: nothing before 30 h may move.
    let mut changed = ev.clone();
    for e in &mut changed {
        match e {
            Event::Observation { t_ns, value, .. } if *t_ns > 30 * H => *value += 50.0,
            Event::Spindle { t_ns, rpm } if *t_ns > 30 * H => *rpm = 5000.0 - *rpm,
            _ => {}
        }
    }
    let (b, _, _) = replay(&m, &changed, 600_000_000_000, i64::MAX, i64::MAX);
    let before = |s: &[driftwatch_thermal::model::ReplayStep]| -> Vec<f64> {
        s.iter()
            .filter(|x| x.t_ns <= 30 * H)
            .flat_map(|x| x.predictions.iter().map(|p| p.value))
            .collect()
    };
    assert_eq!(before(&a), before(&b));
    let after = |s: &[driftwatch_thermal::model::ReplayStep]| -> f64 {
        s.iter()
            .filter(|x| x.t_ns > 31 * H)
            .flat_map(|x| x.predictions.iter().map(|p| p.value))
            .sum()
    };
    assert_ne!(after(&a), after(&b));
}

/// A replay that prints steps from before the end of the fit: the predictor starts from the
/// fit's end, but a last measured value served there is the last reading up to that step,
/// never the fit's last reading (which is later), and persistence is scored the same way.
#[test]
fn within_the_fit_the_last_measured_value_is_the_last_reading_so_far() {
    use driftwatch_thermal::model::Served;
    let ev = events();
    // The filter's own value: anchored at each 15-s reading, the model predicts the next one
    // as well as that reading does, and no last measured value would be served to check.
    let cfg = ModelConfig {
        anchoring: driftwatch_thermal::model::Anchoring::Never,
        ..spindle_only()
    };
    let m = fit(&cfg, &ev, Some(40 * H)).unwrap();
    let (steps, _, guards) = replay(&m, &ev, 600_000_000_000, 40 * H, 30 * H);
    assert!(
        guards.iter().any(|g| g.source == Served::LastMeasured),
        "{guards:?}"
    );
    let mut checked = 0;
    for s in steps
        .iter()
        .filter(|s| s.t_ns >= 30 * H && s.t_ns <= 40 * H)
    {
        for p in &s.predictions {
            if p.source != Served::LastMeasured {
                continue;
            }
            let last = ev
                .iter()
                .filter_map(|e| match e {
                    Event::Observation {
                        t_ns,
                        channel,
                        value,
                        ..
                    } if *t_ns <= s.t_ns && *channel == p.channel => Some(*value),
                    _ => None,
                })
                .next_back()
                .unwrap();
            assert_eq!(p.value, last, "{} at {} h", p.channel, s.t_ns / H);
            checked += 1;
        }
    }
    assert!(checked >= 60, "{checked}");
}

#[test]
fn prediction_meets_the_compensation_goals_on_the_four_scenarios() {
    use driftwatch_lab::strategies::{BENCH_SCENARIOS, bench_scenario};
    for (name, _) in BENCH_SCENARIOS {
        let sc = bench_scenario(name, &Default::default(), true).unwrap();
        // The scenario's own cycles (the patent's), else the shipped schedule's.
        let c = sc.own.as_ref().unwrap_or(&sc.old.result);
        let ez = c.predicted.errors["EZ0B"];
        println!(
            "{name}: EZ0B predicted rms {:.2} max {:.2} um (last measured max {:.2}); tool tip {:.1} % removed",
            ez.rms,
            ez.max,
            c.last_measured.errors["EZ0B"].max,
            100.0 * c.tool_tip_reduction()
        );
        assert_eq!(c.cycles, c.cycles_ok, "{name}");
        assert!(
            c.tool_tip_reduction() >= 0.9,
            "{name}: {:?}",
            c.predicted.tool_tip
        );
        assert!(
            c.predicted.tool_tip.rms < c.last_measured.tool_tip.rms,
            "{name}"
        );
        if name == "patent" {
            assert!(ez.max <= 5.0 && ez.rms <= 1.5, "{ez:?}");
            // What the patent as it is leaves after the stop.
            assert!(c.last_measured.errors["EZ0B"].max > 40.0);
        }
    }
}

use fl::CHANNELS;

/// The families compete on fl-thermal's five channels (fit on 0-40 h, cross-validated there
/// at the horizon of use, 6.3 h, judged on 40-46.3 h with no reading used), with the spindle
/// log and without it. Least squares on every input is the baseline; a challenger replaces
/// it only with wins beyond chance on folds with separate prediction windows, and a 6.3-h
/// horizon in the second half of a 40-h fit leaves fewer such folds than the sign test
/// needs: regression is served, and what is served is its hold-out. The bands cover their
/// share of the CV folds' errors (each fold against the other folds' bands) within 10
/// points. Without the spindle column no design holds a column of zeros and every family
/// is fitted from the temperatures. Figures: `cargo run --release -- bench thermal`.
#[test]
fn on_fl_thermal_least_squares_serves_where_no_challenger_wins_beyond_chance() {
    use driftwatch_core::stats::sign_test_wins;
    use driftwatch_thermal::families::{
        Family, choose, folds, grey_box_config, grid, independent_folds,
    };
    let ev = fl_thermal(true, &CHANNELS);
    for ch in CHANNELS {
        let g = grid(&ev, ch, 300_000_000_000).unwrap();
        let n_train = g.index_at(40 * H);
        let horizon = g.len() - n_train;
        assert!(
            sign_test_wins(independent_folds(&folds(n_train, horizon)).len()).is_none(),
            "{ch}"
        );
        let c = choose(
            &ev,
            &g,
            40 * H,
            &Family::ALL,
            &grey_box_config(&g),
            None,
            horizon,
        )
        .unwrap();
        assert_eq!(
            c.scores.len(),
            6,
            "{ch}: every family fitted: {:#?}",
            c.scores
        );
        let choice = c.choice.as_ref().unwrap();
        assert_eq!(choice.family, Family::Regression, "{ch}: {}", choice.why);
        assert!(choice.why.contains("not beyond chance") || choice.why.contains("lowest CV error"));
        // Served inside the fit range: regression's own free run.
        use driftwatch_thermal::families::{Served, simulate};
        let served = c.serve(&g, n_train, g.len(), &vec![f64::NAN; horizon], f64::NAN);
        let own = simulate(&c.fitted, &g, n_train, g.len());
        assert!(
            served.iter().any(|s| matches!(s.1, Served::Inside(_))),
            "{ch}"
        );
        for ((v, s), p) in served.iter().zip(&own) {
            if matches!(s, Served::Inside(_)) {
                assert!((v - p).abs() < 1e-9, "{ch}");
            }
        }
        let reg = c.scores.iter().find(|x| x.family == "regression").unwrap();
        let (c68, c95) = (reg.cv_cover68.unwrap(), reg.cv_cover95.unwrap());
        assert!(
            (c68 - 0.68).abs() <= 0.15 && (c95 - 0.95).abs() <= 0.15,
            "{ch}: CV coverage {c68} / {c95}"
        );
    }
    let bare = fl_thermal(false, &CHANNELS);
    assert!(!bare.iter().any(|e| matches!(e, Event::Spindle { .. })));
    let g = grid(&bare, "ch3_um", 300_000_000_000).unwrap();
    assert_eq!(g.names.len(), 16, "temperatures only: {:?}", g.names);
    let c = choose(
        &bare,
        &g,
        40 * H,
        &Family::ALL,
        &grey_box_config(&g),
        None,
        76,
    )
    .unwrap();
    assert_eq!(c.scores.len(), 6, "{:#?}", c.scores);
    assert!(
        c.scores
            .iter()
            .all(|x| x.cv_rmse.is_finite() && x.holdout_rmse.is_finite())
    );
}

/// The same competition on a simulated scenario, where the physics is known: two-shift days
/// seen as a test rig sees them (each identified error read every minute with 0.5 um noise,
/// `strategies::sensor_view`), fit on 0-40 h, judged on 40-72 h. Used 2 h ahead (as between
/// a service's cycles), the second half of the fit holds ten folds with separate windows:
/// the grey box's pole basis, which holds the truth's structure, must win beyond chance
/// there, come down to the sensor noise, and beat persistence and every baseline.
#[test]
fn on_a_simulated_two_shift_run_the_grey_box_wins_beyond_chance_and_reaches_the_noise() {
    use driftwatch_thermal::families::{Family, compete, grey_box_config, grid};
    let sigma = 0.5;
    let ev = driftwatch_lab::strategies::sensor_view("two_shift", 3, sigma).unwrap();
    let t0 = ev[0].t_ns();
    assert!(
        ev.iter()
            .any(|e| matches!(e, Event::Spindle { rpm, .. } if *rpm > 0.0))
    );
    for ch in ["EZ0B", "EX0B"] {
        let g = grid(&ev, ch, 300_000_000_000).unwrap();
        let (s, choice) = compete(&ev, &g, t0 + 40 * H, &Family::ALL, &grey_box_config(&g), 24);
        let chosen = s.iter().find(|x| x.chosen).unwrap();
        assert!(choice.inside.folds >= 5, "{}", choice.why);
        let baselines = ["persistence", "regression", "key_regression", "arx"];
        let best_baseline = s
            .iter()
            .filter(|x| baselines.contains(&x.family.as_str()))
            .map(|x| x.holdout_rmse)
            .fold(f64::INFINITY, f64::min);
        println!(
            "{ch}: chosen {} hold-out {:.2}, best baseline {best_baseline:.2}",
            chosen.family, chosen.holdout_rmse
        );
        assert!(
            ["grey_box", "combination"].contains(&chosen.family.as_str()),
            "{ch}: {chosen:?}"
        );
        assert!(chosen.holdout_rmse < 1.3 * sigma, "{ch}: {chosen:?}");
        assert!(chosen.holdout_rmse < best_baseline, "{ch}: {s:#?}");
    }
}
