//! Faults a plant meets, each replayed against the service as `driftwatch serve` starts it (on
//! a manual clock: nothing sleeps on the wall clock to pass): a store that refuses writes, a
//! restart with open and acknowledged alerts, a second process on the same data directory,
//! settings that cannot work, a damaged or emptied database. What the NC is served must always
//! be what the store holds, and a fault must be said where people look.
//!
//! SQLite only (the write faults are SQLite triggers; the database file is damaged by hand).

use crate::common;

use axum::body::Body;
use axum::http::Request;
use common::{MIN, TestService, config, launch_test, patent_m1, refuse_inserts, scratch};
use driftwatch_service::config::ServiceConfig;
use driftwatch_service::launch::{ClockKind, LaunchOptions, launch_with};
use driftwatch_service::store::Store;
use serde_json::Value;
use tokio_util::sync::CancellationToken;

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).unwrap()
}

/// The largest compensation version the database holds for `machine` (0: none), read through
/// a connection of its own, as an auditor would.
async fn stored_max_version(db: &std::path::Path, machine: &str) -> u64 {
    let pool = sqlx::SqlitePool::connect(&format!("sqlite://{}", db.display()))
        .await
        .unwrap();
    let v: Option<i64> =
        sqlx::query_scalar("SELECT MAX(version) FROM compensation_sets WHERE machine_id = ?")
            .bind(machine)
            .fetch_one(&pool)
            .await
            .unwrap();
    pool.close().await;
    v.unwrap_or(0) as u64
}

/// What the NC gets from `/compensation`: the version in the body and the ETag (none on 404).
async fn served(svc: &TestService, id: &str) -> Option<(u64, String)> {
    let (code, h, body) = svc
        .call(get(&format!("/api/v1/machines/{id}/compensation")))
        .await;
    if code == 404 {
        return None;
    }
    assert_eq!(code, 200, "{body}");
    let etag = h["etag"].to_str().unwrap().to_string();
    Some((body["version"].as_u64().unwrap(), etag))
}

/// Run the plant day ten minutes at a time until sim-1 serves a set: the clock then, and the
/// set's version and ETag.
async fn until_served(svc: &TestService) -> (i64, (u64, String)) {
    let t0 = svc.t0();
    let mut t = t0;
    loop {
        if let Some(set) = served(svc, "sim-1").await {
            return (t, set);
        }
        t += 10 * MIN;
        assert!(t < t0 + 8 * 60 * MIN, "no set served in eight hours");
        svc.run_to(t).await;
    }
}

fn metric(metrics: &str, key: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(key)?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {key} in /metrics:\n{metrics}"))
}

/// A store that stops taking compensation sets (a full disk as the writes see it): the NC keeps
/// getting the last *stored* set, never one the store does not hold; the machine says it is
/// failing in `/readyz`, `/api/v1/machines`, an alert and `/metrics`; when the store takes
/// writes again the pending sets are stored in order and served, and the alert resolves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_that_refuses_writes_serves_only_stored_sets_says_so_and_recovers() {
    let dir = scratch("faults-store");
    let db = dir.join("driftwatch.db");
    let svc = launch_test(config(&dir), None).await;
    // The morning until a set is served.
    let (t, (v_before, _)) = until_served(&svc).await;

    refuse_inserts(&db, &["compensation_sets"], "sim-1", true).await;
    let t_fault = t;
    // Three hours of the warm-up: cycles and predictions want new sets all the while.
    let mut tags: Vec<(u64, String)> = Vec::new();
    for k in 1..=18 {
        svc.run_to(t_fault + k * 10 * MIN).await;
        let stored = stored_max_version(&db, "sim-1").await;
        let (v, etag) = served(&svc, "sim-1").await.unwrap();
        assert!(
            v <= stored,
            "at +{k}0 min the NC is served version {v}, the store holds up to {stored}"
        );
        tags.push((v, etag));
    }
    let stored = stored_max_version(&db, "sim-1").await;
    assert_eq!(stored, v_before, "the store took no set during the fault");
    let view = svc.svc.views["sim-1"].lock().unwrap().clone();
    assert!(
        view.health.failing && view.health.faults > 0,
        "{:?}",
        view.health
    );

    // Said where people look.
    let (code, ready) = svc.text("/readyz").await;
    assert_eq!(code, 503, "{ready}");
    assert!(
        ready.contains("sim-1 is failing") && ready.contains("injected fault"),
        "{ready}"
    );
    let (_, _, m) = svc.call(get("/api/v1/machines/sim-1")).await;
    assert_eq!(m["failing"], true, "{m}");
    let (_, _, alerts) = svc.call(get("/api/v1/machines/sim-1/alerts")).await;
    let open: Vec<&Value> = alerts["open"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["rule"] == "loop_fault")
        .collect();
    assert_eq!(open.len(), 1, "{alerts}");
    assert_eq!(open[0]["severity"], "critical");
    let fault_alert = open[0]["id"].as_u64().unwrap();
    let (_, metrics) = svc.text("/metrics").await;
    assert_eq!(
        metric(&metrics, "driftwatch_machine_failing{machine=\"sim-1\"}"),
        1.0
    );

    // The store takes writes again: the loop catches up by itself.
    refuse_inserts(&db, &["compensation_sets"], "sim-1", false).await;
    let t_heal = t_fault + 18 * 10 * MIN;
    for k in 1..=3 {
        svc.run_to(t_heal + k * 20 * MIN).await;
    }
    let stored = stored_max_version(&db, "sim-1").await;
    let (v_after, etag_after) = served(&svc, "sim-1").await.unwrap();
    assert_eq!(v_after, stored, "the newest stored set is served");
    assert!(v_after > v_before, "the pending sets were stored");
    // No ETag named two sets: every tag seen names the one version it was seen with.
    for (v, tag) in tags.iter().chain([&(v_after, etag_after)]) {
        assert!(tag.ends_with(&format!("-v{v}\"")), "{tag} for version {v}");
    }
    let (code, ready) = svc.text("/readyz").await;
    assert_eq!(code, 200, "{ready}");
    let (_, _, alerts) = svc.call(get("/api/v1/machines/sim-1/alerts")).await;
    assert!(
        !alerts["open"]
            .as_array()
            .unwrap()
            .iter()
            .any(|a| a["rule"] == "loop_fault"),
        "{alerts}"
    );
    let kinds: Vec<&str> = alerts["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["alert"] == fault_alert)
        .map(|e| e["kind"].as_str().unwrap())
        .collect();
    // Newest first: the raise was stored when the store healed, then the resolution.
    assert_eq!(kinds, ["resolved", "raised"], "{alerts}");
    svc.stop().await;
}

/// The open alerts people saw, with their acknowledgements and ids, and the machine's phase
/// are what a restart shows; a new alert after it takes a new id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_restores_open_alerts_acknowledgements_ids_and_the_phase() {
    let dir = scratch("faults-restart");
    let svc = launch_test(patent_m1(&dir), None).await;
    let t0 = svc.t0();
    // The patent day: the spindle runs 210 min and stops; EZ0B passes its 30 um limit.
    let mut t = t0;
    let open = loop {
        t += 10 * MIN;
        assert!(t < t0 + 200 * MIN, "no threshold alert before the stop");
        svc.run_to(t).await;
        let (_, _, a) = svc.call(get("/api/v1/machines/m1/alerts")).await;
        let open = a["open"].as_array().unwrap().clone();
        if open.iter().any(|a| a["rule"] == "threshold:EZ0B") {
            break open;
        }
    };
    let ez = open
        .iter()
        .find(|a| a["rule"] == "threshold:EZ0B")
        .unwrap()
        .clone();
    let id = ez["id"].as_u64().unwrap();
    let (code, _, ack) = svc
        .call(
            Request::post(format!("/api/v1/machines/m1/alerts/{id}/ack"))
                .header("authorization", "Bearer write-token")
                .body(Body::empty())
                .unwrap(),
        )
        .await;
    assert_eq!(code, 202, "{ack}");
    // Twelve minutes after the spindle stop: cooling.
    let stop_ns = t0 + 215 * MIN;
    let t_restart = t0 + 227 * MIN;
    svc.run_to(t_restart).await;
    let (_, _, before) = svc.call(get("/api/v1/machines/m1/alerts")).await;
    let (_, _, m_before) = svc.call(get("/api/v1/machines/m1")).await;
    assert_eq!(m_before["phase"]["phase"], "cooling", "{m_before}");
    let open_before = before["open"].clone();
    let ez_before = open_before
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["id"] == id)
        .unwrap_or_else(|| panic!("EZ0B's alert still open at the restart: {before}"))
        .clone();
    assert!(ez_before["acknowledged"]["by"].is_string(), "{ez_before}");
    svc.stop().await;

    let svc = launch_test(patent_m1(&dir), None).await;
    svc.run_to(svc.t0()).await;
    let (_, _, after) = svc.call(get("/api/v1/machines/m1/alerts")).await;
    let (_, _, m_after) = svc.call(get("/api/v1/machines/m1")).await;
    let brief = |open: &Value| -> Vec<String> {
        open.as_array()
            .unwrap()
            .iter()
            .map(|a| {
                format!(
                    "id {} {} {} acknowledged by {}",
                    a["id"], a["rule"], a["severity"], a["acknowledged"]["by"]
                )
            })
            .collect()
    };
    println!("open before the restart: {:?}", brief(&open_before));
    println!("open after the restart:  {:?}", brief(&after["open"]));
    println!(
        "phase before: {} since {:.1} min; after: {} since {:.1} min",
        m_before["phase"]["phase"],
        (m_before["phase"]["since_ns"].as_i64().unwrap() - t0) as f64 / MIN as f64,
        m_after["phase"]["phase"],
        (m_after["phase"]["since_ns"].as_i64().unwrap() - t0) as f64 / MIN as f64
    );
    assert_eq!(
        after["open"], open_before,
        "the same open alerts, ids and acknowledgements"
    );
    assert_eq!(m_after["phase"]["phase"], "cooling", "{m_after}");
    let since = m_after["phase"]["since_ns"].as_i64().unwrap();
    assert!(
        (since - stop_ns).abs() < 10 * MIN,
        "the phase counts from the spindle stop, {:.1} min",
        (since - t0) as f64 / MIN as f64
    );
    // Nothing was resolved without a resolved event: the log has none for the alert.
    let resolved = after["events"]
        .as_array()
        .unwrap()
        .iter()
        .any(|e| e["alert"] == id && e["kind"] == "resolved");
    assert!(!resolved, "{after}");
    // An alert raised after the restart takes a new id: a store fault (its loop_fault alert)
    // for half an hour of the afternoon, then the rest of the day.
    let t1 = svc.t0();
    let db = dir.join("driftwatch.db");
    refuse_inserts(&db, &["spindle_samples"], "m1", true).await;
    for k in 1..=3 {
        svc.run_to(t1 + k * 10 * MIN).await;
    }
    refuse_inserts(&db, &["spindle_samples"], "m1", false).await;
    for k in 4..=12 {
        svc.run_to(t1 + k * 10 * MIN).await;
    }
    let (_, _, later) = svc.call(get("/api/v1/machines/m1/alerts")).await;
    let max_before = before["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["alert"].as_u64())
        .max()
        .unwrap();
    let mut raised_after = 0;
    for e in later["events"].as_array().unwrap() {
        if e["kind"] == "raised" && e["t_ns"].as_i64().unwrap() >= t1 {
            raised_after += 1;
            println!("raised after the restart: id {} {}", e["alert"], e["rule"]);
            assert!(
                e["alert"].as_u64().unwrap() > max_before,
                "an alert raised after the restart reuses an id: {e}"
            );
        }
    }
    assert!(
        raised_after >= 1,
        "no alert raised after the restart: {later}"
    );
    svc.stop().await;
}

async fn launch_err(cfg: ServiceConfig, opts: LaunchOptions) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    match launch_with(cfg, listener, CancellationToken::new(), opts).await {
        Ok(_) => panic!("the start should have been refused"),
        Err(e) => e.to_string(),
    }
}

fn manual() -> LaunchOptions {
    LaunchOptions {
        clock: ClockKind::Manual,
        ..Default::default()
    }
}

/// A second service on a data directory in use is refused, naming the first; the first runs
/// on untouched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_process_on_the_same_data_directory_is_refused_naming_the_first() {
    let dir = scratch("faults-second");
    let first = launch_test(config(&dir), None).await;
    let t0 = first.t0();
    first.run_to(t0 + 30 * MIN).await;
    let err = launch_err(config(&dir), manual()).await;
    assert!(
        err.contains("in use by another driftwatch process")
            && err.contains(&format!("pid {}", std::process::id()))
            && err.contains(&first.svc.addr.to_string()),
        "{err}"
    );
    first.run_to(t0 + 60 * MIN).await;
    let view = first.svc.views["sim-1"].lock().unwrap().clone();
    assert_eq!(view.health.faults, 0, "{:?}", view.health.last_fault);
    first.stop().await;
    // Once the first has stopped, the next one starts.
    launch_test(config(&dir), None).await.stop().await;
}

/// Settings that would reject every cycle or lock everybody out are refused at start, naming
/// the key; a start that fails leaves no directory or database behind.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn settings_that_cannot_work_are_refused_and_a_failed_start_leaves_nothing() {
    let base = scratch("faults-config");
    let dir = base.join("data");
    type Change = Box<dyn Fn(&mut ServiceConfig)>;
    let cases: Vec<(&str, Change)> = vec![
        (
            "validation.max_step_um",
            Box::new(|c| c.validation.max_step_um = f64::NAN),
        ),
        (
            "validation.max_sigma_um",
            Box::new(|c| c.validation.max_sigma_um = -1.0),
        ),
        ("max_file_mib", Box::new(|c| c.max_file_mib = 0)),
        (
            "anonymous_read = false",
            Box::new(|c| {
                c.http.anonymous_read = false;
                c.http.tokens[0].token = "env:DRIFTWATCH_TEST_UNSET_TOKEN".into();
                c.http.tokens[1].token = "env:DRIFTWATCH_TEST_UNSET_TOKEN".into();
            }),
        ),
        // Valid settings, but a machine file that is not there: found after the directory
        // and the database were made.
        (
            "no-such-machine.toml",
            Box::new(|c| c.machines[0].machine = "no-such-machine.toml".into()),
        ),
    ];
    for (key, change) in cases {
        let mut cfg = config(&dir);
        change(&mut cfg);
        let err = launch_err(cfg, manual()).await;
        assert!(err.contains(key), "{key}: {err}");
        assert!(
            !dir.exists(),
            "{key}: the failed start left {} behind",
            dir.display()
        );
    }
}

/// A damaged database is named as such at once; an emptied one beside the recordings of an
/// earlier history is refused unless asked for, and then its sets carry new ETags.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_or_emptied_database_is_named_and_an_emptied_one_needs_asking() {
    let dir = scratch("faults-database");
    let db = dir.join("driftwatch.db");
    let svc = launch_test(config(&dir), None).await;
    let (_, (v1, tag1)) = until_served(&svc).await;
    svc.stop().await;
    let good = std::fs::read(&db).unwrap();
    assert!(good.len() > 8192);

    for side in ["driftwatch.db-wal", "driftwatch.db-shm"] {
        let _ = std::fs::remove_file(dir.join(side));
    }
    // Damaged: its pages overwritten.
    let mut bad = good.clone();
    bad[..4096].fill(0x5a);
    std::fs::write(&db, &bad).unwrap();
    let err = launch_err(config(&dir), manual()).await;
    assert!(
        err.contains("damaged") && !err.contains("timed out"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(&db).unwrap(),
        bad,
        "nothing was written to it"
    );

    // Emptied: refused while the recordings hold the history.
    std::fs::write(&db, b"").unwrap();
    let err = launch_err(config(&dir), manual()).await;
    assert!(
        err.contains("holds no machine") && err.contains("--new-database"),
        "{err}"
    );
    // Asked for: a new store whose first set has a new tag, though its version may repeat.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let opts = LaunchOptions {
        new_database: true,
        ..manual()
    };
    let svc = TestService::new(
        launch_with(config(&dir), listener, CancellationToken::new(), opts)
            .await
            .unwrap(),
    );
    let (_, (v2, tag2)) = until_served(&svc).await;
    assert_ne!(
        tag1, tag2,
        "versions {v1} and {v2} of two stores share a tag"
    );
    assert!(Store::open(&db).await.is_ok());
    svc.stop().await;
}
