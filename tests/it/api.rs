//! The HTTP API over a machine loop run on simulated time: the NC's compensation endpoint with
//! ETag and 304, operator requests and their authorisation, errors as JSON.

use crate::common;
// The dashboard in headless Chromium.
mod dashboard;
// The server's connection limits: timeouts, the cap.
mod connections;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use serde_json::Value;

use common::{MIN, TestService, launch_test, patent_m1, scratch};

/// The patent's simulated day as machine `m1` on the service's shipped settings, with a read
/// and a write token; reads without a token when `anonymous_read`.
async fn service(name: &str, anonymous_read: bool) -> TestService {
    let mut cfg = patent_m1(&scratch(&format!("api-{name}")));
    cfg.http.anonymous_read = anonymous_read;
    launch_test(cfg, None).await
}

async fn call(app: &TestService, req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, Value) {
    app.call(req).await
}

/// POST a body of `bytes` to `uri` as curl sends a large one: the head with `Expect:
/// 100-continue`, the body only once the server asks for it. The status, the content type and
/// the answer's JSON.
///
/// Not through [`call`]: the server refuses such a body on its head and closes the connection,
/// and a client that sends the whole body at once races that close. Some (reqwest) then report
/// the write cut short instead of the answer that is waiting for them.
async fn too_large(app: &TestService, uri: &str, bytes: usize) -> (StatusCode, String, Value) {
    let addr = app.svc.addr;
    let head = format!(
        "POST {uri} HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer write-token\r\n\
         Content-Type: application/json\r\nContent-Length: {bytes}\r\n\
         Expect: 100-continue\r\nConnection: close\r\n\r\n"
    );
    let (code, head, body) =
        tokio::task::spawn_blocking(move || common::child::exchange(addr, &head))
            .await
            .unwrap()
            .expect("an answer to the head");
    let content_type = head
        .lines()
        .find_map(|l| {
            l.split_once(':')
                .filter(|(k, _)| k.eq_ignore_ascii_case("content-type"))
        })
        .map(|(_, v)| v.trim().to_string())
        .unwrap_or_default();
    (StatusCode::from_u16(code).unwrap(), content_type, body)
}

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).unwrap()
}

/// A read with the dashboard's token: it sees token holders' names.
fn read(uri: &str) -> Request<Body> {
    Request::get(uri)
        .header(header::AUTHORIZATION, "Bearer read-token")
        .body(Body::empty())
        .unwrap()
}

#[tokio::test]
async fn the_nc_reads_the_last_validated_set_with_etag_and_304() {
    let app = service("etag", true).await;
    let t0 = app.t0();
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/compensation")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_eq!(body["code"], "no_compensation");
    app.run_to(t0 + 45 * MIN).await;
    let (s, h, body) = call(&app, get("/api/v1/machines/m1/compensation")).await;
    assert_eq!(s, StatusCode::OK);
    let v1 = body["version"].as_u64().unwrap();
    assert!(v1 >= 1);
    assert!(body["offsets"]["B_pivot_z_um"].is_number());
    let etag = h[header::ETAG].to_str().unwrap().to_string();
    let req = Request::get("/api/v1/machines/m1/compensation")
        .header(header::IF_NONE_MATCH, &etag)
        .body(Body::empty())
        .unwrap();
    let (s, _, _) = call(&app, req).await;
    assert_eq!(s, StatusCode::NOT_MODIFIED);
    app.run_to(t0 + 100 * MIN).await;
    let req = Request::get("/api/v1/machines/m1/compensation")
        .header(header::IF_NONE_MATCH, &etag)
        .body(Body::empty())
        .unwrap();
    let (s, h, body) = call(&app, req).await;
    assert_eq!(s, StatusCode::OK, "a newer set replaces the old ETag");
    assert!(body["version"].as_u64().unwrap() > v1);
    assert_ne!(h[header::ETAG].to_str().unwrap(), etag);
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/cycles")).await;
    assert_eq!(s, StatusCode::OK);
    assert!(body.as_array().unwrap().len() >= 2);
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/cycles/1")).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(body["detections"].as_array().unwrap().len(), 24);
    let (s, _, body) = call(&app, get("/api/v1/machines/nope")).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::NOT_FOUND, Some("unknown_machine"))
    );
}

#[tokio::test]
async fn write_endpoints_need_a_write_token() {
    let app = service("auth", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 5 * MIN).await;
    let post = |token: Option<&str>| {
        let mut b = Request::post("/api/v1/machines/m1/cycles");
        if let Some(t) = token {
            b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
        }
        b.body(Body::empty()).unwrap()
    };
    let (s, h, body) = call(&app, post(None)).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    assert_eq!(h[header::WWW_AUTHENTICATE], "Bearer");
    assert_eq!(body["code"], "token_required");
    let (s, _, _) = call(&app, post(Some("read-token"))).await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (s, _, _) = call(&app, post(Some("wrong"))).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    // Counted before the request: it wakes the loop, which may start the cycle at once.
    let before = app.store().cycles("m1", 100, None).await.unwrap().len();
    let (s, _, body) = call(&app, post(Some("write-token"))).await;
    assert_eq!(s, StatusCode::ACCEPTED);
    assert_eq!(body["by"], "operator");
    // The request reaches the loop: a cycle starts at the next idle moment.
    app.run_to(t0 + 8 * MIN).await;
    let after = app.store().cycles("m1", 100, None).await.unwrap();
    assert_eq!(after.len(), before + 1);
    assert!(
        after[0].trigger.contains("operator"),
        "{}",
        after[0].trigger
    );
    // Reads need a token when anonymous reads are off.
    let closed = service("auth-closed", false).await;
    let (s, _, _) = call(&closed, get("/api/v1/machines")).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    let req = Request::get("/api/v1/machines")
        .header(header::AUTHORIZATION, "Bearer read-token")
        .body(Body::empty())
        .unwrap();
    let (s, _, _) = call(&closed, req).await;
    assert_eq!(s, StatusCode::OK);
}

#[tokio::test]
async fn alerts_can_be_listed_and_acknowledged_and_metrics_count_cycles() {
    let app = service("alerts", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 100 * MIN).await;
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/alerts")).await;
    assert_eq!(s, StatusCode::OK);
    let open = body["open"].as_array().unwrap();
    let ez = open
        .iter()
        .find(|a| a["rule"] == "threshold:EZ0B")
        .expect("EZ0B above 30 um");
    let id = ez["id"].as_u64().unwrap();
    assert!(
        body["events"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["kind"] == "raised")
    );
    let ack = |id: u64, token: Option<&str>| {
        let mut b = Request::post(format!("/api/v1/machines/m1/alerts/{id}/ack"));
        if let Some(t) = token {
            b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
        }
        b.body(Body::empty()).unwrap()
    };
    assert_eq!(call(&app, ack(id, None)).await.0, StatusCode::UNAUTHORIZED);
    assert_eq!(
        call(&app, ack(id, Some("read-token"))).await.0,
        StatusCode::FORBIDDEN
    );
    assert_eq!(
        call(&app, ack(999, Some("write-token"))).await.0,
        StatusCode::NOT_FOUND
    );
    assert_eq!(
        call(&app, ack(id, Some("write-token"))).await.0,
        StatusCode::ACCEPTED
    );
    app.run_to(t0 + 101 * MIN).await;
    let (_, _, body) = call(&app, read("/api/v1/machines/m1/alerts")).await;
    let ez = body["open"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["id"] == id)
        .unwrap()
        .clone();
    assert_eq!(ez["acknowledged"]["by"], "operator", "{ez}");
    let (_, text) = app.text("/metrics").await;
    let ok_line = text
        .lines()
        .find(|l| l.starts_with("driftwatch_cycles_total{machine=\"m1\",status=\"ok\"}"))
        .unwrap();
    let n: f64 = ok_line.rsplit(' ').next().unwrap().parse().unwrap();
    assert!(n >= 2.0, "{ok_line}");
    assert!(text.contains("driftwatch_compensation_version{machine=\"m1\"}"));
    // Latency is counted per route pattern, not per raw path; this scrape sees the calls before it.
    let count = |route: &str| -> f64 {
        let key = format!("driftwatch_http_request_duration_seconds_count{{route=\"{route}\"}} ");
        text.lines()
            .find_map(|l| l.strip_prefix(key.as_str()))
            .map_or(0.0, |v| v.parse().unwrap())
    };
    assert_eq!(count("/api/v1/machines/{id}/alerts"), 2.0, "{text}");
    assert_eq!(count("/api/v1/machines/{id}/alerts/{alert}/ack"), 4.0);
    assert!(!text.contains("route=\"/api/v1/machines/m1"));
    assert!(text.contains("driftwatch_webhook_events_total{outcome=\"delivered\"} 0"));
    // The served set, each error with its unit: what the Grafana dashboard plots.
    let (_, _, comp) = call(&app, get("/api/v1/machines/m1/compensation")).await;
    let ez0b = comp["errors"]["EZ0B"].as_f64().unwrap();
    let line = text
        .lines()
        .find(|l| {
            l.starts_with("driftwatch_served_error{")
                && l.contains("error=\"EZ0B\"")
                && l.contains("unit=\"um\"")
        })
        .unwrap_or_else(|| panic!("no served EZ0B in {text}"));
    let v: f64 = line.rsplit(' ').next().unwrap().parse().unwrap();
    assert!((v - ez0b).abs() < 1e-9, "{line} against {ez0b}");
    grafana_queries_only_exported_metrics(&text);
}

/// Every metric the provisioned Grafana dashboard (`deploy/grafana/dashboards`) queries is one
/// the service exports, and its panels use the provisioned Prometheus data source.
fn grafana_queries_only_exported_metrics(metrics_text: &str) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/grafana");
    let dash: Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("dashboards/driftwatch.json")).unwrap(),
    )
    .unwrap();
    let datasources =
        std::fs::read_to_string(root.join("provisioning/datasources/prometheus.yaml")).unwrap();
    let exported: std::collections::BTreeSet<&str> = metrics_text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| l.split(['{', ' ']).next())
        .collect();
    let mut queried = 0;
    for panel in dash["panels"].as_array().unwrap() {
        let uid = panel["datasource"]["uid"].as_str().unwrap();
        assert!(datasources.contains(&format!("uid: {uid}")), "{uid}");
        for t in panel["targets"].as_array().unwrap() {
            let expr = t["expr"].as_str().unwrap();
            let names: Vec<&str> = expr
                .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                .filter(|w| w.starts_with("driftwatch_"))
                .collect();
            assert!(!names.is_empty(), "{expr}");
            for n in names {
                assert!(exported.contains(n), "{n} (in {expr}) is not exported");
                queried += 1;
            }
        }
    }
    assert!(queried >= 10, "{queried}");
}

/// The OpenAPI document is pinned: a change to the API shows in `docs/openapi.json` (rewrite
/// it with `UPDATE_SNAPSHOTS=1 cargo test --test it -- api::`) and is reviewed there. Every
/// answer of every operation has a schema, except those without a body (204, 304).
#[test]
fn the_openapi_document_matches_its_snapshot_and_every_answer_has_a_schema() {
    use utoipa::OpenApi as _;
    let doc = serde_json::to_value(driftwatch_service::api::ApiDoc::openapi()).unwrap();
    let mut answers = 0;
    for (path, item) in doc["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            for (status, response) in op["responses"].as_object().unwrap() {
                answers += 1;
                let content = response["content"].as_object();
                if status == "204" || status == "304" {
                    assert!(content.is_none(), "{method} {path} {status} has a body");
                    continue;
                }
                let schemas = content
                    .into_iter()
                    .flatten()
                    .filter(|(_, c)| c["schema"].is_object())
                    .count();
                assert!(schemas > 0, "{method} {path} {status}: no response schema");
            }
        }
    }
    assert!(answers > 100, "{answers} answers");
    let text = serde_json::to_string_pretty(&doc).unwrap() + "\n";
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/openapi.json");
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() {
        std::fs::write(&file, &text).unwrap();
    }
    let pinned = std::fs::read_to_string(&file).unwrap_or_default();
    assert!(
        pinned == text,
        "the API's OpenAPI document differs from docs/openapi.json: review the change and \
         rewrite it with UPDATE_SNAPSHOTS=1 cargo test --test it -- api::"
    );
}

/// Every `$ref` of the document names a schema it defines: a dangling one makes the document
/// invalid for validators, and generators drop the operation that uses it.
#[test]
fn every_reference_of_the_openapi_document_is_defined() {
    use utoipa::OpenApi as _;
    fn refs<'a>(v: &'a Value, out: &mut Vec<&'a str>) {
        match v {
            Value::Object(m) => {
                if let Some(Value::String(r)) = m.get("$ref") {
                    out.push(r);
                }
                m.values().for_each(|x| refs(x, out));
            }
            Value::Array(a) => a.iter().for_each(|x| refs(x, out)),
            _ => {}
        }
    }
    let doc = serde_json::to_value(driftwatch_service::api::ApiDoc::openapi()).unwrap();
    let mut found = Vec::new();
    refs(&doc, &mut found);
    assert!(found.len() > 50, "{} references", found.len());
    let schemas = doc["components"]["schemas"].as_object().unwrap();
    let dangling: Vec<&str> = found
        .into_iter()
        .filter(|r| {
            r.strip_prefix("#/components/schemas/")
                .is_none_or(|name| !schemas.contains_key(name))
        })
        .collect();
    assert!(dangling.is_empty(), "undefined references: {dangling:?}");
}

#[tokio::test]
async fn the_openapi_document_lists_every_endpoint_and_swagger_ui_is_served() {
    let app = service("openapi", true).await;
    let (s, _, doc) = call(&app, get("/api/v1/openapi.json")).await;
    assert_eq!(s, StatusCode::OK);
    let paths = doc["paths"].as_object().unwrap();
    for p in [
        "/api/v1/machines",
        "/api/v1/machines/{id}/compensation",
        "/api/v1/machines/{id}/cycles",
        "/api/v1/machines/{id}/cycles/{n}",
        "/api/v1/machines/{id}/errors",
        "/api/v1/machines/{id}/alerts",
        "/api/v1/machines/{id}/alerts/{alert}/ack",
        "/api/v1/machines/{id}/nc/events",
        "/api/v1/machines/{id}/nc/request",
        "/api/v1/machines/{id}/diagnoses",
        "/api/v1/machines/{id}/diagnoses/{n}",
        "/api/v1/machines/{id}/verifications",
        "/api/v1/machines/{id}/geometry",
        "/metrics",
    ] {
        assert!(
            paths.contains_key(p),
            "{p} missing from the OpenAPI document"
        );
    }
    assert!(doc["components"]["securitySchemes"]["bearer"].is_object());
    // Every status a path can answer is listed, the shared error answers included.
    for (p, item) in paths {
        for (method, op) in item.as_object().unwrap() {
            let codes = op["responses"].as_object().unwrap();
            let mut want = vec!["400", "401", "500"];
            if p.contains("{id}") {
                want.push("404");
            }
            if method == "post" {
                want.push("403");
            }
            for c in want {
                assert!(codes.contains_key(c), "{method} {p} does not document {c}");
            }
        }
    }
    let (status, _) = app.text("/api/v1/docs/").await;
    assert_eq!(status, StatusCode::OK);
}

#[tokio::test]
async fn the_error_series_is_windowed_and_bucketed_for_dashboards() {
    let app = service("series", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 240 * MIN).await;
    let (s, _, all) = call(&app, get("/api/v1/machines/m1/errors?source=measured")).await;
    assert_eq!(s, StatusCode::OK);
    let all = all.as_array().unwrap().clone();
    assert!(all.iter().all(|v| v["source"] == "measured"));
    // The thermal model's served values come as a second series, and `all` is both.
    let (_, _, pred) = call(&app, get("/api/v1/machines/m1/errors?source=predicted")).await;
    let pred = pred.as_array().unwrap().clone();
    assert!(!pred.is_empty() && pred.iter().all(|v| v["source"] == "predicted"));
    let (_, _, both) = call(&app, get("/api/v1/machines/m1/errors")).await;
    assert_eq!(both.as_array().unwrap().len(), all.len() + pred.len());
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/errors?source=guessed")).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_source"))
    );
    let ez: Vec<&Value> = all.iter().filter(|v| v["name"] == "EZ0B").collect();
    assert!(ez.len() >= 4, "{} EZ0B values", ez.len());
    assert_eq!(all.len(), 6 * ez.len(), "six errors per validated cycle");
    // A window keeps the samples inside it.
    let mid = ez[ez.len() / 2]["t_ns"].as_i64().unwrap();
    let (_, _, later) = call(
        &app,
        get(&format!(
            "/api/v1/machines/m1/errors?source=measured&from={mid}"
        )),
    )
    .await;
    let later = later.as_array().unwrap();
    assert!(later.iter().all(|v| v["t_ns"].as_i64().unwrap() >= mid));
    assert_eq!(
        later.len(),
        all.iter()
            .filter(|v| v["t_ns"].as_i64().unwrap() >= mid)
            .count()
    );
    // Hourly buckets: every EZ0B sample lands in exactly one, the counts add up, and each
    // mean lies within its bucket's range.
    let (s, _, hourly) = call(
        &app,
        get("/api/v1/machines/m1/errors?source=measured&every=1h"),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let buckets: Vec<&Value> = hourly
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["name"] == "EZ0B")
        .collect();
    assert!(buckets.len() < ez.len());
    let n: u64 = buckets.iter().map(|b| b["n"].as_u64().unwrap()).sum();
    assert_eq!(n as usize, ez.len());
    for b in &buckets {
        assert_eq!(b["t_ns"].as_i64().unwrap() % 3_600_000_000_000, 0);
        let (v, lo, hi) = (
            b["value"].as_f64().unwrap(),
            b["min"].as_f64().unwrap(),
            b["max"].as_f64().unwrap(),
        );
        assert!(lo <= v && v <= hi, "{b}");
    }
    for bad in ["0", "soon", "-1h"] {
        let (s, _, body) = call(
            &app,
            get(&format!("/api/v1/machines/m1/errors?every={bad}")),
        )
        .await;
        assert_eq!(s, StatusCode::BAD_REQUEST, "{bad}");
        assert_eq!(body["code"], "bad_every");
    }
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/errors?from=5&to=4")).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert_eq!(body["code"], "bad_window");
}

#[tokio::test]
async fn the_model_and_its_predictions_are_served() {
    let app = service("model", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 20 * MIN).await;
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/model")).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(body["status"], "waiting", "{body}");
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/prediction")).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::NOT_FOUND, Some("no_model"))
    );
    // The patent day: a cycle every 30 min, so six validated cycles by about 150 min.
    app.run_to(t0 + 200 * MIN).await;
    let (_, _, body) = call(&app, get("/api/v1/machines/m1/model")).await;
    assert_eq!(body["status"], "fitted", "{body}");
    let channels = body["model"]["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 6);
    assert_eq!(
        body["model"]["spindle_time_constants_min"],
        serde_json::json!([6.0, 15.0, 40.0, 100.0, 250.0, 600.0])
    );
    let (s, _, now) = call(&app, get("/api/v1/machines/m1/prediction")).await;
    assert_eq!(s, StatusCode::OK, "{now}");
    let t = now["t_ns"].as_i64().unwrap();
    let sigma = |b: &Value, e: &str| -> f64 {
        b["values"]
            .as_array()
            .unwrap()
            .iter()
            .find(|v| v["channel"] == e)
            .unwrap()["sigma"]
            .as_f64()
            .unwrap()
    };
    // Later, with no measurement in between, the prediction is less certain.
    let (_, _, later) = call(
        &app,
        get(&format!(
            "/api/v1/machines/m1/prediction?at={}",
            t + 120 * MIN
        )),
    )
    .await;
    assert!(sigma(&later, "EZ0B") > sigma(&now, "EZ0B"), "{now} {later}");
    let (s, _, body) = call(
        &app,
        get(&format!("/api/v1/machines/m1/prediction?at={}", t - MIN)),
    )
    .await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("before_last_input"))
    );
    // Predicted sets are served between cycles, with their source.
    let sets = app.store().compensation_versions("m1").await.unwrap();
    assert!(sets.iter().any(|s| s.1 == "predicted"), "{sets:?}");
    let (_, _, comp) = call(&app, get("/api/v1/machines/m1/compensation")).await;
    assert!(
        comp["source"] == "predicted" || comp["source"] == "measured",
        "{comp}"
    );
}

#[tokio::test]
async fn a_diagnosis_runs_on_a_stored_window_and_is_kept() {
    let app = service("diagnosis", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 300 * MIN).await;
    let post = |token: &str, body: &str| {
        Request::post("/api/v1/machines/m1/diagnoses")
            .header(header::AUTHORIZATION, format!("Bearer {token}"))
            .header(header::CONTENT_TYPE, "application/json")
            .body(Body::from(body.to_string()))
            .unwrap()
    };
    let (s, _, _) = call(&app, post("read-token", "{}")).await;
    assert_eq!(
        s,
        StatusCode::FORBIDDEN,
        "running a diagnosis needs a write token"
    );
    let (s, _, body) = call(&app, post("write-token", r#"{"from_ns": 5, "to_ns": 1}"#)).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_window"))
    );
    let (s, _, body) = call(&app, post("write-token", r#"{"from_ns": 0, "to_ns": 1}"#)).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("no_detections"))
    );
    // A reading noise no setter has (these panicked in an SVD of an empty design): 400.
    for sigma in ["1e-5", "1e-93", "0", "-1", "1e6"] {
        let (s, _, body) = call(
            &app,
            post("write-token", &format!(r#"{{"sigma_um": {sigma}}}"#)),
        )
        .await;
        assert_eq!(
            (s, body["code"].as_str()),
            (StatusCode::BAD_REQUEST, Some("bad_sigma")),
            "{sigma}: {body}"
        );
        assert!(
            body["message"].as_str().unwrap().contains("between"),
            "{body}"
        );
    }

    let (s, h, body) = call(&app, post("write-token", "{}")).await;
    assert_eq!(s, StatusCode::CREATED, "{body}");
    assert_eq!(h[header::LOCATION], "/api/v1/machines/m1/diagnoses/1");
    let d = &body["result"]["diagnosis"];
    let cycles = d["cycles"].as_u64().unwrap();
    assert!(cycles >= 5, "{cycles}");
    assert_eq!(d["readings"].as_u64().unwrap(), 24 * cycles);
    assert!(
        d["baseline"]["chi2_dof"].as_f64().unwrap() <= 1.2,
        "{}",
        d["baseline"]
    );
    // Five hours: the last third (the stop and restart) is beyond what the rest showed, and
    // the result says so instead of passing the figure off as a fit.
    assert_eq!(
        d["baseline"]["heldout_extrapolates"], true,
        "{}",
        d["baseline"]
    );
    assert!(body["summary"].as_str().unwrap().contains("readings"));

    let (s, _, list) = call(&app, read("/api/v1/machines/m1/diagnoses")).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(list.as_array().unwrap().len(), 1);
    assert_eq!(list[0]["status"], "done");
    assert_eq!(list[0]["requested_by"], "operator");
    let (s, _, one) = call(&app, read("/api/v1/machines/m1/diagnoses/1")).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(
        one["result"], body["result"],
        "the stored result is the one returned"
    );
    let (s, _, _) = call(&app, get("/api/v1/machines/m1/diagnoses/2")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);

    // A window that starts inside cycle 2 takes that cycle whole.
    let (_, _, c2) = call(&app, get("/api/v1/machines/m1/cycles/2")).await;
    let mid = c2["detections"][5]["t_ns"].as_i64().unwrap();
    let (s, _, body) = call(
        &app,
        post("write-token", &format!(r#"{{"from_ns": {mid}}}"#)),
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{body}");
    let d2 = &body["result"]["diagnosis"];
    assert_eq!(d2["cycles"].as_u64().unwrap(), cycles - 1);
    assert_eq!(d2["readings"].as_u64().unwrap(), 24 * (cycles - 1));

    // One diagnosis at a time: with the slot taken, a request is told to come back.
    let _held = app
        .svc
        .api
        .diagnosis_slots
        .clone()
        .try_acquire_owned()
        .unwrap();
    let (s, _, body) = call(&app, post("write-token", "{}")).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::TOO_MANY_REQUESTS, Some("diagnosis_busy"))
    );
}

/// Cycles, diagnoses and alert events come in pages (`?limit=&before=`,
/// the next one named in a Link header or `next_before`), and the stored diagnoses are capped.
#[tokio::test]
async fn lists_are_paged_and_stored_diagnoses_are_capped() {
    let app = service("paging", true).await;
    let t0 = app.t0();
    app.run_to(t0 + 300 * MIN).await;
    let (_, _, all) = call(&app, get("/api/v1/machines/m1/cycles?limit=1000")).await;
    let all: Vec<i64> = all
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["cycle"].as_i64().unwrap())
        .collect();
    assert!(all.len() >= 5, "{all:?}");
    let mut walked = Vec::new();
    let mut uri = "/api/v1/machines/m1/cycles?limit=2".to_string();
    loop {
        let (s, h, page) = call(&app, get(&uri)).await;
        assert_eq!(s, StatusCode::OK);
        walked.extend(
            page.as_array()
                .unwrap()
                .iter()
                .map(|c| c["cycle"].as_i64().unwrap()),
        );
        let Some(link) = h.get(header::LINK) else {
            break;
        };
        let link = link.to_str().unwrap();
        assert!(link.ends_with("; rel=\"next\""), "{link}");
        uri = link[1..link.find('>').unwrap()].to_string();
    }
    assert_eq!(walked, all);
    let (s, _, body) = call(&app, get("/api/v1/machines/m1/cycles?before=x")).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_query"))
    );

    // Alert events, one per page, by their cursor.
    let (_, _, first) = call(&app, get("/api/v1/machines/m1/alerts?limit=1000")).await;
    let every = first["events"].as_array().unwrap().clone();
    assert!(every.len() >= 2, "{first}");
    let mut seen = Vec::new();
    let mut uri = "/api/v1/machines/m1/alerts?limit=1".to_string();
    loop {
        let (_, _, page) = call(&app, get(&uri)).await;
        seen.extend(page["events"].as_array().unwrap().iter().cloned());
        match page["next_before"].as_str() {
            Some(c) => uri = format!("/api/v1/machines/m1/alerts?limit=1&before={c}"),
            None => break,
        }
        assert!(seen.len() <= every.len(), "the cursor does not advance");
    }
    assert_eq!(seen, every);

    // Diagnoses: the newest `keep` stay, numbers are never given again.
    for i in 0..5 {
        let d = driftwatch_service::store::NewDiagnosis {
            machine: "m1",
            requested_ns: t0 + i,
            requested_by: "test",
            from_ns: 0,
            to_ns: 1,
            status: driftwatch_service::store::DiagnosisStatus::Failed,
            summary: "test",
            result: None,
        };
        assert_eq!(app.store().add_diagnosis(&d, 3).await.unwrap(), i + 1);
    }
    let (_, h, list) = call(&app, get("/api/v1/machines/m1/diagnoses?limit=2")).await;
    let ids: Vec<i64> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["id"].as_i64().unwrap())
        .collect();
    assert_eq!(ids, vec![5, 4]);
    assert!(h[header::LINK].to_str().unwrap().contains("before=4"));
    let (_, _, rest) = call(&app, get("/api/v1/machines/m1/diagnoses?before=4")).await;
    assert_eq!(rest.as_array().unwrap().len(), 1, "{rest}");
    assert_eq!(rest[0]["id"], 3);
}

/// The API's conformance: 413 for a body too large, the JSON error for
/// every failure the framework answers itself, the bearer scheme in any case, /metrics and
/// /readyz behind anonymous_read, token holders' names only for authenticated readers, and an
/// idempotent acknowledgement.
#[tokio::test]
async fn errors_are_json_names_are_for_readers_and_an_ack_is_idempotent() {
    let open = service("conformance", true).await;
    let t0 = open.t0();
    open.run_to(t0 + 100 * MIN).await;
    // The same service with anonymous reads off.
    let closed = service("conformance-closed", false).await;
    let with = |uri: &str, auth: &str| {
        Request::get(uri)
            .header(header::AUTHORIZATION, auth)
            .body(Body::empty())
            .unwrap()
    };
    // The scheme is case-insensitive.
    for auth in [
        "Bearer read-token",
        "bearer read-token",
        "BEARER  read-token",
    ] {
        let (s, _, _) = call(&closed, with("/api/v1/machines", auth)).await;
        assert_eq!(s, StatusCode::OK, "{auth}");
    }
    // Metrics and readiness name the machines: not for anonymous callers of a closed service.
    for uri in ["/metrics", "/readyz"] {
        let (s, _, body) = call(&closed, get(uri)).await;
        assert_eq!(
            (s, body["code"].as_str()),
            (StatusCode::UNAUTHORIZED, Some("token_required"))
        );
        let (s, _, _) = call(&closed, with(uri, "Bearer read-token")).await;
        assert_ne!(s, StatusCode::UNAUTHORIZED, "{uri}");
        assert_ne!(call(&open, get(uri)).await.0, StatusCode::UNAUTHORIZED);
    }
    assert_eq!(call(&closed, get("/healthz")).await.0, StatusCode::OK);
    // A body over the limit is refused on its head, before it is read.
    let (s, content_type, body) = too_large(&open, "/api/v1/machines/m1/diagnoses", 10 << 20).await;
    assert_eq!(
        (s, body["code"].as_str()),
        (StatusCode::PAYLOAD_TOO_LARGE, Some("body_too_large")),
        "{body}"
    );
    assert!(body["message"].as_str().is_some_and(|m| !m.is_empty()));
    assert_eq!(content_type, "application/json");
    // Failures the framework answers: JSON with a code, the status kept.
    for (req, status, code) in [
        (
            get("/api/v1/machines/m1/cycles/abc"),
            StatusCode::BAD_REQUEST,
            "bad_request",
        ),
        (
            get("/api/v1/machines/m1/cycles?limit=x"),
            StatusCode::BAD_REQUEST,
            "bad_request",
        ),
        (
            Request::delete("/api/v1/machines")
                .header(header::AUTHORIZATION, "Bearer write-token")
                .body(Body::empty())
                .unwrap(),
            StatusCode::METHOD_NOT_ALLOWED,
            "method_not_allowed",
        ),
        (get("/nowhere"), StatusCode::NOT_FOUND, "not_found"),
        // A method the path does not have is 405 before any token is asked for.
        (
            Request::put("/metrics").body(Body::empty()).unwrap(),
            StatusCode::METHOD_NOT_ALLOWED,
            "method_not_allowed",
        ),
        (
            Request::delete("/api/v1/machines/m1/cycles")
                .body(Body::empty())
                .unwrap(),
            StatusCode::METHOD_NOT_ALLOWED,
            "method_not_allowed",
        ),
    ] {
        let uri = req.uri().to_string();
        let (s, h, body) = call(&open, req).await;
        assert_eq!(
            (s, body["code"].as_str()),
            (status, Some(code)),
            "{uri}: {body}"
        );
        assert!(
            body["message"].as_str().is_some_and(|m| !m.is_empty()),
            "{uri}"
        );
        assert_eq!(h[header::CONTENT_TYPE], "application/json", "{uri}");
    }

    // Acknowledge once; again is answered 200 with who did it first, and changes nothing.
    let (_, _, alerts) = call(&open, get("/api/v1/machines/m1/alerts")).await;
    let id = alerts["open"][0]["id"].as_u64().expect("an open alert");
    let ack = |token: &str| {
        Request::post(format!("/api/v1/machines/m1/alerts/{id}/ack"))
            .header(header::AUTHORIZATION, format!("Bearer {token}"))
            .body(Body::empty())
            .unwrap()
    };
    assert_eq!(
        call(&open, ack("write-token")).await.0,
        StatusCode::ACCEPTED
    );
    open.run_to(t0 + 101 * MIN).await;
    let (s, _, again) = call(&open, ack("write-token")).await;
    assert_eq!(
        (s, again["already"].as_bool()),
        (StatusCode::OK, Some(true)),
        "{again}"
    );
    assert_eq!(again["by"], "operator");
    // Names: for the token holder, not for an anonymous reader.
    let (_, _, anon) = call(&open, get("/api/v1/machines/m1/alerts")).await;
    let (_, _, reader) = call(
        &open,
        with("/api/v1/machines/m1/alerts", "Bearer read-token"),
    )
    .await;
    let acked = |v: &Value| {
        v["open"]
            .as_array()
            .unwrap()
            .iter()
            .find(|a| a["id"] == id)
            .unwrap()["acknowledged"]["by"]
            .clone()
    };
    assert_eq!(acked(&reader), "operator");
    assert_eq!(acked(&anon), "a token holder");
    assert!(!anon.to_string().contains("operator"), "{anon}");
    let events = |v: &Value| {
        v["events"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| e["kind"] == "acknowledged")
            .count()
    };
    assert_eq!(events(&reader), 1, "{reader}");
}
