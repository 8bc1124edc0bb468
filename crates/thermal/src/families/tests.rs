//! The tests on a simulated plant, which cross the parts: its grid, the competition on it and
//! the choice.

use super::*;
use crate::model::Event;
use driftwatch_core::units;

const MIN: i64 = units::NS_PER_MIN;

/// A first-order plant driven by one temperature, another temperature that is noise,
/// sampled every minute.
fn plant(n: usize, gain: f64) -> Vec<Event> {
    let mut ev = Vec::new();
    let mut x = 0.0;
    let mut rng = 12345u64;
    let mut noise = || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((rng >> 33) as f64 / (1u64 << 31) as f64) - 0.5
    };
    for k in 0..n {
        let t = k as i64 * MIN;
        let drive = 20.0 + 5.0 * ((k as f64) / 300.0).sin();
        x += (gain * (drive - 20.0) - x) / 60.0;
        ev.push(Event::Temperature {
            t_ns: t,
            sensor: "drive".into(),
            celsius: drive,
        });
        ev.push(Event::Temperature {
            t_ns: t,
            sensor: "other".into(),
            celsius: 20.0 + noise(),
        });
        ev.push(Event::Observation {
            t_ns: t,
            channel: "d".into(),
            value: x + 0.05 * noise(),
            sigma: None,
        });
    }
    ev
}

#[test]
fn the_grid_holds_each_value_and_leaves_out_a_spindle_that_never_turned() {
    let mut ev = plant(30, 2.0);
    ev.push(Event::Spindle { t_ns: 0, rpm: 0.0 });
    ev.sort_by_key(|e| e.t_ns());
    let g = grid(&ev, "d", 5 * MIN).unwrap();
    assert_eq!(g.names, ["drive", "other"]);
    assert_eq!(g.len(), 6);
    assert_eq!(g.t_ns[1], 5 * MIN);
    assert!(grid(&ev, "nothing", MIN).is_none());
}

#[test]
fn a_choice_round_trips_through_json_with_figures_it_could_not_have() {
    let ev = plant(600, 2.0);
    let g = grid(&ev, "d", 5 * MIN).unwrap();
    let fams = [Family::Persistence, Family::Regression];
    let mut c = choose(&ev, &g, 400 * MIN, &fams, &grey_box_config(&g), None, 12).unwrap();
    let ch = c.choice.as_mut().unwrap();
    ch.inside.rmse = f64::NAN;
    ch.tested_excursion = f64::INFINITY;
    let text = serde_json::to_string(&c).unwrap();
    let back: ChannelChoice = serde_json::from_str(&text).unwrap();
    assert_eq!(back.family, c.family);
    assert!(back.choice.unwrap().inside.rmse.is_nan());
}

/// On a lagged plant the free-run ARX beats regression at the same time, both beat
/// persistence, key selection finds the driving sensor, and the CV choice is ARX.
#[test]
fn the_family_that_matches_the_plant_wins_the_cross_validation() {
    let ev = plant(3000, 2.0);
    let g = grid(&ev, "d", 5 * MIN).unwrap();
    let n_train = g.index_at(2000 * MIN);
    assert_eq!(key_inputs(&g, n_train, 12), [0]);
    let s = compete(
        &ev,
        &g,
        2000 * MIN,
        &[
            Family::Persistence,
            Family::Regression,
            Family::KeyRegression,
            Family::Arx,
        ],
        &grey_box_config(&g),
        // An hour ahead: the second half of the fit holds eight separate windows.
        12,
    )
    .0;
    let by = |f: Family| s.iter().find(|x| x.family == f.as_str()).unwrap();
    let arx = by(Family::Arx);
    assert!(arx.chosen, "{s:#?}");
    assert!(
        arx.holdout_rmse < 0.2 * by(Family::Regression).holdout_rmse,
        "{s:#?}"
    );
    assert!(by(Family::Regression).holdout_rmse < by(Family::Persistence).holdout_rmse);
    // Its band, from the CV errors, covers about what it claims on the hold-out.
    assert!(arx.cover95 > 0.8, "{arx:?}");
}
