//! Alert webhooks: JSON bodies in order, retried with backoff while the receiver fails, not
//! retried when it refuses.

use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::routing::post;
use driftwatch_machine::alerts::{AlertEvent, EventKind, Severity};
use driftwatch_service::webhook::{Notifier, WebhookConfig};

#[derive(Default)]
struct Receiver {
    /// Status codes to answer, in order; 200 once they run out.
    script: Vec<u16>,
    seen: Vec<(u16, serde_json::Value, Option<String>)>,
}

async fn receive(
    State(r): State<Arc<Mutex<Receiver>>>,
    headers: HeaderMap,
    body: String,
) -> StatusCode {
    let mut r = r.lock().unwrap();
    let status = if r.script.is_empty() {
        200
    } else {
        r.script.remove(0)
    };
    let auth = headers
        .get("authorization")
        .map(|v| v.to_str().unwrap().to_string());
    r.seen
        .push((status, serde_json::from_str(&body).unwrap(), auth));
    StatusCode::from_u16(status).unwrap()
}

async fn receiver(script: Vec<u16>) -> (String, Arc<Mutex<Receiver>>) {
    let r = Arc::new(Mutex::new(Receiver {
        script,
        seen: Vec::new(),
    }));
    let app = Router::new()
        .route("/hook", post(receive))
        .with_state(r.clone());
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}/hook", l.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(l, app).await });
    (url, r)
}

fn event(id: u64, kind: EventKind, severity: Severity) -> AlertEvent {
    AlertEvent {
        id,
        rule: "threshold:EZ0B".into(),
        kind,
        t_ns: 1_700_000_000_000_000_000,
        cycle: 7,
        severity,
        message: "EZ0B is 31.2 um from its reference (limit 30)".into(),
        value: 31.2,
        acknowledged: false,
    }
}

fn hook(url: &str, extra: &str) -> WebhookConfig {
    toml::from_str(&format!(
        "url = \"{url}\"\nfirst_retry_s = 0.01\nmax_retry_s = 0.05\n{extra}"
    ))
    .unwrap()
}

async fn send_all(cfg: WebhookConfig, token: Option<String>, events: &[AlertEvent]) -> [u64; 4] {
    let (n, tasks) = Notifier::start(vec![(cfg, token)]).unwrap();
    for e in events {
        n.notify("sim-1", e);
    }
    let stats = n.stats.clone();
    drop(n);
    for t in tasks {
        t.await.unwrap();
    }
    use std::sync::atomic::Ordering::Relaxed;
    [
        stats.delivered.load(Relaxed),
        stats.retried.load(Relaxed),
        stats.failed.load(Relaxed),
        stats.dropped.load(Relaxed),
    ]
}

#[tokio::test]
async fn events_arrive_in_order_after_retries() {
    let (url, r) = receiver(vec![503, 500]).await;
    let events = [
        event(1, EventKind::Raised, Severity::Warning),
        event(1, EventKind::Resolved, Severity::Warning),
    ];
    let stats = send_all(hook(&url, ""), Some("s3cret".into()), &events).await;
    assert_eq!(stats, [2, 2, 0, 0]);
    let r = r.lock().unwrap();
    let codes: Vec<u16> = r.seen.iter().map(|s| s.0).collect();
    assert_eq!(codes, [503, 500, 200, 200]);
    let kinds: Vec<&str> = r
        .seen
        .iter()
        .map(|s| s.1["event"]["kind"].as_str().unwrap())
        .collect();
    assert_eq!(kinds, ["raised", "raised", "raised", "resolved"]);
    let body = &r.seen[2].1;
    assert_eq!(body["machine"], "sim-1");
    assert_eq!(body["event"]["rule"], "threshold:EZ0B");
    assert_eq!(body["event"]["value"], 31.2);
    assert_eq!(body["time"], "2023-11-14T22:13:20+00:00");
    assert_eq!(r.seen[0].2.as_deref(), Some("Bearer s3cret"));
}

#[tokio::test]
async fn a_refusal_is_final_and_retries_stop_at_the_limit() {
    let (url, r) = receiver(vec![400, 503, 503, 503]).await;
    let events = [
        event(1, EventKind::Raised, Severity::Critical),
        event(2, EventKind::Raised, Severity::Critical),
    ];
    let stats = send_all(hook(&url, "max_attempts = 3"), None, &events).await;
    // The first event is refused once; the second fails three times and is given up.
    assert_eq!(stats, [0, 2, 2, 0]);
    let r = r.lock().unwrap();
    assert_eq!(r.seen.len(), 4);
    assert_eq!(r.seen[0].2, None);
}

#[tokio::test]
async fn severity_below_the_minimum_is_not_sent_and_a_dead_receiver_is_given_up() {
    let (url, r) = receiver(vec![]).await;
    let events = [
        event(1, EventKind::Raised, Severity::Warning),
        event(2, EventKind::Raised, Severity::Critical),
    ];
    let stats = send_all(hook(&url, "min_severity = \"critical\""), None, &events).await;
    assert_eq!(stats, [1, 0, 0, 0]);
    assert_eq!(r.lock().unwrap().seen[0].1["event"]["id"], 2);

    // Nothing listens on this port: connection refused, retried, then given up.
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let dead = format!("http://{}/hook", l.local_addr().unwrap());
    drop(l);
    let stats = send_all(hook(&dead, "max_attempts = 2"), None, &events[..1]).await;
    assert_eq!(stats, [0, 1, 1, 0]);
}

#[test]
fn the_documented_example_in_the_default_configuration_parses() {
    let text = driftwatch_service::config::DEFAULT_CONFIG;
    let block: String = text
        .lines()
        .skip_while(|l| !l.starts_with("# [[webhooks]]"))
        .map_while(|l| l.strip_prefix("# "))
        .collect::<Vec<_>>()
        .join("\n");
    assert!(block.contains("max_attempts"), "{block}");
    let with = format!("{text}\n{block}\n");
    let cfg = driftwatch_service::config::ServiceConfig::from_toml(&with, "t").unwrap();
    assert_eq!(cfg.webhooks.len(), 1);
    assert_eq!(cfg.webhooks[0].max_attempts, 8);
    // https is built in; a ca_cert is for https receivers only.
    let tls = with.replace("http://127.0.0.1:9000", "https://127.0.0.1:9000");
    assert!(driftwatch_service::config::ServiceConfig::from_toml(&tls, "t").is_ok());
    let bad = format!("{with}ca_cert = \"plant-ca.pem\"\n");
    let e = driftwatch_service::config::ServiceConfig::from_toml(&bad, "t")
        .unwrap_err()
        .to_string();
    assert!(e.contains("ca_cert is for https"), "{e}");
}
