//! Verification against a reference instrument through the running service: a reference made
//! from the machine's own stored tool-setter results (slightly changed) is compared at its
//! time (nearest, interpolated), stored, listed, refused when it cannot be taken or has no
//! setter result near it, and alerted on when it exceeds. The clock is the tests' manual one.

use crate::common;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use serde_json::{Value, json};

use common::{MIN, TestService, launch_test, patent_m1, scratch};
use driftwatch_core::recording::CycleResultMsg;

/// The patent's simulated day as machine `m1` (table_bc) on the shipped settings.
async fn service(name: &str) -> TestService {
    let cfg = patent_m1(&scratch(&format!("verification-{name}")));
    launch_test(cfg, None).await
}

const PATH: &str = "/api/v1/machines/m1/verifications";

fn post(token: Option<&str>, body: &Value) -> Request<Body> {
    let mut b = Request::post(PATH).header(header::CONTENT_TYPE, "application/json");
    if let Some(t) = token {
        b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    b.body(Body::from(body.to_string())).unwrap()
}

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).unwrap()
}

fn read(uri: &str) -> Request<Body> {
    Request::get(uri)
        .header(header::AUTHORIZATION, "Bearer read-token")
        .body(Body::empty())
        .unwrap()
}

/// A reference at `t_ns` with each error of `values`, sigma `sigma` of each.
fn reference(t_ns: i64, values: &[(String, f64)], sigma: f64) -> Value {
    let errors: serde_json::Map<String, Value> =
        values.iter().map(|(k, v)| (k.clone(), json!(v))).collect();
    let sigmas: serde_json::Map<String, Value> = values
        .iter()
        .map(|(k, _)| (k.clone(), json!(sigma)))
        .collect();
    json!({
        "instrument": "rtest",
        "t_ns": t_ns,
        "errors": errors,
        "sigma": sigmas,
        "frame_note": "R-test sphere frame turned to the machine frame",
        "source": "rtest-test.csv",
    })
}

fn values(r: &CycleResultMsg, shift: f64) -> Vec<(String, f64)> {
    r.errors
        .as_ref()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v + shift))
        .collect()
}

#[tokio::test]
async fn a_reference_is_compared_stored_listed_refused_and_alerted_on() {
    let app = service("e2e").await;
    let t0 = app.t0();
    app.run_to(t0 + 100 * MIN).await;
    let results = app
        .store()
        .accepted_results_between("m1", i64::MIN, i64::MAX)
        .await
        .unwrap();
    assert!(results.len() >= 3, "{} accepted results", results.len());
    let (r1, r2, last) = (&results[0], &results[1], results.last().unwrap());
    assert!(
        r2.t_ns - r1.t_ns <= 120 * MIN,
        "a midpoint within 60 min of both"
    );

    // At a stored result's own time, 0.1 um off on every error: compared with that result.
    let sigma = 0.5;
    let body = reference(r1.t_ns, &values(r1, 0.1), sigma);
    let (s, _, v) = app.call(post(Some("write-token"), &body)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(
        (v["id"].as_i64(), v["requested_by"].as_str()),
        (Some(1), Some("operator"))
    );
    assert_eq!(v["machine_id"], "m1");
    assert_eq!(v["method"], "nearest");
    assert_eq!(v["setter_cycles"], json!([r1.cycle]));
    assert_eq!(
        (v["gap_ns"].as_i64(), v["setter_t_ns"].as_i64()),
        (Some(0), Some(r1.t_ns))
    );
    assert_eq!(
        (v["k"].as_f64(), v["exceeds_any"].as_bool()),
        (Some(2.0), Some(false))
    );
    assert_eq!(v["source"], "rtest-test.csv");
    let per = v["per_error"].as_object().unwrap();
    assert_eq!(per.len(), 6, "{v}");
    for (name, c) in per {
        let setter = r1.errors.as_ref().unwrap()[name];
        let s_setter = r1.sigma.as_ref().unwrap()[name];
        assert_eq!(c["setter"].as_f64(), Some(setter), "{name}");
        assert!(
            (c["difference"].as_f64().unwrap() - 0.1).abs() < 1e-9,
            "{name}: {c}"
        );
        let combined = sigma.hypot(s_setter);
        assert!((c["combined_sigma"].as_f64().unwrap() - combined).abs() < 1e-12);
        assert!((c["z"].as_f64().unwrap() - 0.1 / combined).abs() < 1e-9);
        assert_eq!(c["exceeds"], false);
    }
    assert_eq!(per["EA0C"]["unit"], "urad");

    // Midway between the first two: each error interpolated to the reference time.
    let mid = (r1.t_ns + r2.t_ns) / 2;
    let w = (mid - r1.t_ns) as f64 / (r2.t_ns - r1.t_ns) as f64;
    let interpolated: Vec<(String, f64)> = values(r1, 0.0)
        .into_iter()
        .map(|(k, v1)| {
            let v2 = r2.errors.as_ref().unwrap()[&k];
            (k, (1.0 - w) * v1 + w * v2)
        })
        .collect();
    let (s, _, v) = app
        .call(post(
            Some("write-token"),
            &reference(mid, &interpolated, sigma),
        ))
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["method"], "interpolated");
    assert_eq!(v["setter_cycles"], json!([r1.cycle, r2.cycle]));
    assert_eq!(v["setter_t_ns"].as_i64(), Some(mid));
    for (name, want) in &interpolated {
        let c = &v["per_error"][name];
        assert!(
            (c["setter"].as_f64().unwrap() - want).abs() < 1e-9,
            "{name}: {c}"
        );
        let (s1, s2) = (
            r1.sigma.as_ref().unwrap()[name],
            r2.sigma.as_ref().unwrap()[name],
        );
        let s_setter = ((1.0 - w) * s1).hypot(w * s2);
        assert!((c["setter_sigma"].as_f64().unwrap() - s_setter).abs() < 1e-12);
    }

    // Refusals: the token, the body, the names, the sigma, the time, no setter result near.
    let good = reference(last.t_ns, &values(last, 0.0), sigma);
    assert_eq!(
        app.call(post(None, &good)).await.0,
        StatusCode::UNAUTHORIZED
    );
    assert_eq!(
        app.call(post(Some("read-token"), &good)).await.0,
        StatusCode::FORBIDDEN
    );
    let mut refusals = Vec::new();
    let mut no_sigma = good.clone();
    no_sigma["sigma"]["EZ0B"] = json!(-0.5);
    refusals.push((
        no_sigma,
        StatusCode::BAD_REQUEST,
        "bad_reference",
        "sigma.EZ0B",
    ));
    let mut foreign = good.clone();
    foreign["errors"]["EZ0A"] = json!(1.0);
    foreign["sigma"]["EZ0A"] = json!(1.0);
    refusals.push((
        foreign,
        StatusCode::BAD_REQUEST,
        "bad_reference",
        "errors.EZ0A",
    ));
    let mut ahead = good.clone();
    ahead["t_ns"] = json!(t0 + 200 * MIN);
    refusals.push((ahead, StatusCode::BAD_REQUEST, "bad_reference", "t_ns"));
    let mut shapeless = good.clone();
    shapeless.as_object_mut().unwrap().remove("t_ns");
    refusals.push((
        shapeless,
        StatusCode::UNPROCESSABLE_ENTITY,
        "bad_body",
        "t_ns",
    ));
    let mut early = good.clone();
    early["t_ns"] = json!(r1.t_ns - 90 * MIN);
    refusals.push((
        early,
        StatusCode::UNPROCESSABLE_ENTITY,
        "no_setter_result",
        "within 60 min",
    ));
    for (body, status, code, says) in refusals {
        let (s, _, e) = app.call(post(Some("write-token"), &body)).await;
        assert_eq!((s, e["code"].as_str()), (status, Some(code)), "{e}");
        assert!(e["message"].as_str().unwrap().contains(says), "{e}");
    }

    // No verification alert so far; one that exceeds raises it at the loop's next step.
    let open = |alerts: &Value| {
        alerts["open"]
            .as_array()
            .unwrap()
            .iter()
            .find(|a| a["rule"] == "verification")
            .cloned()
    };
    let (_, _, alerts) = app.call(get("/api/v1/machines/m1/alerts")).await;
    assert!(open(&alerts).is_none(), "{alerts}");
    let mut off = values(last, 0.0);
    for (k, v) in off.iter_mut() {
        if k == "EZ0B" {
            *v += 20.0;
        }
    }
    let (s, _, v) = app
        .call(post(
            Some("write-token"),
            &reference(last.t_ns, &off, sigma),
        ))
        .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["exceeds_any"], true);
    assert_eq!(
        (v["worst_error"].as_str(), v["id"].as_i64()),
        (Some("EZ0B"), Some(3))
    );
    assert_eq!(v["per_error"]["EZ0B"]["exceeds"], true);
    assert_eq!(v["per_error"]["EX0B"]["exceeds"], false);
    app.run_to(t0 + 101 * MIN).await;
    let (_, _, alerts) = app.call(get("/api/v1/machines/m1/alerts")).await;
    let a = open(&alerts).expect("a verification alert");
    let message = a["message"].as_str().unwrap();
    assert!(
        message.contains("rtest differs from the tool setter"),
        "{message}"
    );
    assert!(message.contains("EZ0B +20.00 um"), "{message}");
    assert_eq!(a["raised_cycle"].as_i64(), Some(last.cycle));
    assert!(
        alerts["events"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["rule"] == "verification" && e["kind"] == "raised"),
        "{alerts}"
    );

    // The list: latest reference time first, windowed, limited; names for token holders.
    let (s, _, list) = app.call(read(PATH)).await;
    assert_eq!(s, StatusCode::OK);
    let ids: Vec<i64> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["id"].as_i64().unwrap())
        .collect();
    assert_eq!(ids, [3, 2, 1]);
    assert_eq!(list[0]["requested_by"], "operator");
    assert_eq!(list[2]["per_error"], per_json(&app, r1.t_ns).await);
    let (_, _, one) = app.call(get(&format!("{PATH}?limit=1"))).await;
    assert_eq!(one.as_array().unwrap().len(), 1);
    assert_eq!(one[0]["id"], 3);
    assert_eq!(one[0]["requested_by"], "a token holder");
    let (_, _, window) = app
        .call(get(&format!("{PATH}?from={}&to={}", r1.t_ns, mid)))
        .await;
    let ids: Vec<i64> = window
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["id"].as_i64().unwrap())
        .collect();
    assert_eq!(ids, [2, 1]);
    let (s, _, e) = app.call(get(&format!("{PATH}?from=10&to=5"))).await;
    assert_eq!(
        (s, e["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_window"))
    );
    let (s, _, e) = app.call(get("/api/v1/machines/nope/verifications")).await;
    assert_eq!(
        (s, e["code"].as_str()),
        (StatusCode::NOT_FOUND, Some("unknown_machine"))
    );
    app.stop().await;
}

/// The stored per-error comparison of the verification at `t_ns`, from the store.
async fn per_json(app: &TestService, t_ns: i64) -> Value {
    let rows = app
        .store()
        .verifications("m1", t_ns, t_ns, 10)
        .await
        .unwrap();
    serde_json::to_value(&rows[0].verification.per_error).unwrap()
}

/// A measured linear-axis geometry posted as a version: refused when it cannot be taken,
/// stored, listed, named by every cycle result solved after it, and still the machine's after
/// a restart.
#[tokio::test]
async fn a_geometry_version_is_stored_used_by_the_solves_and_restored() {
    const GEOMETRY: &str = "/api/v1/machines/m1/geometry";
    let dir = scratch("verification-geometry");
    let app = launch_test(patent_m1(&dir), None).await;
    let t0 = app.t0();
    app.run_to(t0 + 100 * MIN).await;
    let store = app.store().clone();
    let before = store
        .accepted_results_between("m1", i64::MIN, i64::MAX)
        .await
        .unwrap();
    assert!(!before.is_empty() && before.iter().all(|r| r.geometry.is_none()));
    let posting = |token: &str, body: Value| {
        Request::post(GEOMETRY)
            .header(header::CONTENT_TYPE, "application/json")
            .header(header::AUTHORIZATION, format!("Bearer {token}"))
            .body(Body::from(body.to_string()))
            .unwrap()
    };
    let geometry = json!({
        "source": "laser step diagonal 2026-11-26",
        "geometry": { "squareness_urad": { "xz": 4.0 }, "components": { "EZX": [0.0, 0.5, 0.0] } }
    });
    // Refused: a unit slip, an unknown component, no source, a reader's token.
    for (body, code) in [
        (
            json!({"source": "x", "geometry": {"scale_ppm": [3e6, 0, 0]}}),
            "bad_geometry",
        ),
        (
            json!({"source": "x", "geometry": {"components": {"EQX": [1, 0, 0]}}}),
            "bad_geometry",
        ),
        (json!({"source": " ", "geometry": {}}), "bad_geometry"),
    ] {
        let (s, _, v) = app.call(posting("write-token", body)).await;
        assert_eq!(
            (s, v["code"].as_str()),
            (StatusCode::BAD_REQUEST, Some(code)),
            "{v}"
        );
        assert!(v["message"].as_str().is_some_and(|m| !m.is_empty()));
    }
    let (s, _, _) = app.call(posting("read-token", geometry.clone())).await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (s, _, v) = app.call(posting("write-token", geometry.clone())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(
        (v["version"].as_i64(), v["requested_by"].as_str()),
        (Some(1), Some("operator"))
    );
    assert_eq!(v["geometry"]["squareness_urad"]["xz"], 4.0);
    let (s, _, listed) = app.call(read(GEOMETRY)).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(listed.as_array().map(Vec::len), Some(1), "{listed}");
    let label = "version 1: laser step diagonal 2026-11-26";
    app.run_to(t0 + 300 * MIN).await;
    let after = store
        .accepted_results_between("m1", before.last().unwrap().t_ns + 1, i64::MAX)
        .await
        .unwrap();
    assert!(!after.is_empty(), "no cycle after the geometry was posted");
    assert!(
        after.iter().all(|r| r.geometry.as_deref() == Some(label)),
        "{:?}",
        after.iter().map(|r| &r.geometry).collect::<Vec<_>>()
    );
    let stop_ns = t0 + 300 * MIN;
    app.stop().await;
    // Restarted on the same store: the solves still start from version 1.
    let app = launch_test(patent_m1(&dir), Some(stop_ns)).await;
    app.run_to(stop_ns + 200 * MIN).await;
    let later = app
        .store()
        .accepted_results_between("m1", stop_ns + 1, i64::MAX)
        .await
        .unwrap();
    println!(
        "results: {} before the geometry, {} after, {} after the restart",
        before.len(),
        after.len(),
        later.len()
    );
    assert!(!later.is_empty(), "no cycle after the restart");
    assert!(later.iter().all(|r| r.geometry.as_deref() == Some(label)));
    app.stop().await;
}
