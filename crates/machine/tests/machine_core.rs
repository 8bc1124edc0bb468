//! The machine core driven by plain calls: no runtime, no database, no recorder. Each test
//! plays the executor: it feeds inputs, looks at the effects in their order, and answers the
//! two effects that have an answer (a cycle request, a solve).

use std::sync::Arc;

use driftwatch_core::cycle::{CycleChecks, plan_measurements};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::{
    DetectionMsg, MachineStateKind, ResultStatus, SpindleMsg, StateMsg, TemperatureMsg, Timed,
};
use driftwatch_core::units::NS_PER_MIN;
use driftwatch_machine::link_event::LinkEvent;
use driftwatch_machine::machine_core::{
    Effect, Input, MachineCore, Record, Restored, Sample, Settings, SolveJob,
    TEMPERATURE_HEARTBEAT_MIN,
};

const T0: i64 = 1_700_000_000_000_000_000;

fn min(m: i64) -> i64 {
    T0 + m * NS_PER_MIN
}

struct Rig {
    core: MachineCore,
    plan: Plan,
    tool: String,
}

/// A core of `table_bc` on the patent plan with `settings`, started from `restored`.
fn rig_using(settings: &Settings, restored: Restored) -> Rig {
    let k = Kinematics::load("table_bc").unwrap();
    let plan = Plan::build(&k, &PlanConfig::load("patent").unwrap()).unwrap();
    let mut checks = CycleChecks::new(&k);
    checks.expected = Some(plan_measurements(&plan));
    let tool = k.tool_id.clone();
    let (core, _) = MachineCore::new(
        Arc::new(k),
        checks,
        plan.steps.len(),
        settings,
        restored,
        T0,
    )
    .unwrap();
    Rig { core, plan, tool }
}

fn rig_with(restored: Restored) -> Rig {
    let mut settings = Settings::default();
    // The thermal model has its own tests; here it would only add predicted sets.
    settings.prediction.enabled = false;
    rig_using(&settings, restored)
}

fn rig() -> Rig {
    rig_with(Restored {
        next_cycle: 1,
        ..Default::default()
    })
}

fn idle(t_ns: i64) -> Input {
    Input::Link(LinkEvent::State(Timed {
        t_ns,
        msg: StateMsg {
            state: MachineStateKind::Idle,
            program: None,
        },
    }))
}

/// Every step of the plan read where the nominal machine puts it, but for a few tenths of a
/// micrometre that differ from step to step (a solver's fit is not exact).
fn readings(rig: &Rig, cycle: i64, t_ns: i64) -> Vec<Input> {
    rig.plan
        .steps
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let mut pos = s.start;
            pos[s.approach.axis.index()] = s.expected + 3e-4 * ((i * 7 % 5) as f64 - 2.0);
            Input::Link(LinkEvent::Detection(Timed {
                t_ns: t_ns + i as i64 * 1_000_000_000,
                msg: DetectionMsg {
                    cycle,
                    step: s.label.clone(),
                    b_deg: s.b_deg,
                    c_deg: s.c_deg,
                    axis: s.approach.axis,
                    direction: s.approach.direction,
                    feed_mm_min: s.approach.feed_mm_min,
                    spindle_rpm: 0.0,
                    tool_id: rig.tool.clone(),
                    x_mm: pos.x,
                    y_mm: pos.y,
                    z_mm: pos.z,
                    status: None,
                },
            }))
        })
        .collect()
}

fn feed(core: &mut MachineCore, inputs: impl IntoIterator<Item = Input>, now: i64) -> Vec<Effect> {
    inputs
        .into_iter()
        .flat_map(|i| core.handle(i, now))
        .collect()
}

fn requested(effects: &[Effect]) -> Option<i64> {
    effects.iter().find_map(|e| match e {
        Effect::RequestCycle { number } => Some(*number),
        _ => None,
    })
}

fn solve_job(effects: &[Effect]) -> Option<&SolveJob> {
    effects.iter().find_map(|e| match e {
        Effect::Solve(j) => Some(j.as_ref()),
        _ => None,
    })
}

fn position(effects: &[Effect], f: impl Fn(&Effect) -> bool) -> Option<usize> {
    effects.iter().position(f)
}

/// An operator's request at `at` min, answered by the machine with `answer`; the effects of
/// the step and of the answer.
fn ask(rig: &mut Rig, at: i64, answer: Result<(), String>) -> (Option<i64>, Vec<Effect>) {
    let now = min(at);
    let mut fx = feed(
        &mut rig.core,
        [
            idle(now),
            Input::Request {
                by: "operator".into(),
            },
            Input::Tick,
        ],
        now,
    );
    let number = requested(&fx);
    if let Some(number) = number {
        fx.extend(rig.core.handle(
            Input::CycleRequested {
                number,
                result: answer,
            },
            now,
        ));
    }
    (number, fx)
}

/// Run cycle `number` to its end at `at` min; the effects up to the solve, then after it.
fn run_cycle(rig: &mut Rig, number: i64, at: i64) -> (Vec<Effect>, Vec<Effect>) {
    let now = min(at);
    let mut inputs = readings(rig, number, now);
    inputs.push(Input::Link(LinkEvent::CycleDone {
        cycle: number,
        t_ns: now + NS_PER_MIN,
    }));
    let before = feed(&mut rig.core, inputs, now + NS_PER_MIN);
    let job = solve_job(&before)
        .expect("a finished cycle is solved")
        .clone();
    let after = rig.core.handle(
        Input::Solved {
            number,
            outcome: Box::new(Ok(job.run())),
            seconds: 0.01,
        },
        now + NS_PER_MIN,
    );
    (before, after)
}

#[test]
fn a_requested_cycle_is_opened_solved_stored_and_only_then_served() {
    let mut rig = rig();
    let (number, fx) = ask(&mut rig, 0, Ok(()));
    assert_eq!(number, Some(1));
    let open = position(&fx, |e| matches!(e, Effect::OpenCycle { number: 1, .. }));
    let shown = position(&fx, |e| matches!(e, Effect::PublishView));
    assert!(open.is_some() && open < shown, "{fx:#?}");
    assert_eq!(rig.core.view().cycles.open, Some(1));
    assert!(
        rig.core
            .view()
            .cycles
            .schedule
            .starts_with("cycle 1 started")
    );

    let (before, after) = run_cycle(&mut rig, 1, 1);
    let stored = position(
        &before,
        |e| matches!(e, Effect::StoreDetections { number: 1, rows } if rows.len() == rig.plan.steps.len()),
    );
    let solve = position(&before, |e| matches!(e, Effect::Solve(_)));
    assert!(stored.is_some() && stored < solve, "{before:#?}");
    // Every detection is recorded as it arrives.
    let recorded = before
        .iter()
        .filter(|e| matches!(e, Effect::Record(r) if matches!(**r, Record::Detection(_))))
        .count();
    assert_eq!(recorded, rig.plan.steps.len());

    let close = position(
        &after,
        |e| matches!(e, Effect::CloseCycle { result, set: Some(_), .. } if result.status == ResultStatus::Ok),
    );
    let shown = position(&after, |e| matches!(e, Effect::PublishView));
    assert!(close.is_some() && close < shown, "{after:#?}");
    let served = rig
        .core
        .view()
        .compensation
        .as_ref()
        .expect("a set is served");
    assert_eq!(served.version, 1);
    assert_eq!(served.cycle, Some(1));
    assert_eq!(rig.core.view().cycles.ok, 1);
    assert_eq!(rig.core.view().cycles.last, Some(1));
}

#[test]
fn a_refused_request_opens_nothing_and_the_next_step_asks_again_with_the_same_number() {
    let mut rig = rig();
    let (number, fx) = ask(&mut rig, 0, Err("not idle".into()));
    assert_eq!(number, Some(1));
    assert!(!fx.iter().any(|e| matches!(e, Effect::OpenCycle { .. })));
    assert_eq!(rig.core.open_cycle(), None);
    let schedule = &rig.core.view().cycles.schedule;
    assert!(
        schedule.contains("the machine refused: not idle"),
        "{schedule}"
    );
    let again = feed(&mut rig.core, [Input::Tick], min(1));
    assert_eq!(requested(&again), Some(1));
}

/// The schedule line says the reason to wait again after a refused request said something
/// else, though the reason is the one it said before (it is formatted only when it changed).
#[test]
fn the_schedule_line_says_the_reason_to_wait_again_after_a_refusal() {
    let mut rig = rig();
    let cutting = |t_ns| {
        Input::Link(LinkEvent::State(Timed {
            t_ns,
            msg: StateMsg {
                state: MachineStateKind::Cutting,
                program: None,
            },
        }))
    };
    let schedule = |rig: &Rig| rig.core.view().cycles.schedule.clone();
    for at in [0, 10] {
        ask(&mut rig, at, Err("not idle".into()));
        assert!(
            schedule(&rig).contains("the machine refused"),
            "{}",
            schedule(&rig)
        );
        feed(
            &mut rig.core,
            [cutting(min(at + 1)), Input::Tick],
            min(at + 1),
        );
        assert!(
            schedule(&rig).contains("the NC is cutting"),
            "{}",
            schedule(&rig)
        );
    }
}

#[test]
fn a_failed_solve_abandons_the_cycle_with_its_reason_and_a_retry_follows() {
    let mut rig = rig();
    ask(&mut rig, 0, Ok(()));
    let mut inputs = readings(&rig, 1, min(1));
    inputs.push(Input::Link(LinkEvent::CycleDone {
        cycle: 1,
        t_ns: min(2),
    }));
    feed(&mut rig.core, inputs, min(2));
    let fx = rig.core.handle(
        Input::Solved {
            number: 1,
            outcome: Box::new(Err("the solver panicked".into())),
            seconds: 0.0,
        },
        min(2),
    );
    assert!(
        fx.iter().any(|e| matches!(e, Effect::AbandonCycle { number: 1, reason, .. } if reason.contains("the solver panicked"))),
        "{fx:#?}"
    );
    assert!(!fx.iter().any(|e| matches!(e, Effect::CloseCycle { .. })));
    assert_eq!(rig.core.view().cycles.abandoned, 1);
    assert!(rig.core.view().compensation.is_none());
    // The retry waits for the spacing between starts (10 min by default), then runs.
    assert_eq!(requested(&feed(&mut rig.core, [Input::Tick], min(5))), None);
    assert_eq!(
        requested(&feed(&mut rig.core, [Input::Tick], min(11))),
        Some(2)
    );
}

#[test]
fn a_cycle_that_times_out_is_aborted_at_the_machine_and_abandoned() {
    let mut rig = rig();
    ask(&mut rig, 0, Ok(()));
    let some = readings(&rig, 1, min(1)).into_iter().take(3);
    feed(&mut rig.core, some, min(1));
    assert_eq!(requested(&feed(&mut rig.core, [Input::Tick], min(4))), None);
    let fx = feed(&mut rig.core, [Input::Tick], min(5));
    let abort = position(&fx, |e| matches!(e, Effect::AbortCycle { number: 1 }));
    let kept = position(
        &fx,
        |e| matches!(e, Effect::StoreDetections { number: 1, rows } if rows.len() == 3),
    );
    let abandon = position(&fx, |e| matches!(e, Effect::AbandonCycle { number: 1, .. }));
    assert!(abort < kept && kept < abandon && abort.is_some(), "{fx:#?}");
    assert_eq!(rig.core.open_cycle(), None);
    // A detection of the abandoned cycle is recorded but changes nothing.
    let late = readings(&rig, 1, min(6)).remove(3);
    let fx = rig.core.handle(late, min(6));
    assert!(
        matches!(fx.as_slice(), [Effect::Record(_), Effect::Log(..)]),
        "{fx:#?}"
    );
}

#[test]
fn cycle_numbers_continue_from_the_store_and_a_restart_does_not_measure_for_its_own_sake() {
    let mut rig = rig_with(Restored {
        next_cycle: 42,
        last_start_ns: Some(min(-20)),
        last_good_ns: Some(min(-19)),
        ..Default::default()
    });
    // Idle with nothing due: no cycle.
    let fx = feed(&mut rig.core, [idle(min(0)), Input::Tick], min(0));
    assert_eq!(requested(&fx), None, "{fx:#?}");
    let (number, _) = ask(&mut rig, 1, Ok(()));
    assert_eq!(number, Some(42));
    run_cycle(&mut rig, 42, 1);
    assert_eq!(rig.core.view().cycles.last, Some(42));
    assert_eq!(ask(&mut rig, 20, Ok(())).0, Some(43));
}

#[test]
fn shutdown_during_a_cycle_stores_what_came_and_abandons_it() {
    let mut rig = rig();
    ask(&mut rig, 0, Ok(()));
    let some = readings(&rig, 1, min(1)).into_iter().take(2);
    feed(&mut rig.core, some, min(1));
    let fx = rig.core.handle(Input::Shutdown, min(2));
    assert!(
        matches!(
            fx.as_slice(),
            [
                Effect::AbortCycle { number: 1 },
                Effect::StoreDetections { number: 1, .. },
                Effect::AbandonCycle { number: 1, .. }
            ]
        ),
        "{fx:#?}"
    );
}

#[test]
fn samples_are_stored_in_ten_minute_batches_and_a_steady_temperature_as_a_heartbeat() {
    let mut rig = rig();
    let mut batches = Vec::new();
    for m in 0..=40 {
        let t = min(m);
        let fx = feed(
            &mut rig.core,
            [
                Input::Link(LinkEvent::Spindle(Timed {
                    t_ns: t,
                    msg: SpindleMsg {
                        rpm: if m < 20 { 1000.0 } else { 2000.0 },
                    },
                })),
                Input::Link(LinkEvent::Temperature(Timed {
                    t_ns: t,
                    msg: TemperatureMsg {
                        sensor: "hall".into(),
                        celsius: 20.0,
                    },
                })),
            ],
            t,
        );
        batches.extend(fx.into_iter().filter_map(|e| match e {
            Effect::StoreSamples(rows) => Some(rows),
            _ => None,
        }));
    }
    // A batch is stored once it spans ten minutes of machine time: minutes 0-10, 10-20,
    // 20-30 and 30-40 (the sample that closes a batch is its last; the temperature read at
    // the same minute opens the next).
    assert_eq!(batches.len(), 4, "{batches:#?}");
    let all: Vec<&Sample> = batches.iter().flatten().collect();
    let spindle = all
        .iter()
        .filter(|s| matches!(s, Sample::Spindle { .. }))
        .count();
    let temps: Vec<i64> = all
        .iter()
        .filter_map(|s| match s {
            Sample::Temperature { t_ns, .. } => Some((t_ns - T0) / NS_PER_MIN),
            _ => None,
        })
        .collect();
    // One spindle sample a minute (every minute is a new (minute, speed) pair).
    assert_eq!(spindle, 41);
    // The same temperature at the first minute and then every heartbeat.
    let beat = TEMPERATURE_HEARTBEAT_MIN;
    assert_eq!(temps, vec![0, beat, 2 * beat, 3 * beat]);
    // The one read at minute 40 is held for the next batch.
}

/// A verification that exceeds raises the `verification` alert (logged, stored, shown in the
/// view); a later one within the combined sigma resolves it.
#[test]
fn a_verification_that_exceeds_raises_an_alert_and_one_within_resolves_it() {
    use driftwatch_core::error_name::ErrorName;
    use driftwatch_core::recording::CycleResultMsg;
    use driftwatch_machine::alerts::EventKind;
    use driftwatch_machine::verification::{ReferenceResult, compare};
    let mut rig = rig();
    let r0 = rig.core.view().alerts_revision;
    let setter = CycleResultMsg {
        cycle: 3,
        t_ns: min(10),
        status: ResultStatus::Ok,
        reason: None,
        errors: Some([("EZ0B".to_string(), 12.0)].into()),
        sigma: Some([("EZ0B".to_string(), 0.4)].into()),
        residual_rms_um: None,
        chi2: None,
        dof: None,
        n_detections: None,
        nuisance: None,
        redundancy_um: None,
        chi2_point: None,
        geometry: None,
        notes: None,
    };
    let verify = |t: i64, ez0b: f64| {
        let r = ReferenceResult {
            instrument: "rtest".into(),
            t_ns: t,
            errors: [("EZ0B".to_string(), ez0b)].into(),
            sigma: [("EZ0B".to_string(), 0.3)].into(),
            frame_note: None,
            source: None,
        };
        let names = [ErrorName::parse("EZ0B").unwrap()];
        r.validate(&names, min(30)).unwrap();
        compare(
            "m1",
            &r,
            std::slice::from_ref(&setter),
            60 * NS_PER_MIN,
            2.0,
        )
        .unwrap()
    };
    let out = rig.core.handle(
        Input::Verification(Box::new(verify(min(12), 14.0))),
        min(30),
    );
    let alerts: Vec<_> = out
        .iter()
        .filter_map(|e| match e {
            Effect::Alert(a) => Some(a.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(alerts.len(), 1, "{out:?}");
    assert_eq!(
        (alerts[0].rule.as_str(), alerts[0].kind),
        ("verification", EventKind::Raised)
    );
    assert_eq!(alerts[0].cycle, 3);
    assert!((alerts[0].value - 4.0).abs() < 1e-9, "{}", alerts[0].value);
    assert!(
        alerts[0].message.contains("EZ0B +2.00 um (z +4.00"),
        "{}",
        alerts[0].message
    );
    assert!(
        matches!(out.first(), Some(Effect::Log(_, m)) if m.starts_with("verification: rtest differs"))
    );
    // The view goes out, and the alert state is kept after the event that changed it.
    assert!(out.iter().any(|e| matches!(e, Effect::PublishView)));
    assert!(matches!(out.last(), Some(Effect::StoreAlertState { .. })));
    assert_eq!(rig.core.view().open_alerts[0].rule, "verification");
    // The alerts' revision moves with the alerts, not with every step: the loop copies them
    // for the API only when it moved.
    let r1 = rig.core.view().alerts_revision;
    assert!(r1 > r0);
    let cutting = Input::Link(LinkEvent::State(Timed {
        t_ns: min(30),
        msg: StateMsg {
            state: MachineStateKind::Cutting,
            program: None,
        },
    }));
    let out = feed(&mut rig.core, [cutting, Input::Tick], min(30) + 1);
    assert!(
        out.iter().any(|e| matches!(e, Effect::PublishView)),
        "{out:?}"
    );
    assert_eq!(rig.core.view().alerts_revision, r1);
    let out = rig.core.handle(
        Input::Verification(Box::new(verify(min(13), 12.2))),
        min(31),
    );
    assert!(
        out.iter()
            .any(|e| matches!(e, Effect::Alert(a) if a.kind == EventKind::Resolved)),
        "{out:?}"
    );
    assert!(rig.core.view().open_alerts.is_empty());
    assert!(rig.core.view().alerts_revision > r1);
}

/// A core started from a model fitted on an earlier day of every error (a 12-min lag seen
/// every 30 min), the schedule's tool-tip limit `tip_sigma_um`.
fn rig_with_model(tip_sigma_um: f64) -> Rig {
    use driftwatch_thermal::model::Event;
    let k = Kinematics::load("table_bc").unwrap();
    let lag = |t: i64| 40.0 * (1.0 - (-(t as f64) / (12.0 * NS_PER_MIN as f64)).exp());
    let mut earlier = vec![Event::Spindle {
        t_ns: 0,
        rpm: 20000.0,
    }];
    for i in 0..8 {
        let t = (i * 30 + 5) * NS_PER_MIN;
        for name in k.identify_names() {
            earlier.push(Event::Observation {
                t_ns: t,
                channel: name,
                value: lag(t),
                sigma: Some(0.3),
            });
        }
    }
    let model = driftwatch_thermal::model::fit(&Default::default(), &earlier, None).unwrap();
    let mut settings = Settings {
        initial_model: Some(Arc::new(model)),
        ..Default::default()
    };
    settings.schedule.tip_sigma_um = tip_sigma_um;
    // Each error's own limit would ask for a cycle too (the model is a day's walk away from
    // its data): out of the way of the rule under test.
    settings.prediction.cycle_above_sigma_um = 1e6;
    settings.prediction.cycle_above_sigma_urad = 1e6;
    rig_using(
        &settings,
        Restored {
            next_cycle: 7,
            // The last cycle (20 min before) gave no good result: no look since one has
            // shown the band a measurement leaves, and the rule is in charge from the first.
            last_start_ns: Some(min(-20)),
            last_good_ns: None,
            ..Default::default()
        },
    )
}

/// The spindle starts on an idle NC: the warm-up cadence's first cycle is due at once. With
/// the model's tool-tip band in charge it is not, unless that band is over its limit; the
/// cadence-only schedule keeps it.
#[test]
fn the_model_tool_tip_band_orders_cycles_in_place_of_the_cadence() {
    let start = |rig: &mut Rig| {
        let now = min(0);
        let spin = Input::Link(LinkEvent::Spindle(Timed {
            t_ns: now,
            msg: SpindleMsg { rpm: 20000.0 },
        }));
        let fx = feed(&mut rig.core, [idle(now), spin, Input::Tick], now);
        let number = requested(&fx);
        if let Some(number) = number {
            rig.core.handle(
                Input::CycleRequested {
                    number,
                    result: Ok(()),
                },
                now,
            );
        }
        (number, rig.core.view().cycles.schedule.clone())
    };
    let (n, why) = start(&mut rig_with_model(0.0));
    assert_eq!(n, Some(7), "{why}");
    assert!(why.contains("warm-up cadence"), "{why}");
    let (n, why) = start(&mut rig_with_model(1e6));
    assert_eq!((n, why.as_str()), (None, "nothing due"));
    let (n, why) = start(&mut rig_with_model(1e-6));
    assert_eq!(n, Some(7), "{why}");
    assert!(why.contains("tool tip is uncertain"), "{why}");
}

/// Before the model can predict, a look that changes nothing leaves the thermal view's
/// revision where it was (the executor copies the view only when it moved); a change of the
/// model (its first input) still moves it.
#[test]
fn a_look_without_a_prediction_moves_the_thermal_view_only_when_the_model_changed() {
    let settings = Settings::default();
    assert!(settings.prediction.enabled);
    let Rig { mut core, .. } = rig_using(
        &settings,
        Restored {
            next_cycle: 1,
            ..Default::default()
        },
    );
    let revision = |c: &MachineCore| c.view().thermal.revision;
    feed(&mut core, [Input::Tick], min(0));
    let first = revision(&core);
    for m in 1..=5 {
        feed(&mut core, [Input::Tick], min(m));
        assert_eq!(revision(&core), first, "an empty look at minute {m}");
    }
    let temperature = Input::Link(LinkEvent::Temperature(Timed {
        t_ns: min(6),
        msg: TemperatureMsg {
            sensor: "spindle".into(),
            celsius: 21.0,
        },
    }));
    feed(&mut core, [temperature, Input::Tick], min(6));
    assert!(revision(&core) > first, "the model's first input is shown");
}
