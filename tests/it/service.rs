//! The service as `driftwatch serve` starts it: through `launch`, on a listener bound to port 0
//! that the test keeps, with a manual clock that the test moves (hours of a plant day in
//! seconds, nothing sleeps on the wall clock to pass).

use crate::common;

use common::{MIN, TestService, config, launch_test, refuse_inserts, scratch};
use driftwatch_service::config::ServiceConfig;
use driftwatch_service::store::Store;

/// The shipped default with its simulated machine twice (sim-1, sim-2), on one store in `dir`.
fn two_machines(dir: &std::path::Path) -> ServiceConfig {
    let mut cfg = config(dir);
    let mut second = cfg.machines[0].clone();
    assert_eq!(cfg.machines[0].id, "sim-1");
    second.id = "sim-2".into();
    cfg.machines.push(second);
    cfg
}

fn view_of(t: &TestService, id: &str) -> driftwatch_service::daemon::MachineView {
    t.svc.views[id].lock().unwrap().clone()
}

/// The tables a machine loop writes as it runs: samples and cycles.
const LOOP_TABLES: [&str; 3] = ["spindle_samples", "temperature_samples", "cycles"];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_machine_whose_store_fails_stops_neither_the_others_nor_the_api() {
    let dir = scratch("service-store-fault");
    let db = dir.join("driftwatch.db");
    // The schema first, then the fault: sim-2's samples and cycles may not be written.
    Store::open(&db).await.unwrap().close().await;
    refuse_inserts(&db, &LOOP_TABLES, "sim-2", true).await;

    let svc = launch_test(two_machines(&dir), None).await;
    let t0 = svc.t0();
    // Six hours of the plant day, ten minutes at a time; only sim-1 must keep up.
    for k in 1..=36 {
        svc.run_to_for(t0 + k * 10 * MIN, &["sim-1"]).await;
        // The API answers throughout.
        let (code, _, body) = svc.call(get("/api/v1/machines")).await;
        assert_eq!(code, 200, "{body}");
    }
    let one = view_of(&svc, "sim-1");
    let two = view_of(&svc, "sim-2");
    assert!(
        one.cycles.ok >= 5,
        "sim-1 keeps cycling: {} validated cycles",
        one.cycles.ok
    );
    assert!(one.compensation.is_some(), "sim-1 serves a set");
    assert_eq!(
        one.health.faults, 0,
        "sim-1 has no fault: {:?}",
        one.health.last_fault
    );
    assert!(two.health.faults > 0, "sim-2's failed writes are counted");
    assert!(
        two.health
            .last_fault
            .as_ref()
            .is_some_and(|(_, f)| f.contains("injected fault")),
        "sim-2 says why: {:?}",
        two.health.last_fault
    );
    assert_eq!(two.cycles.ok, 0, "sim-2 could not store a cycle");

    // /metrics counts the faults by machine.
    let (code, metrics) = svc.text("/metrics").await;
    assert_eq!(code, 200);
    let faults = |id: &str| -> f64 {
        let key = format!("driftwatch_machine_faults_total{{machine=\"{id}\"}} ");
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(&key)?.parse().ok())
            .unwrap_or_else(|| panic!("no {key} in /metrics:\n{metrics}"))
    };
    assert_eq!(faults("sim-1"), 0.0);
    assert!(faults("sim-2") >= 1.0);
    // The machine's own page answers too, with the fault.
    let (code, _, v) = svc.call(get("/api/v1/machines/sim-2")).await;
    assert_eq!(code, 200, "{v}");
    assert!(v.to_string().contains("injected fault"), "{v}");

    // The store heals: sim-2 catches up by itself (its retries), and keeps going.
    refuse_inserts(&db, &LOOP_TABLES, "sim-2", false).await;
    let t_heal = t0 + 36 * 10 * MIN;
    for k in 1..=18 {
        svc.run_to(t_heal + k * 10 * MIN).await;
    }
    let healed = view_of(&svc, "sim-2");
    assert!(!healed.health.failing, "sim-2's steps succeed again");
    let (t_fault, _) = healed.health.last_fault.clone().unwrap();
    assert!(
        t_fault <= t_heal,
        "no step fails after the store heals: the last failure at {:.1} min, healed at {:.1} min",
        (t_fault - t0) as f64 / MIN as f64,
        (t_heal - t0) as f64 / MIN as f64
    );
    let two = healed;
    assert!(
        two.cycles.ok >= 1,
        "sim-2 cycles again after the store heals"
    );

    // A graceful stop: the loops close their recordings and the server its connections.
    svc.stop().await;
    let store = Store::open(&db).await.unwrap();
    assert!(store.open_cycles("sim-1").await.unwrap().is_empty());
    // Nothing of the fault window was lost: the failed writes waited at the head of sim-2's
    // queue, and its machine's reports behind them, until the store healed. Both machines
    // run the same simulated day, so each stored a temperature sample of each sensor at the
    // same minutes (the values differ where sim-1's cycles spun its spindle and sim-2's could
    // not run).
    let minutes = |id: &'static str| {
        let store = &store;
        async move {
            store
                .samples(id, t0, t_heal)
                .await
                .unwrap()
                .into_iter()
                .filter_map(|s| match s {
                    driftwatch_service::store::Sample::Temperature { t_ns, sensor, .. } => {
                        Some((t_ns, sensor))
                    }
                    _ => None,
                })
                .collect::<Vec<_>>()
        }
    };
    let (one, two) = (minutes("sim-1").await, minutes("sim-2").await);
    assert!(
        one.len() > 300,
        "{} temperature samples in six hours",
        one.len()
    );
    assert!(
        one == two,
        "sim-1 stored {} temperature samples, sim-2 {}",
        one.len(),
        two.len()
    );
    store.close().await;
}

fn get(uri: &str) -> axum::http::Request<axum::body::Body> {
    axum::http::Request::get(uri)
        .body(axum::body::Body::empty())
        .unwrap()
}

/// `config/fleet.toml` as shipped: four simulated machines of four families in one service.
/// Each runs its own plan, fits its own thermal model and serves compensation in its own names
/// and NC offsets; an alert rule on an error a machine does not identify is refused at start,
/// naming both.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_shipped_fleet_runs_four_families_each_serving_its_own_compensation() {
    let dir = scratch("service-fleet");
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/fleet.toml");
    let mut cfg = ServiceConfig::load(Some(&path)).unwrap();
    cfg.data_dir = dir.clone();
    cfg.http.tokens.clear();
    let families: Vec<(String, String)> = cfg
        .machines
        .iter()
        .map(|m| (m.id.clone(), m.machine.clone()))
        .collect();
    assert_eq!(families.len(), 4);

    // A service-wide rule on table_bc's EZ0B given to the trunnion is refused at start.
    let mut wrong = cfg.clone();
    wrong.data_dir = scratch("service-fleet-wrong");
    wrong.machines.retain(|m| m.id == "ac-1");
    wrong.machines[0].alerts = None;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let token = tokio_util::sync::CancellationToken::new();
    let e = driftwatch_service::launch::launch(wrong, listener, token)
        .await
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(
        e.contains("EZ0B") && e.contains("trunnion_ac") && e.contains("alerts"),
        "{e}"
    );

    let svc = launch_test(cfg, None).await;
    let t0 = svc.t0();
    // The morning's warm-up, its cycles every 30 min from power-on, and the machining after.
    for k in 1..=28 {
        svc.run_to(t0 + k * 15 * MIN).await;
    }
    for (id, family) in &families {
        let v = view_of(&svc, id);
        assert!(v.cycles.ok >= 6, "{id} ({family}): {:?}", v.cycles);
        // Each machine's own thermal model, fitted on its own errors, predicting them.
        let model = v.thermal.model.as_ref().expect("a model view");
        assert_eq!(model.status, "fitted", "{id}: {}", model.message);
        let predicted: Vec<&str> = v
            .thermal
            .prediction
            .iter()
            .map(|p| p.channel.as_str())
            .collect();
        for name in driftwatch_core::kinematics::Kinematics::load(family)
            .unwrap()
            .identify_names()
        {
            assert!(predicted.contains(&name.as_str()), "{id}: {predicted:?}");
        }
        let k = driftwatch_core::kinematics::Kinematics::load(family).unwrap();
        let (code, _, set) = svc
            .call(get(&format!("/api/v1/machines/{id}/compensation")))
            .await;
        assert_eq!(code, 200, "{id}: {set}");
        let names: Vec<String> = set["errors"].as_object().unwrap().keys().cloned().collect();
        let mut want = k.identify_names();
        want.sort();
        assert_eq!(names, want, "{id} ({family})");
        // The NC offsets of its own lines: the tilting axis' pivot and the C table's tilts.
        let tilt = k.tilting_axes()[0].to_string();
        let offsets = set["offsets"].as_object().unwrap();
        assert!(
            offsets
                .keys()
                .any(|o| o.starts_with(&format!("{tilt}_pivot_")))
                && offsets.contains_key("C_tilt_a_urad"),
            "{id}: {offsets:?}"
        );
        println!(
            "{id} ({family}): {} cycles ok, set {} offsets {offsets:?}",
            v.cycles.ok, set["version"]
        );
    }
    svc.stop().await;
}

/// The API is served by threads of its own, not by the loops' runtime: here the loops' runtime
/// has one thread, and the test holds it in a blocking read of the API's answer. Were the API a
/// task of that runtime, nothing could answer and the read would run into its bound.
#[tokio::test(flavor = "current_thread")]
async fn the_api_answers_while_the_loops_runtime_is_held() {
    let dir = scratch("service-api-apart");
    let svc = launch_test(common::patent_m1(&dir), None).await;
    // A blocking request, on the runtime's only thread (its read bound, 10 s, is for a failing
    // build: the answer comes at once).
    let answer = common::child::get(svc.svc.addr, "/healthz");
    assert_eq!(
        answer.as_ref().map(|(code, _)| *code),
        Some(200),
        "no answer while the loops' runtime is held: {answer:?}"
    );
    svc.svc.stop();
    svc.svc.wait().await;
}
