//! The tests that cross the parts: a fit on simulated days, then its predictor or a causal
//! replay of them.

use std::collections::BTreeMap;

use super::*;
use driftwatch_core::units;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const MIN: i64 = units::NS_PER_MIN;

/// A patent-like day: 20000 min^-1 for 210 min, 30 min stop, restart; observations of a
/// two-lag channel every `every` min with noise `sd`.
fn day(every: i64, sd: f64, seed: u64) -> (Vec<Event>, Vec<(i64, f64)>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut ev = vec![
        Event::Spindle {
            t_ns: 0,
            rpm: 20000.0,
        },
        Event::Spindle {
            t_ns: 210 * MIN,
            rpm: 0.0,
        },
        Event::Spindle {
            t_ns: 240 * MIN,
            rpm: 20000.0,
        },
        Event::Spindle {
            t_ns: 400 * MIN,
            rpm: 10000.0,
        },
        Event::Spindle {
            t_ns: 500 * MIN,
            rpm: 0.0,
        },
    ];
    let truth = |t: f64, lags: &mut (f64, f64), u: f64, dt: f64| {
        let a1 = (-dt / 12.0).exp();
        let a2 = (-dt / 120.0).exp();
        lags.0 = a1 * lags.0 + (1.0 - a1) * u;
        lags.1 = a2 * lags.1 + (1.0 - a2) * u;
        let _ = t;
        5.0 + 39.0 * lags.0 + 49.0 * lags.1
    };
    let mut lags = (0.0, 0.0);
    let mut truth_at = Vec::new();
    let speed = |m: i64| match m {
        0..210 => 20000.0,
        240..400 => 20000.0,
        400..500 => 10000.0,
        _ => 0.0,
    };
    let mut y = 5.0;
    for m in 0..=700 {
        if m > 0 {
            let u = (speed(m - 1) / 20000.0f64).powf(1.5);
            y = truth(m as f64, &mut lags, u, 1.0);
        }
        truth_at.push((m * MIN, y));
        if m % every == 0 {
            ev.push(Event::Observation {
                t_ns: m * MIN,
                channel: "EZ0B".into(),
                value: y + sd * rng.random_range(-1.0..1.0) * 3f64.sqrt(),
                sigma: Some(sd),
            });
        }
    }
    ev.sort_by_key(|e| (e.t_ns(), matches!(e, Event::Observation { .. })));
    (ev, truth_at)
}

const DAY: i64 = 1440 * MIN;

/// A truth sample: time and each channel's value.
type Truth = (i64, BTreeMap<String, f64>);

/// Speed of a two-shift day at minute `m` of the day: on at 06:00, lunch 11:30-12:15, a
/// break 17:00-17:20, off at 22:00.
fn two_shift_rpm(m: i64) -> f64 {
    match m {
        360..690 => 15000.0,
        735..1020 => 20000.0,
        1040..1320 => 12000.0,
        _ => 0.0,
    }
}

/// A truth channel: spindle lag gain and time constant (min), cycle noise (one sd), and
/// a random walk of its own, unit^2/h.
struct Chan {
    name: &'static str,
    gain: f64,
    tau_min: f64,
    sd: f64,
    walk_per_h: f64,
}

/// `days` two-shift days: the spindle log, each channel observed every 40 min between
/// 06:20 and 21:40 with its noise (the stated sigma is the noise), and the truth every
/// minute.
fn shifts(days: i64, chans: &[Chan], seed: u64) -> (Vec<Event>, Vec<Truth>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let normal = |rng: &mut ChaCha8Rng| -> f64 {
        // Box-Muller from two uniforms.
        let (a, b): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let mut ev = Vec::new();
    let mut truth = Vec::new();
    let mut lag = vec![0.0; chans.len()];
    let mut walk = vec![0.0; chans.len()];
    let mut rpm = -1.0;
    for t in 0..days * 1440 {
        let r = two_shift_rpm(t % 1440);
        if r != rpm {
            ev.push(Event::Spindle {
                t_ns: t * MIN,
                rpm: r,
            });
            rpm = r;
        }
        let mut values = BTreeMap::new();
        for (i, c) in chans.iter().enumerate() {
            values.insert(c.name.to_string(), c.gain * lag[i] + walk[i]);
        }
        let m = t % 1440;
        if (380..=1300).contains(&m) && (m - 380) % 40 == 0 {
            for c in chans {
                ev.push(Event::Observation {
                    t_ns: t * MIN,
                    channel: c.name.into(),
                    value: values[c.name] + c.sd * normal(&mut rng),
                    sigma: Some(c.sd),
                });
            }
        }
        truth.push((t * MIN, values));
        let u = (r / 20000.0f64).powf(1.5);
        for (i, c) in chans.iter().enumerate() {
            let a = (-1.0 / c.tau_min).exp();
            lag[i] = a * lag[i] + (1.0 - a) * u;
            walk[i] += (c.walk_per_h / 60.0).sqrt() * normal(&mut rng);
        }
    }
    (ev, truth)
}

/// How the service did before the walk was learnt and the model guarded: one offset walk of
/// 1 unit^2/h for every channel, the model always served, its band unscaled.
fn as_before() -> ModelConfig {
    ModelConfig {
        offset_walk_grid_per_h: Vec::new(),
        min_scored: 1000,
        ..Default::default()
    }
}

/// Fit on the first two days, replay the third causally (each cycle scored before it
/// corrects the filter): the scores of the held-out cycles and against the truth.
fn third_day(
    cfg: &ModelConfig,
    ev: &[Event],
    truth: &[(i64, BTreeMap<String, f64>)],
) -> (Vec<HoldoutScore>, Vec<TruthScore>, Vec<GuardSummary>) {
    let m = fit(cfg, ev, Some(2 * DAY - 1)).unwrap();
    let (steps, held_out, served) = replay(&m, ev, MIN, i64::MAX, 2 * DAY);
    let reference = truth[0].1.clone();
    let vs_truth = truth_scores(&steps, ev, truth, &reference, 2 * DAY);
    (held_out, vs_truth, served)
}

fn of<'a, T>(v: &'a [T], name: &str, f: impl Fn(&T) -> &str) -> &'a T {
    v.iter().find(|x| f(x) == name).unwrap()
}

#[test]
fn a_noisy_channel_without_thermal_gain_is_never_served_worse_than_no_change() {
    // EZ0B: a strong lag the model follows. EA0C: no thermal change at all, 2.5 urad of
    // noise in every cycle (a failure seen before: gains about zero, the offset walk
    // chasing each noisy cycle).
    let chans = [
        Chan {
            name: "EZ0B",
            gain: 48.0,
            tau_min: 120.0,
            sd: 0.3,
            walk_per_h: 0.0,
        },
        Chan {
            name: "EA0C",
            gain: 0.0,
            tau_min: 90.0,
            sd: 2.5,
            walk_per_h: 0.0,
        },
    ];
    let (ev, truth) = shifts(3, &chans, 12);
    let (_, before, _) = third_day(&as_before(), &ev, &truth);
    let (_, after, served) = third_day(&ModelConfig::default(), &ev, &truth);
    let b = of(&before, "EA0C", |s| &s.channel);
    let a = of(&after, "EA0C", |s| &s.channel);
    let no_change = of(&served, "EA0C", |s| &s.channel);
    println!("EA0C before: {b:?}\nEA0C after: {a:?}\n{no_change:?}");
    // Uncompensated, EA0C is exactly right (the truth never moves): anything served is
    // worse by its own error. Before, the filter chased the noise, well beyond what the
    // mean of the cycles leaves.
    assert!(a.served_rms < 0.5 * b.served_rms, "{a:?} vs {b:?}");
    assert!(a.served_rms < 0.8, "{a:?}");
    // Its walk is learned in its own unit (urad^2/h) and is small.
    assert!(no_change.offset_walk_learned, "{no_change:?}");
    assert!(no_change.offset_walk_per_h <= 0.1, "{no_change:?}");
    // EZ0B keeps its model and what it removes of its thermal error (the rest is the pole
    // basis' misfit of a 120-min lag, the same with or without the guard).
    let ez = of(&after, "EZ0B", |s| &s.channel);
    let ez_before = of(&before, "EZ0B", |s| &s.channel);
    assert!(
        ez.removed() > 0.85 && ez.removed() >= ez_before.removed() - 0.01,
        "{ez:?} before {ez_before:?}"
    );
    assert_eq!(of(&served, "EZ0B", |s| &s.channel).source, Served::Model);
}

#[test]
fn an_implausible_input_never_makes_a_prediction_non_finite() {
    let (ev, _) = day(10, 0.5, 4);
    let m = fit(&ModelConfig::default(), &ev, None).unwrap();
    let mut p = Predictor::new(&m, m.to_ns);
    let mut q = p.clone();
    p.apply(&Event::Spindle {
        t_ns: m.to_ns + MIN,
        rpm: 1e300,
    });
    p.apply(&Event::Spindle {
        t_ns: m.to_ns + 2 * MIN,
        rpm: f64::NAN,
    });
    let (a, b) = (p.predict(m.to_ns + 60 * MIN), q.predict(m.to_ns + 60 * MIN));
    assert!(
        a.iter().all(|x| x.value.is_finite() && x.sigma.is_finite()),
        "{a:?}"
    );
    assert_eq!(a, b, "the implausible speeds are not taken");
}

#[test]
fn temperature_gains_fitted_to_noise_are_not_extrapolated() {
    // Two days in a hall at 20 +- 1 K: EZ0B follows it at 4 um/K, EA0C does not follow it
    // at all (2.5 urad of noise per cycle). Then the hall at 17 C, outside the fit data.
    let cfg = ModelConfig {
        taus_min: vec![60.0],
        temperatures: vec![TemperatureInput {
            sensor: "ambient".into(),
            taus_min: vec![0.0],
        }],
        ..Default::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let hall = |m: i64| 20.0 + (std::f64::consts::TAU * m as f64 / 1440.0).sin();
    let mut ev = vec![Event::Spindle { t_ns: 0, rpm: 0.0 }];
    for m in (0..2 * 1440).step_by(20) {
        ev.push(Event::Temperature {
            t_ns: m * MIN,
            sensor: "ambient".into(),
            celsius: hall(m),
        });
        for (ch, v, sd) in [("EZ0B", 4.0 * (hall(m) - 20.0), 0.3), ("EA0C", 0.0, 2.5)] {
            let noise: f64 = rng.random_range(-1.0..1.0) * sd * 3f64.sqrt();
            ev.push(Event::Observation {
                t_ns: m * MIN + 1,
                channel: ch.into(),
                value: v + noise,
                sigma: Some(sd),
            });
        }
    }
    let m = fit(&cfg, &ev, None).unwrap();
    let held = |n: &str| {
        m.channels
            .iter()
            .find(|c| c.name == n)
            .unwrap()
            .held_to_range
            .len()
    };
    assert_eq!((held("EZ0B"), held("EA0C")), (0, 1));
    let at = |celsius: f64| {
        let mut p = Predictor::new(&m, m.to_ns);
        p.apply(&Event::Temperature {
            t_ns: m.to_ns + MIN,
            sensor: "ambient".into(),
            celsius,
        });
        let v = p.predict(m.to_ns + 2 * MIN);
        let get = |n: &str| v.iter().find(|x| x.channel == n).unwrap().model_value;
        (get("EZ0B"), get("EA0C"))
    };
    let (ez17, ea17) = at(17.0);
    let (_, ea_edge) = at(19.0);
    // The response the data show is extrapolated as fitted; the noise's is held at the
    // edge of the range the fit saw.
    assert!((ez17 + 12.0).abs() < 0.5, "{ez17}");
    assert!((ea17 - ea_edge).abs() < 0.05, "{ea17} vs {ea_edge}");
    // (Not trivially: the noise's gain would have moved it by more than that.)
    let ea = m.channels.iter().find(|c| c.name == "EA0C").unwrap();
    let gain = ea.coef[2];
    assert!(2.0 * gain.abs() > 0.1, "EA0C gain {gain}");
}

#[test]
fn the_served_model_passes_through_the_last_observation_and_moves_by_its_change() {
    let (ev, _) = day(30, 0.3, 7);
    let cut = 300 * MIN;
    let model = fit(&ModelConfig::default(), &ev, Some(cut)).unwrap();
    let served_after_an_offset = |anchored: bool| {
        let mut m = model.clone();
        m.config.anchoring = if anchored {
            Anchoring::Always
        } else {
            Anchoring::Never
        };
        let mut p = Predictor::new(&m, 0);
        for e in ev.iter().filter(|e| e.t_ns() <= cut) {
            p.apply(e);
        }
        // A cycle 6 um above what the model says: an error that persists.
        let t = cut + 15 * MIN;
        let before = p.predict(t)[0].model_value;
        p.apply(&Event::Observation {
            t_ns: t,
            channel: "EZ0B".into(),
            value: before + 6.0,
            sigma: Some(0.3),
        });
        let now = p.predict(t)[0].clone();
        let later = p.predict(t + 20 * MIN)[0].clone();
        (before + 6.0, now, later)
    };
    let (y, now, later) = served_after_an_offset(true);
    assert_eq!(now.source, Served::Model, "{now:?}");
    assert!((now.value - y).abs() < 1e-9, "{} vs {y}", now.value);
    // Twenty minutes on, the anchored value has moved by the model's change only.
    let (_, raw_now, raw_later) = served_after_an_offset(false);
    let change = raw_later.model_value - raw_now.model_value;
    assert!(
        (later.value - (y + change)).abs() < 0.5,
        "{later:?} {change}"
    );
    // The filter alone takes part of the 6 um as noise of the model.
    assert!((raw_now.value - y).abs() > 0.1, "{raw_now:?} vs {y}");
}

#[test]
fn the_offset_walk_is_learned_per_channel_in_its_own_unit() {
    // Same program, same lags: one channel's offset wanders by 3 unit^2/h, the other's
    // stays put.
    let chans = [
        Chan {
            name: "EX0B",
            gain: 22.0,
            tau_min: 60.0,
            sd: 0.3,
            walk_per_h: 3.0,
        },
        Chan {
            name: "EB0C",
            gain: -4.0,
            tau_min: 90.0,
            sd: 2.5,
            walk_per_h: 0.0,
        },
    ];
    let (ev, _) = shifts(3, &chans, 5);
    let m = fit(&ModelConfig::default(), &ev, None).unwrap();
    let walk = |n: &str| {
        m.channels
            .iter()
            .find(|c| c.name == n)
            .and_then(|c| c.offset_walk_per_h)
            .unwrap()
    };
    println!(
        "EX0B {} um^2/h, EB0C {} urad^2/h",
        walk("EX0B"),
        walk("EB0C")
    );
    assert!((1.0..=10.0).contains(&walk("EX0B")), "{}", walk("EX0B"));
    assert!(walk("EB0C") <= 0.1, "{}", walk("EB0C"));
    // The served band follows: after 8 h without a cycle the wandering channel is the
    // less certain one relative to its noise, the still one barely moves.
    let mut p = Predictor::resume(
        std::sync::Arc::new(m.clone()),
        Features::new(&m.config, &m.t_ref_c, m.from_ns),
        m.to_ns,
    );
    let s = |p: &mut Predictor, t: i64, n: &str| {
        p.predict(t).into_iter().find(|x| x.channel == n).unwrap()
    };
    let now = m.to_ns;
    let (a0, a8) = (s(&mut p, now, "EX0B"), s(&mut p, now + 480 * MIN, "EX0B"));
    let (b0, b8) = (s(&mut p, now, "EB0C"), s(&mut p, now + 480 * MIN, "EB0C"));
    assert_eq!((a8.source, b8.source), (Served::Model, Served::Model));
    assert!(a8.sigma > 1.4 * a0.sigma, "{a0:?} {a8:?}");
    assert!(b8.sigma < 1.5 * b0.sigma, "{b0:?} {b8:?}");
}

#[test]
fn the_band_is_calibrated_on_held_out_cycles() {
    // A lag outside the pole basis (35 min) and a slow wander: the model's own band is
    // not right by construction; the held-out scale brings it to z rms near 1.
    let chans = [
        Chan {
            name: "EZ0B",
            gain: 48.0,
            tau_min: 35.0,
            sd: 0.5,
            walk_per_h: 0.3,
        },
        Chan {
            name: "EX0B",
            gain: 22.0,
            tau_min: 60.0,
            sd: 0.5,
            walk_per_h: 0.0,
        },
    ];
    let (ev, truth) = shifts(3, &chans, 21);
    let (before, _, _) = third_day(&as_before(), &ev, &truth);
    let (after, _, served) = third_day(&ModelConfig::default(), &ev, &truth);
    for n in ["EZ0B", "EX0B"] {
        let b = of(&before, n, |s| &s.channel);
        let a = of(&after, n, |s| &s.channel);
        let g = of(&served, n, |s| &s.channel);
        println!("{n} before: {b:?}\n{n} after: {a:?}\n{n} guard: {g:?}");
        // Over every held-out cycle (the fit's tail, then the third day, each scored
        // before it corrected the model): calibrated.
        assert!(g.scored >= 30, "{g:?}");
        assert!((0.75..=1.25).contains(&g.z_rms), "{n}: {g:?}");
        assert!(g.sigma_scale != 1.0, "{g:?}");
        // The third day alone: no band too narrow, at least 85 % within 2 sigma.
        assert!(a.n >= 20, "{a:?}");
        assert!((0.6..=1.25).contains(&a.z_rms), "{n}: {a:?}");
        assert!(a.within_2_sigma >= 0.85, "{n}: {a:?}");
    }
}

#[test]
fn a_two_lag_channel_is_recovered_and_predicted() {
    let (ev, truth) = day(5, 0.3, 7);
    let m = fit(&ModelConfig::default(), &ev, None).unwrap();
    let c = &m.channels[0];
    assert_eq!(c.name, "EZ0B");
    assert!(c.rms_um < 0.5, "rms {}", c.rms_um);
    assert!(c.chi2_dof < 1.5, "{}", c.chi2_dof);
    // The basis represents the 12/120-min lags: steady-state gain (sum) near 88 um.
    let total: f64 = c.spindle_gains(&m.config).iter().map(|g| g.1).sum();
    assert!((total - 88.0).abs() < 3.0, "total gain {total}");
    // Predicting the day again without observations follows the truth within 1.5 um.
    let mut p = Predictor::new(&m, 0);
    let inputs: Vec<&Event> = ev
        .iter()
        .filter(|e| !matches!(e, Event::Observation { .. }))
        .collect();
    let mut worst: f64 = 0.0;
    let mut k = 0;
    for (t, y) in &truth {
        while k < inputs.len() && inputs[k].t_ns() <= *t {
            p.apply(inputs[k]);
            k += 1;
        }
        let pr = &p.predict(*t)[0];
        worst = worst.max((pr.value - y).abs());
    }
    assert!(worst < 1.5, "worst {worst}");
}

#[test]
fn the_online_filter_from_the_prior_reproduces_the_batch_fit() {
    let (ev, _) = day(10, 0.5, 3);
    let m = fit(&ModelConfig::default(), &ev, None).unwrap();
    let mut p = Predictor::from_prior(&m, 0);
    for e in &ev {
        p.apply(e);
    }
    let online = p.coef("EZ0B").unwrap();
    let batch = &m.channels[0].coef;
    // Compared where it matters: the predicted values over the day.
    let mut f = Features::new(&m.config, &m.t_ref_c, 0);
    let mut worst: f64 = 0.0;
    for e in &ev {
        f.apply(e);
        let r = f.row();
        let a: f64 = r.iter().zip(&online).map(|(x, b)| x * b).sum();
        let b: f64 = r.iter().zip(batch).map(|(x, b)| x * b).sum();
        worst = worst.max((a - b).abs());
    }
    assert!(worst < 1e-6, "online and batch differ by {worst} um");
}

/// A day's fit with one walk for the channel (none learned) and the model's band as it is
/// (unscaled).
fn unscaled_day_model() -> ThermalModel {
    let (ev, _) = day(10, 0.5, 4);
    let cfg = ModelConfig {
        offset_walk_grid_per_h: Vec::new(),
        min_scored: 1000,
        ..Default::default()
    };
    fit(&cfg, &ev, None).unwrap()
}

/// An observation of EZ0B, 20 um +- 0.5, 10 h into the day.
fn ez0b_after_10_h() -> Event {
    Event::Observation {
        t_ns: 600 * MIN,
        channel: "EZ0B".into(),
        value: 20.0,
        sigma: Some(0.5),
    }
}

#[test]
fn uncertainty_grows_without_observations_and_shrinks_with_one() {
    let m = unscaled_day_model();
    assert_eq!(m.channels[0].offset_walk_per_h, None);
    let mut p = Predictor::new(&m, 0);
    let s0 = p.predict(0)[0].sigma;
    let s1 = p.predict(600 * MIN)[0].sigma;
    assert!(s1 > s0, "{s0} -> {s1}");
    // 10 h of offset walk at 1 um^2/h: at least sqrt(10) um.
    assert!(s1 >= 10f64.sqrt(), "{s1}");
    p.apply(&ez0b_after_10_h());
    let s2 = p.predict(600 * MIN)[0].sigma;
    assert!(s2 < 1.0, "{s2}");
    assert!(!p.apply(&Event::Observation {
        t_ns: 600 * MIN,
        channel: "nope".into(),
        value: 1.0,
        sigma: None,
    }));
}

/// A copy of a running predictor (the loop's copy for the API) shares its covariance until
/// one of them takes an observation: the other keeps its own band, to the bit.
#[test]
fn a_copy_keeps_its_band_when_the_original_takes_an_observation() {
    let m = unscaled_day_model();
    let mut p = Predictor::new(&m, 0);
    let mut copy = p.clone();
    let before = copy.predict(600 * MIN)[0].sigma;
    p.apply(&ez0b_after_10_h());
    let corrected = p.predict(600 * MIN)[0].sigma;
    assert!(corrected < 0.5 * before, "{before} -> {corrected}");
    assert_eq!(copy.predict(600 * MIN)[0].sigma.to_bits(), before.to_bits());
    // And the other way round: the copy's observation leaves the original as it was.
    let mut fresh = Predictor::new(&m, 0);
    let untouched = fresh.clone();
    fresh.apply(&ez0b_after_10_h());
    assert_eq!(
        untouched.clone().predict(600 * MIN)[0].sigma.to_bits(),
        before.to_bits()
    );
}

#[test]
fn bad_configurations_and_empty_data_are_named() {
    let cfg = ModelConfig {
        taus_min: vec![0.0],
        ..Default::default()
    };
    assert!(matches!(fit(&cfg, &[], None), Err(ModelError::Config(_))));
    assert!(matches!(
        fit(&ModelConfig::default(), &[], None),
        Err(ModelError::NoData(_))
    ));
    let cfg = ModelConfig {
        temperatures: vec![TemperatureInput {
            sensor: "head".into(),
            taus_min: vec![0.0],
        }],
        ..Default::default()
    };
    let (ev, _) = day(10, 0.5, 5);
    let e = fit(&cfg, &ev, None).unwrap_err().to_string();
    assert!(e.contains("head"), "{e}");
}

#[test]
fn a_model_file_reads_back_and_a_damaged_one_is_refused() {
    let (ev, _) = day(10, 0.5, 5);
    let m = fit(&ModelConfig::default(), &ev, None).unwrap();
    let text = serde_json::to_string(&m).unwrap();
    assert_eq!(ThermalModel::from_json(&text).unwrap(), m);
    let e = ThermalModel::from_json("{}").unwrap_err().to_string();
    assert!(e.contains("not a driftwatch model"), "{e}");
    let mut other = m.clone();
    other.format = "driftwatch.thermal_model.v0".into();
    let e = ThermalModel::from_json(&serde_json::to_string(&other).unwrap())
        .unwrap_err()
        .to_string();
    assert!(e.contains("v0"), "{e}");
    let mut short = m.clone();
    short.channels[0].coef.pop();
    let e = ThermalModel::from_json(&serde_json::to_string(&short).unwrap())
        .unwrap_err()
        .to_string();
    assert!(e.contains("do not match"), "{e}");
}
