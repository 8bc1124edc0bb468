//! The service loop on a simulated machine through a simulated day, on simulated time: no
//! wall clock, hours in seconds.

use crate::common;

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::{DetectionStatus, MachineInfo, MachineStateKind, ResultStatus};
use driftwatch_recording::mcap_io::{ReadOptions, read_file};
use driftwatch_service::daemon::{MachineRuntime, Settings};
use driftwatch_service::link::{LinkError, LinkEvent, MachineLink, Simulated};
use driftwatch_service::recorder::Recorder;
use driftwatch_service::store::{CycleStatus, Store};
use driftwatch_sim::scenario::Scenario;
use driftwatch_thermal::model::Prediction;

const MIN: i64 = 60_000_000_000;

/// A simulated machine whose cycle `bad` has one failed approach.
struct Tamper {
    inner: Simulated,
    bad: i64,
}

impl MachineLink for Tamper {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        let mut ev = self.inner.poll(now_ns);
        for e in &mut ev {
            if let LinkEvent::Detection(d) = e
                && d.msg.cycle == self.bad
                && d.msg.step == "B0C-90/x#1"
            {
                d.msg.status = Some(DetectionStatus::NoTrip);
            }
        }
        ev
    }
    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        self.inner.request_cycle(number, now_ns)
    }
    fn abort_cycle(&mut self, number: i64, now_ns: i64) {
        self.inner.abort_cycle(number, now_ns)
    }
    fn next_event_ns(&self) -> Option<i64> {
        self.inner.next_event_ns()
    }
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("daemon-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[tokio::test]
async fn a_simulated_day_runs_cycles_in_idle_windows_and_serves_only_validated_sets() {
    let d = dir("day");
    let scn = Scenario::load("two_shift").unwrap();
    let k = Kinematics::load(&scn.machine).unwrap();
    let plan = Plan::build(&k, &PlanConfig::load(&scn.plan).unwrap()).unwrap();
    let sim = Simulated::new(k.clone(), plan.clone(), scn.clone()).unwrap();
    let t0 = sim.start_ns();
    let link = Tamper { inner: sim, bad: 3 };
    let store = common::test_store(&d).await;
    let info = MachineInfo {
        machine_id: "sim-1".into(),
        kinematics: k.name.clone(),
        software: "test".into(),
    };
    let recorder = Recorder::new(&d.join("mcap"), info, 256 << 20).unwrap();
    let settings = Settings::default();
    let mut rt = MachineRuntime::new(
        "sim-1",
        k,
        &plan,
        Box::new(link),
        &settings,
        store.clone(),
        recorder,
        t0,
    )
    .await
    .unwrap();
    let (hook_url, hook_seen) = hook_receiver().await;
    let hook: driftwatch_service::webhook::WebhookConfig =
        toml::from_str(&format!("url = \"{hook_url}\"")).unwrap();
    let (notifier, deliveries) =
        driftwatch_service::webhook::Notifier::start(vec![(hook, None)]).unwrap();
    rt.set_notifier(notifier);
    // 31 h: a production day, the night, the next morning's start.
    let end = t0 + 31 * 60 * MIN;
    let mut now = t0;
    let mut versions = Vec::new();
    while now < end {
        let wake = rt.step(now).await.unwrap();
        if let Some(set) = rt.served()
            && versions.last() != Some(&set.version)
        {
            versions.push(set.version);
        }
        now = wake.min(end).max(now + 1);
    }
    rt.shutdown(end).await.unwrap();

    let cycles = store.cycles("sim-1", 1000, None).await.unwrap();
    println!("{} cycles", cycles.len());
    for c in cycles.iter().rev() {
        println!(
            "cycle {:>3} at {:>7.1} min: {:<9} {} {}",
            c.cycle,
            (c.started_ns - t0) as f64 / MIN as f64,
            c.status,
            c.trigger,
            c.reason.clone().unwrap_or_default()
        );
    }
    assert!(cycles.len() >= 10, "{}", cycles.len());
    // No cycle while cutting: each started when the last state reported was idle (the
    // state history read back from the recording).
    let files: Vec<_> = std::fs::read_dir(d.join("mcap").join("sim-1"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert!(
        files.iter().all(|p| p.extension().unwrap() == "mcap"),
        "{files:?}"
    );
    let mut dets = 0;
    let mut results = Vec::new();
    let mut states = Vec::new();
    for f in &files {
        let r = read_file(f, &ReadOptions::default()).unwrap();
        dets += r.detections.len();
        results.extend(r.results.iter().map(|m| m.msg.clone()));
        states.extend(r.states.iter().map(|s| (s.t_ns, s.msg.state)));
    }
    states.sort_by_key(|s| s.0);
    for c in &cycles {
        // The state the NC reported up to the start, other than the cycle's own Measuring.
        let before = states
            .iter()
            .rfind(|s| s.0 <= c.started_ns && s.1 != MachineStateKind::Measuring)
            .unwrap();
        assert_eq!(
            before.1,
            MachineStateKind::Idle,
            "cycle {} started while {:?}",
            c.cycle,
            before.1
        );
    }
    // Every cycle is in SQLite and in MCAP.
    assert_eq!(
        results.len(),
        cycles
            .iter()
            .filter(|c| c.status != CycleStatus::Abandoned)
            .count()
    );
    assert_eq!(dets, 24 * cycles.len());
    // The tampered cycle is rejected with its reason, and the compensation did not move.
    let bad = store.result("sim-1", 3).await.unwrap().unwrap();
    assert_eq!(bad.status, ResultStatus::Rejected);
    assert!(
        bad.reason.as_ref().unwrap().contains("no_trip"),
        "{:?}",
        bad.reason
    );
    // Versions only go up, one per validated cycle.
    let ok = cycles
        .iter()
        .filter(|c| c.status == CycleStatus::Ok)
        .count() as u64;
    assert!(versions.windows(2).all(|w| w[1] > w[0]));
    // One measured set per validated cycle; between cycles, once the model is fitted,
    // predicted sets; every version once, in order.
    let sets = store.compensation_versions("sim-1").await.unwrap();
    let measured = sets.iter().filter(|s| s.1 == "measured").count() as u64;
    let predicted = sets.iter().filter(|s| s.1 == "predicted").count();
    assert_eq!(measured, ok);
    assert!(predicted > 0, "no predicted set");
    println!("{measured} measured and {predicted} predicted sets");
    assert!(sets.iter().enumerate().all(|(i, s)| s.0 == i as i64 + 1));
    assert_eq!(versions.last().copied(), Some(sets.len() as u64));
    // The first predicted set comes after the model's first fit (6 validated cycles).
    let first_pred = sets.iter().position(|s| s.1 == "predicted").unwrap();
    assert!(
        sets[..first_pred]
            .iter()
            .filter(|s| s.1 == "measured")
            .count()
            >= 6
    );
    // EZ0B passes 30 um during production (alert raised) and falls back overnight (resolved).
    // Every alert event as stored, oldest first.
    let mut log = store.alert_events("sim-1", 100_000, None).await.unwrap();
    log.reverse();
    let raised = log
        .iter()
        .find(|e| e.rule == "threshold:EZ0B" && format!("{:?}", e.kind) == "Raised");
    let resolved = log
        .iter()
        .find(|e| e.rule == "threshold:EZ0B" && format!("{:?}", e.kind) == "Resolved");
    assert!(raised.is_some() && resolved.is_some(), "{log:?}");
    assert!(resolved.unwrap().t_ns > raised.unwrap().t_ns);
    // Every alert event reached the webhook, in order.
    rt.set_notifier(Default::default());
    for d in deliveries {
        d.await.unwrap();
    }
    let seen = hook_seen.lock().unwrap().clone();
    let sent: Vec<(u64, String)> = seen
        .iter()
        .map(|v| {
            (
                v["event"]["id"].as_u64().unwrap(),
                v["event"]["kind"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let logged: Vec<(u64, String)> = log
        .iter()
        .map(|e| (e.alert as u64, format!("{:?}", e.kind).to_lowercase()))
        .collect();
    assert_eq!(sent, logged);
    assert!(seen.iter().all(|v| v["machine"] == "sim-1"));
    // The stored series: each sensor whenever its minute's reading changed, and at least
    // every TEMPERATURE_HEARTBEAT_MIN minutes; written in batches, all flushed.
    let samples = store.samples("sim-1", t0, end).await.unwrap();
    let mut per_sensor: std::collections::BTreeMap<String, Vec<(i64, f64)>> = Default::default();
    for s in &samples {
        if let driftwatch_service::store::Sample::Temperature {
            t_ns,
            sensor,
            celsius,
        } = s
        {
            per_sensor
                .entry(sensor.clone())
                .or_default()
                .push((t_ns / MIN, *celsius));
        }
    }
    assert!(!per_sensor.is_empty());
    let beat = driftwatch_machine::machine_core::TEMPERATURE_HEARTBEAT_MIN;
    for (sensor, rows) in &per_sensor {
        assert!(
            rows[0].0 <= t0 / MIN + 1,
            "{sensor} starts late: {:?}",
            rows[0]
        );
        assert!(
            rows.last().unwrap().0 >= end / MIN - beat - 1,
            "{sensor} ends early"
        );
        for w in rows.windows(2) {
            let gap = w[1].0 - w[0].0;
            assert!((1..=beat).contains(&gap), "{sensor}: {w:?}");
            // A repeated value is stored only as the heartbeat.
            assert!(w[1].1 != w[0].1 || gap == beat, "{sensor}: {w:?}");
        }
    }
    assert!(samples.iter().any(
        |s| matches!(s, driftwatch_service::store::Sample::Spindle { rpm, .. } if *rpm > 0.0)
    ));
    // SQLite checks its file; PostgreSQL has no such statement and says so.
    let expected = match store.backend() {
        driftwatch_service::store::Backend::Sqlite => "ok",
        driftwatch_service::store::Backend::Postgres => "not applicable (PostgreSQL)",
    };
    assert_eq!(store.integrity_check().await.unwrap(), expected);
}

/// A webhook receiver that keeps every JSON body it is sent.
async fn hook_receiver() -> (String, Arc<Mutex<Vec<serde_json::Value>>>) {
    let seen: Arc<Mutex<Vec<serde_json::Value>>> = Arc::default();
    let app = axum::Router::new()
        .route(
            "/hook",
            axum::routing::post(
                |axum::extract::State(s): axum::extract::State<
                    Arc<Mutex<Vec<serde_json::Value>>>,
                >,
                 axum::Json(v): axum::Json<serde_json::Value>| async move {
                    s.lock().unwrap().push(v);
                },
            ),
        )
        .with_state(seen.clone());
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", l.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(l, app).await });
    (url, seen)
}

/// A machine that reports itself idle with the spindle stopped, and accepts cycle requests.
struct IdleMachine {
    said: bool,
    requested: Arc<Mutex<Vec<i64>>>,
}

impl MachineLink for IdleMachine {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        if std::mem::replace(&mut self.said, true) {
            return Vec::new();
        }
        vec![
            LinkEvent::State(driftwatch_core::recording::Timed {
                t_ns: now_ns,
                msg: driftwatch_core::recording::StateMsg {
                    state: MachineStateKind::Idle,
                    program: None,
                },
            }),
            LinkEvent::Spindle(driftwatch_core::recording::Timed {
                t_ns: now_ns,
                msg: driftwatch_core::recording::SpindleMsg { rpm: 0.0 },
            }),
        ]
    }
    fn request_cycle(&mut self, number: i64, _now_ns: i64) -> Result<(), LinkError> {
        self.requested.lock().unwrap().push(number);
        Ok(())
    }
    fn abort_cycle(&mut self, _number: i64, _now_ns: i64) {}
    fn next_event_ns(&self) -> Option<i64> {
        None
    }
}

#[tokio::test]
async fn a_restart_remembers_the_last_good_result_and_does_not_measure_for_it() {
    let d = dir("restart");
    let scn = Scenario::load("two_shift").unwrap();
    let k = Kinematics::load(&scn.machine).unwrap();
    let plan = Plan::build(&k, &PlanConfig::load(&scn.plan).unwrap()).unwrap();
    let store = common::test_store(&d).await;
    let info = MachineInfo {
        machine_id: "sim-1".into(),
        kinematics: k.name.clone(),
        software: "test".into(),
    };
    let settings = Settings::default();
    let recorder = || Recorder::new(&d.join("mcap"), info.clone(), 256 << 20).unwrap();
    let sim = Simulated::new(k.clone(), plan.clone(), scn.clone()).unwrap();
    let t0 = sim.start_ns();
    let mut first = MachineRuntime::new(
        "sim-1",
        k.clone(),
        &plan,
        Box::new(sim),
        &settings,
        store.clone(),
        recorder(),
        t0,
    )
    .await
    .unwrap();
    // The shift change's stop (840 min), in the warm-up after lunch.
    let end = t0 + 14 * 60 * MIN;
    let mut now = t0;
    while now < end {
        now = first.step(now).await.unwrap().min(end).max(now + 1);
    }
    first.shutdown(end).await.unwrap();
    let (_, last_good) = store.schedule_memory("sim-1").await.unwrap();
    let last_good = last_good.expect("a good cycle in the first 14 h");
    // What the running model predicted for a minute after the end.
    let before: Vec<Prediction> = {
        let v = first.view.lock().unwrap();
        assert_eq!(v.thermal.model.as_ref().unwrap().status, "fitted");
        let mut p = v
            .thermal
            .predictor
            .as_ref()
            .expect("a fitted model")
            .as_ref()
            .clone();
        p.predict(end + MIN)
    };
    assert!(end - last_good < settings.schedule.max_age_min as i64 * MIN);

    // Restarted a minute later beside an idle machine: the last result is fresh, no cycle.
    let asked = |now: i64| {
        let store = store.clone();
        let (k, plan, settings, rec) = (k.clone(), plan.clone(), settings.clone(), recorder());
        async move {
            let requested = Arc::new(Mutex::new(Vec::new()));
            let link = IdleMachine {
                said: false,
                requested: requested.clone(),
            };
            let mut rt = MachineRuntime::new(
                "sim-1",
                k,
                &plan,
                Box::new(link),
                &settings,
                store,
                rec,
                now,
            )
            .await
            .unwrap();
            rt.step(now).await.unwrap();
            let (schedule, model, prediction) = {
                let v = rt.view.lock().unwrap();
                (
                    v.cycles.schedule.clone(),
                    v.thermal.model.clone(),
                    v.thermal.prediction.clone(),
                )
            };
            rt.shutdown(now + 2).await.unwrap();
            let n = requested.lock().unwrap().len();
            (n, schedule, model, prediction)
        }
    };
    let (n, schedule, model, after) = asked(end + MIN).await;
    // Never for the last good result, which is fresh. The restarted service knows the phase:
    // the warm-up cadence cycle that fell due while the spindle cut runs at this stop, as it
    // would have without the restart.
    assert!(
        n == 0 || (n == 1 && schedule.contains("warm-up cadence")),
        "{n} cycles: {schedule}"
    );
    // The thermal model is back at once, rebuilt from the stored inputs and results, and
    // predicts what the running one did.
    let model = model.expect("a model view");
    assert_eq!(model.status, "fitted", "{}", model.message);
    // On every validated cycle the store holds.
    let ok = store
        .cycles("sim-1", 1000, None)
        .await
        .unwrap()
        .iter()
        .filter(|c| c.status == driftwatch_service::store::CycleStatus::Ok)
        .count();
    assert!(ok >= 5, "{ok} validated cycles");
    let fitted_on = format!("fitted on {ok} validated cycles");
    assert!(model.message.contains(&fitted_on), "{}", model.message);
    assert_eq!(after.len(), before.len());
    for (a, b) in after.iter().zip(&before) {
        println!(
            "{}: before the restart {:.2} +- {:.2}, after {:.2} +- {:.2}",
            a.channel, b.value, b.sigma, a.value, a.sigma
        );
        assert_eq!(a.channel, b.channel);
        assert!(
            (a.value - b.value).abs() < 0.5 * b.sigma.max(a.sigma),
            "{a:?} {b:?}"
        );
    }
    // Past the maximum age a cycle runs.
    let late = last_good + settings.schedule.max_age_min as i64 * MIN + MIN;
    let (n, schedule, ..) = asked(late).await;
    assert_eq!(n, 1, "{schedule}");
    // The stale result, or (the phase being restored) the cycles still owed to the stop the
    // restart above reported, which fell due first.
    assert!(
        schedule.contains("stale")
            || schedule.contains("old")
            || schedule.contains("after the spindle stop"),
        "{schedule}"
    );
    // A clock behind the stored cycles (a simulated day started again) starts afresh: no
    // result is known at that time, so it measures.
    let (n, schedule, ..) = asked(t0 - 60 * MIN).await;
    assert_eq!(n, 1, "{schedule}");
}

/// One simulated machine of the two-shift day on a fresh SQLite store in `d` (the engine whose
/// writes may run on a thread of their own), its writes apart or not.
async fn two_shift(d: &std::path::Path, apart: bool) -> (MachineRuntime, Store, i64) {
    let scn = Scenario::load("two_shift").unwrap();
    let k = Kinematics::load(&scn.machine).unwrap();
    let plan = Plan::build(&k, &PlanConfig::load(&scn.plan).unwrap()).unwrap();
    let sim = Simulated::new(k.clone(), plan.clone(), scn).unwrap();
    let t0 = sim.start_ns();
    let store = Store::open(&d.join("driftwatch.db")).await.unwrap();
    let info = MachineInfo {
        machine_id: "sim-1".into(),
        kinematics: k.name.clone(),
        software: "test".into(),
    };
    let recorder = Recorder::new(&d.join("mcap"), info, 256 << 20).unwrap();
    let mut rt = MachineRuntime::new(
        "sim-1",
        k,
        &plan,
        Box::new(sim),
        &Settings::default(),
        store.clone(),
        recorder,
        t0,
    )
    .await
    .unwrap();
    if apart {
        rt.write_apart().unwrap();
        assert!(rt.writes_are_apart());
    }
    (rt, store, t0)
}

/// The newest set version the store holds (0: none), read through the store's readers.
async fn newest_stored(store: &Store) -> u64 {
    let sets = store.compensation_versions("sim-1").await.unwrap();
    sets.last().map_or(0, |s| s.0 as u64)
}

/// Everything the store and the recording hold of a run, as text to compare.
async fn holdings(d: &std::path::Path, store: &Store, t0: i64, end: i64) -> Vec<String> {
    let mut out = vec![format!(
        "{:?}",
        store.compensation_versions("sim-1").await.unwrap()
    )];
    for c in store.cycles("sim-1", 1000, None).await.unwrap() {
        out.push(format!(
            "{} {} {:?} {:?}",
            c.cycle, c.started_ns, c.status, c.reason
        ));
    }
    out.push(format!(
        "{:?}",
        store.samples("sim-1", t0, end).await.unwrap()
    ));
    let mut log = store.alert_events("sim-1", 100_000, None).await.unwrap();
    log.reverse();
    out.extend(log.iter().map(|e| format!("{e:?}")));
    let mut files: Vec<_> = std::fs::read_dir(d.join("mcap").join("sim-1"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    for f in &files {
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        out.push(format!("{name}: {}", std::fs::read(f).unwrap().len()));
        out.push(format!(
            "{:?}",
            read_file(f, &ReadOptions::default()).unwrap()
        ));
    }
    out
}

/// The writes on a thread of their own store and record what the loop's own thread does, byte
/// for byte, and the API is never shown a set the store does not hold yet.
#[tokio::test]
async fn writes_apart_store_and_record_what_inline_writes_do() {
    let mut runs = Vec::new();
    for apart in [false, true] {
        let d = dir(if apart {
            "writes-apart"
        } else {
            "writes-inline"
        });
        let (mut rt, store, t0) = two_shift(&d, apart).await;
        let end = t0 + 26 * 60 * MIN;
        let mut now = t0;
        let mut shown = 0;
        while now < end {
            let wake = rt.step(now).await.unwrap();
            // Read in this order, a set shown is one stored before it was looked at.
            let served = rt.served().map_or(0, |s| s.version);
            let stored = newest_stored(&store).await;
            assert!(
                served <= stored,
                "apart {apart}: version {served} shown, the store holds up to {stored}"
            );
            shown = shown.max(served);
            now = wake.min(end).max(now + 1);
        }
        rt.shutdown(end).await.unwrap();
        assert!(shown > 10, "apart {apart}: only {shown} sets shown");
        assert_eq!(
            rt.served().map(|s| s.version),
            Some(newest_stored(&store).await)
        );
        runs.push(holdings(&d, &store, t0, end).await);
        store.close().await;
    }
    assert_eq!(runs[0].len(), runs[1].len());
    for (a, b) in runs[0].iter().zip(&runs[1]) {
        assert_eq!(a, b);
    }
}

/// Writes that fail (the store refuses the sets, as a full disk would), on the loop's thread
/// and apart: the loop's step fails and says why (apart: its next step), no set the store does
/// not hold is shown, and when the store takes writes again the held ones are stored in order
/// and the newest is shown.
#[tokio::test]
async fn writes_that_fail_hold_the_loop_and_lose_nothing() {
    for apart in [false, true] {
        writes_that_fail(apart).await;
    }
}

async fn writes_that_fail(apart: bool) {
    let d = dir(&format!("writes-fail-apart-{apart}"));
    let (mut rt, store, t0) = two_shift(&d, apart).await;
    assert_eq!(rt.writes_are_apart(), apart);
    let db = d.join("driftwatch.db");
    let mut now = t0;
    while newest_stored(&store).await < 3 {
        let wake = rt.step(now).await.unwrap();
        now = wake.max(now + 1);
        assert!(now < t0 + 12 * 60 * MIN, "no third set by noon");
    }
    rt.settle_writes(now).await.unwrap();
    let before = newest_stored(&store).await;
    common::refuse_inserts(&db, &["compensation_sets"], "sim-1", true).await;
    // Steps go on until one fails: the writer's failure reaches the loop.
    let mut failed = None;
    for _ in 0..10_000 {
        match rt.step(now).await {
            Ok(wake) => now = wake.max(now + 1),
            Err(e) => {
                failed = Some(e.to_string());
                break;
            }
        }
        let served = rt.served().map_or(0, |s| s.version);
        assert!(served <= newest_stored(&store).await);
    }
    let failed = failed.expect("a step failed while the store refused the sets");
    assert!(failed.contains("injected fault"), "{failed}");
    assert_eq!(newest_stored(&store).await, before);
    assert_eq!(rt.served().map(|s| s.version), Some(before));
    // Still failing: a step tries the held write again, and fails again.
    now += MIN;
    assert!(rt.step(now).await.is_err());
    assert_eq!(rt.served().map(|s| s.version), Some(before));
    {
        let v = rt.view.lock().unwrap();
        assert!(
            v.open_alerts.iter().any(|a| a.rule == "loop_fault"),
            "{:?}",
            v.open_alerts
        );
    }

    common::refuse_inserts(&db, &["compensation_sets"], "sim-1", false).await;
    now += MIN;
    rt.step(now).await.unwrap();
    rt.settle_writes(now).await.unwrap();
    let after = newest_stored(&store).await;
    assert!(after > before, "the held sets were stored");
    assert_eq!(rt.served().map(|s| s.version), Some(after));
    let sets = store.compensation_versions("sim-1").await.unwrap();
    assert!(sets.iter().enumerate().all(|(i, s)| s.0 == i as i64 + 1));
    rt.shutdown(now).await.unwrap();
    assert!(
        !rt.view
            .lock()
            .unwrap()
            .open_alerts
            .iter()
            .any(|a| a.rule == "loop_fault")
    );
    store.close().await;
}
