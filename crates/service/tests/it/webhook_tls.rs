//! Webhooks over TLS: an https receiver served through rustls with a certificate made by the
//! test (rcgen), trusted through the webhook's `ca_cert`; and a receiver whose certificate
//! chains to another CA, which is refused (failed at once, never delivered).

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::State;
use axum::http::StatusCode;
use axum::routing::post;
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto::Builder;
use hyper_util::service::TowerToHyperService;
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair, KeyUsagePurpose,
    SanType,
};
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};
use tokio_rustls::TlsAcceptor;

use driftwatch_machine::alerts::{AlertEvent, EventKind, Severity};
use driftwatch_service::webhook::{Notifier, WebhookConfig};

/// A CA of the test's own.
fn ca(name: &str) -> CertifiedIssuer<'static, KeyPair> {
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    p.distinguished_name.push(DnType::CommonName, name);
    p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    CertifiedIssuer::self_signed(p, KeyPair::generate().unwrap()).unwrap()
}

/// A server certificate for 127.0.0.1 signed by `ca`, with its key.
fn server_cert(
    ca: &CertifiedIssuer<'static, KeyPair>,
) -> (CertificateDer<'static>, PrivateKeyDer<'static>) {
    let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
    p.subject_alt_names = vec![
        SanType::IpAddress(IpAddr::V4(Ipv4Addr::LOCALHOST)),
        SanType::DnsName("localhost".try_into().unwrap()),
    ];
    p.distinguished_name.push(DnType::CommonName, "receiver");
    let key = KeyPair::generate().unwrap();
    let cert = p.signed_by(&key, ca).unwrap();
    let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(key.serialize_der()));
    (cert.der().clone(), key)
}

type Seen = Arc<Mutex<Vec<serde_json::Value>>>;

async fn receive(State(seen): State<Seen>, body: String) -> StatusCode {
    seen.lock()
        .unwrap()
        .push(serde_json::from_str(&body).unwrap_or(serde_json::Value::Null));
    StatusCode::OK
}

/// An https receiver on 127.0.0.1 presenting `cert`; returns its URL and what it received.
async fn tls_receiver(
    cert: CertificateDer<'static>,
    key: PrivateKeyDer<'static>,
) -> (String, Seen) {
    let provider = Arc::new(rustls::crypto::aws_lc_rs::default_provider());
    let config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_no_client_auth()
        .with_single_cert(vec![cert], key)
        .unwrap();
    let acceptor = TlsAcceptor::from(Arc::new(config));
    let seen: Seen = Arc::default();
    let app = Router::new()
        .route("/hook", post(receive))
        .with_state(seen.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("https://{}/hook", listener.local_addr().unwrap());
    tokio::spawn(async move {
        while let Ok((tcp, _)) = listener.accept().await {
            let (acceptor, app) = (acceptor.clone(), app.clone());
            tokio::spawn(async move {
                // A client that does not trust the certificate ends the handshake here.
                let Ok(tls) = acceptor.accept(tcp).await else {
                    return;
                };
                let _ = Builder::new(TokioExecutor::new())
                    .serve_connection(TokioIo::new(tls), TowerToHyperService::new(app))
                    .await;
            });
        }
    });
    (url, seen)
}

fn scratch(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn event(id: u64) -> AlertEvent {
    AlertEvent {
        id,
        rule: "threshold:EZ0B".into(),
        kind: EventKind::Raised,
        t_ns: 1_700_000_000_000_000_000,
        cycle: 7,
        severity: Severity::Critical,
        message: "EZ0B is 31.2 um from its reference (limit 30)".into(),
        value: 31.2,
        acknowledged: false,
    }
}

fn hook(url: &str, ca_cert: Option<&std::path::Path>) -> WebhookConfig {
    let mut text =
        format!("url = \"{url}\"\nmax_attempts = 4\nfirst_retry_s = 0.01\nmax_retry_s = 0.05\n");
    if let Some(p) = ca_cert {
        text.push_str(&format!("ca_cert = {:?}\n", p.display().to_string()));
    }
    toml::from_str(&text).unwrap()
}

/// Send one event and wait for its delivery task: [delivered, retried, failed, dropped].
async fn send(cfg: WebhookConfig) -> [u64; 4] {
    let (n, tasks) = Notifier::start(vec![(cfg, Some("tls-token".into()))]).unwrap();
    n.notify("vmc-1", &event(3));
    let stats = n.stats.clone();
    drop(n);
    for t in tasks {
        t.await.unwrap();
    }
    [
        stats.delivered.load(Relaxed),
        stats.retried.load(Relaxed),
        stats.failed.load(Relaxed),
        stats.dropped.load(Relaxed),
    ]
}

#[tokio::test]
async fn an_alert_reaches_an_https_receiver_trusted_through_ca_cert() {
    let dir = scratch("webhook-tls-ok");
    let plant_ca = ca("plant CA");
    let ca_file = dir.join("plant-ca.pem");
    std::fs::write(&ca_file, plant_ca.pem()).unwrap();
    let (cert, key) = server_cert(&plant_ca);
    let (url, seen) = tls_receiver(cert, key).await;

    assert_eq!(send(hook(&url, Some(&ca_file))).await, [1, 0, 0, 0]);
    let seen = seen.lock().unwrap();
    assert_eq!(seen.len(), 1);
    assert_eq!(seen[0]["machine"], "vmc-1");
    assert_eq!(seen[0]["event"]["id"], 3);
    assert_eq!(seen[0]["event"]["rule"], "threshold:EZ0B");
    assert_eq!(seen[0]["event"]["value"], 31.2);
}

#[tokio::test]
async fn a_receiver_whose_certificate_is_not_trusted_is_refused() {
    let dir = scratch("webhook-tls-untrusted");
    let plant_ca = ca("plant CA");
    let ca_file = dir.join("plant-ca.pem");
    std::fs::write(&ca_file, plant_ca.pem()).unwrap();
    // The receiver's certificate chains to another CA, trusted neither by the system nor by
    // the webhook's ca_cert.
    let (cert, key) = server_cert(&ca("someone else's CA"));
    let (url, seen) = tls_receiver(cert, key).await;

    // Failed at the first attempt, not retried (the same certificate stays untrusted), and
    // nothing reached the receiver.
    assert_eq!(send(hook(&url, Some(&ca_file))).await, [0, 0, 1, 0]);
    assert_eq!(send(hook(&url, None)).await, [0, 0, 1, 0]);
    assert!(seen.lock().unwrap().is_empty());
}

#[tokio::test]
async fn a_ca_cert_that_cannot_be_read_stops_the_start() {
    let dir = scratch("webhook-tls-bad-ca");
    let missing = dir.join("missing.pem");
    let e = Notifier::start(vec![(
        hook("https://127.0.0.1:9/hook", Some(&missing)),
        None,
    )])
    .err()
    .unwrap();
    assert!(e.contains("missing.pem"), "{e}");
    let garbage = dir.join("garbage.pem");
    std::fs::write(&garbage, "not a certificate").unwrap();
    let e = Notifier::start(vec![(
        hook("https://127.0.0.1:9/hook", Some(&garbage)),
        None,
    )])
    .err()
    .unwrap();
    assert!(e.contains("garbage.pem"), "{e}");
}
