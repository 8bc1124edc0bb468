//! Alert delivery to webhooks: every alert event (raised, updated, resolved) is POSTed as JSON
//! to each configured URL, in order, retried with exponential backoff while the receiver is down
//! or answers 5xx, 408 or 429. A 4xx answer is final (the receiver refused the request; retrying
//! the same body cannot help). Delivery never blocks a machine loop: events wait in a bounded
//! queue per webhook, and the events are in the database whatever happens to the delivery.
//!
//! `https://` receivers are reached through rustls (no system OpenSSL): the server's
//! certificate must chain to the system's roots or to the webhook's own `ca_cert` (a plant's
//! internal CA). A certificate that does not verify is a refusal, not a network error: it is
//! final (counted as failed), since sending the same request again cannot make it trusted.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::sync::mpsc;
use tracing::{error, info, warn};

use driftwatch_machine::alerts::{AlertEvent, Severity};

/// Events waiting per webhook before new ones are dropped (they stay in the database).
const QUEUE: usize = 1024;

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhookConfig {
    /// `http://` or `https://` URL the events are POSTed to.
    pub url: String,
    /// A PEM file of CA certificates trusted for this `https` receiver besides the system's
    /// (a plant-internal CA).
    #[serde(default)]
    pub ca_cert: Option<std::path::PathBuf>,
    /// Optional bearer token sent as `Authorization`, or `env:VAR`.
    #[serde(default)]
    pub token: Option<String>,
    /// Events of lower severity are not sent.
    #[serde(default = "default_severity")]
    pub min_severity: Severity,
    /// Attempts per event before it is given up (logged as an error).
    #[serde(default = "default_attempts")]
    pub max_attempts: u32,
    /// Wait before the first retry, seconds; it doubles at each further retry.
    #[serde(default = "default_first_retry")]
    pub first_retry_s: f64,
    /// Longest wait between retries, seconds.
    #[serde(default = "default_max_retry")]
    pub max_retry_s: f64,
    /// Time allowed for one attempt, seconds.
    #[serde(default = "default_timeout")]
    pub timeout_s: f64,
}

fn default_severity() -> Severity {
    Severity::Warning
}
fn default_attempts() -> u32 {
    8
}
fn default_first_retry() -> f64 {
    1.0
}
fn default_max_retry() -> f64 {
    300.0
}
fn default_timeout() -> f64 {
    5.0
}

impl WebhookConfig {
    pub fn validate(&self) -> Result<(), String> {
        let url = reqwest::Url::parse(&self.url)
            .map_err(|e| format!("webhook url '{}': {e}", self.url))?;
        match url.scheme() {
            "https" => {}
            "http" if self.ca_cert.is_none() => {}
            "http" => {
                return Err(format!(
                    "webhook url '{}': ca_cert is for https receivers; this one is http",
                    self.url
                ));
            }
            s => {
                return Err(format!(
                    "webhook url '{}': scheme '{s}' is not http or https",
                    self.url
                ));
            }
        }
        if self.max_attempts == 0 {
            return Err("webhook max_attempts must be at least 1".into());
        }
        for (k, v) in [
            ("first_retry_s", self.first_retry_s),
            ("max_retry_s", self.max_retry_s),
            ("timeout_s", self.timeout_s),
        ] {
            if !driftwatch_core::units::positive(v) {
                return Err(format!("webhook {k} must be > 0, not {v}"));
            }
        }
        Ok(())
    }

    /// Wait before attempt `attempt` (1-based; the first attempt does not wait).
    pub fn delay_before(&self, attempt: u32) -> Duration {
        if attempt <= 1 {
            return Duration::ZERO;
        }
        let s = self.first_retry_s * 2f64.powi((attempt - 2).min(60) as i32);
        Duration::from_secs_f64(s.min(self.max_retry_s))
    }
}

/// What a webhook receives.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Notification {
    pub machine: String,
    /// The event time as RFC 3339, for people.
    pub time: String,
    pub event: AlertEvent,
    pub source: String,
}

impl Notification {
    pub fn new(machine: &str, event: &AlertEvent) -> Self {
        Notification {
            machine: machine.to_string(),
            time: chrono::DateTime::from_timestamp_nanos(event.t_ns).to_rfc3339(),
            event: event.clone(),
            source: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        }
    }
}

/// Delivery counters, shown on `/metrics`.
#[derive(Debug, Default)]
pub struct WebhookStats {
    pub delivered: AtomicU64,
    pub retried: AtomicU64,
    pub failed: AtomicU64,
    pub dropped: AtomicU64,
}

/// The sending end, cloned into every machine loop.
#[derive(Clone, Default)]
pub struct Notifier {
    hooks: Vec<(Severity, String, mpsc::Sender<Arc<Notification>>)>,
    pub stats: Arc<WebhookStats>,
}

/// How one attempt ended.
#[derive(Debug, PartialEq)]
enum Outcome {
    Delivered,
    Retry(String),
    Refused(String),
}

impl Notifier {
    /// Start one delivery task per webhook; `token`s are already resolved. Returns the
    /// notifier and the tasks, which end once every notifier clone is dropped and their
    /// queues are empty.
    pub fn start(
        hooks: Vec<(WebhookConfig, Option<String>)>,
    ) -> Result<(Notifier, Vec<tokio::task::JoinHandle<()>>), String> {
        let stats = Arc::new(WebhookStats::default());
        let mut senders = Vec::new();
        let mut tasks = Vec::new();
        for (cfg, token) in hooks {
            cfg.validate()?;
            let mut builder =
                reqwest::Client::builder().timeout(Duration::from_secs_f64(cfg.timeout_s));
            if let Some(path) = &cfg.ca_cert {
                builder = builder.tls_certs_merge(ca_certs(path)?);
            }
            let client = builder
                .build()
                .map_err(|e| format!("webhook {} client: {e}", cfg.url))?;
            let (tx, rx) = mpsc::channel(QUEUE);
            senders.push((cfg.min_severity, cfg.url.clone(), tx));
            tasks.push(tokio::spawn(deliver(cfg, token, client, rx, stats.clone())));
        }
        Ok((
            Notifier {
                hooks: senders,
                stats,
            },
            tasks,
        ))
    }

    pub fn is_empty(&self) -> bool {
        self.hooks.is_empty()
    }

    /// Queue the event for every webhook that wants its severity; never waits.
    pub fn notify(&self, machine: &str, event: &AlertEvent) {
        if self.hooks.is_empty() {
            return;
        }
        let n = Arc::new(Notification::new(machine, event));
        for (min, url, tx) in &self.hooks {
            if event.severity < *min {
                continue;
            }
            if tx.try_send(n.clone()).is_err() {
                self.stats.dropped.fetch_add(1, Ordering::Relaxed);
                error!(url = %url, alert = event.id, "webhook queue full or closed: event not sent (it is stored)");
            }
        }
    }
}

/// The CA certificates of a PEM file (one or more), or why there are none.
fn ca_certs(path: &std::path::Path) -> Result<Vec<reqwest::Certificate>, String> {
    let what = |m: String| format!("webhook ca_cert {}: {m}", path.display());
    let pem = std::fs::read(path).map_err(|e| what(e.to_string()))?;
    let certs = reqwest::Certificate::from_pem_bundle(&pem).map_err(|e| what(e.to_string()))?;
    if certs.is_empty() {
        return Err(what("no PEM certificate in it".into()));
    }
    Ok(certs)
}

/// Whether a failed request failed because the receiver's certificate did not verify: rustls
/// says so in an I/O error of the connection, nested in I/O errors whose `source` skips it (so
/// the chain is walked through `get_ref` too).
fn untrusted(e: &reqwest::Error) -> Option<String> {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(err) = cur {
        if let Some(rustls::Error::InvalidCertificate(c)) = err.downcast_ref::<rustls::Error>() {
            return Some(format!("the receiver's certificate is not trusted: {c:?}"));
        }
        cur = match err
            .downcast_ref::<std::io::Error>()
            .and_then(|io| io.get_ref())
        {
            Some(inner) => Some(inner as &(dyn std::error::Error + 'static)),
            None => err.source(),
        };
    }
    None
}

async fn deliver(
    cfg: WebhookConfig,
    token: Option<String>,
    client: reqwest::Client,
    mut rx: mpsc::Receiver<Arc<Notification>>,
    stats: Arc<WebhookStats>,
) {
    while let Some(n) = rx.recv().await {
        let body = match serde_json::to_vec(&*n) {
            Ok(b) => b,
            Err(e) => {
                error!("webhook body: {e}");
                continue;
            }
        };
        let mut attempt = 1;
        loop {
            tokio::time::sleep(cfg.delay_before(attempt)).await;
            let mut req = client
                .post(&cfg.url)
                .header(reqwest::header::CONTENT_TYPE, "application/json")
                .body(body.clone());
            if let Some(t) = &token {
                req = req.bearer_auth(t);
            }
            let outcome = match req.send().await {
                Ok(r) if r.status().is_success() => Outcome::Delivered,
                Ok(r) => {
                    let s = r.status();
                    if s.is_server_error() || s.as_u16() == 408 || s.as_u16() == 429 {
                        Outcome::Retry(format!("answered {s}"))
                    } else {
                        Outcome::Refused(format!("answered {s}"))
                    }
                }
                Err(e) => match untrusted(&e) {
                    Some(why) => Outcome::Refused(why),
                    None => Outcome::Retry(e.to_string()),
                },
            };
            match outcome {
                Outcome::Delivered => {
                    stats.delivered.fetch_add(1, Ordering::Relaxed);
                    info!(url = %cfg.url, machine = %n.machine, alert = n.event.id, attempt, "alert delivered to webhook");
                    break;
                }
                Outcome::Refused(why) => {
                    stats.failed.fetch_add(1, Ordering::Relaxed);
                    error!(url = %cfg.url, machine = %n.machine, alert = n.event.id, "webhook refused the alert ({why}); not retried");
                    break;
                }
                Outcome::Retry(why) if attempt >= cfg.max_attempts => {
                    stats.failed.fetch_add(1, Ordering::Relaxed);
                    error!(url = %cfg.url, machine = %n.machine, alert = n.event.id, "alert not delivered after {attempt} attempts: {why}");
                    break;
                }
                Outcome::Retry(why) => {
                    stats.retried.fetch_add(1, Ordering::Relaxed);
                    warn!(url = %cfg.url, alert = n.event.id, attempt, "webhook delivery failed ({why}); retrying in {:?}", cfg.delay_before(attempt + 1));
                    attempt += 1;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(url: &str) -> WebhookConfig {
        toml::from_str(&format!("url = \"{url}\"")).unwrap()
    }

    #[test]
    fn backoff_doubles_up_to_its_limit() {
        let c = cfg("http://127.0.0.1:9/hook");
        let d: Vec<f64> = (1..=12).map(|a| c.delay_before(a).as_secs_f64()).collect();
        assert_eq!(&d[..5], &[0.0, 1.0, 2.0, 4.0, 8.0]);
        assert_eq!(d[9], 256.0);
        assert_eq!((d[10], d[11]), (300.0, 300.0));
    }

    #[test]
    fn http_and_https_urls_are_taken() {
        assert!(cfg("http://relay.plant:8000/alerts").validate().is_ok());
        assert!(cfg("https://hooks.example/x").validate().is_ok());
        let mut c = cfg("http://relay.plant:8000/alerts");
        c.ca_cert = Some("plant-ca.pem".into());
        let e = c.validate().unwrap_err();
        assert!(e.contains("ca_cert is for https"), "{e}");
        assert!(cfg("ftp://x/y").validate().is_err());
        assert!(cfg("not a url").validate().is_err());
        let mut c = cfg("http://x/");
        c.max_attempts = 0;
        assert!(c.validate().is_err());
    }
}
