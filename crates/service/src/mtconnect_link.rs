//! The `mtconnect` machine link: follows an MTConnect agent's `current` and `sample` streams
//! over HTTP and hands the service loop the contract's `/spindle`, `/machine/state` and
//! `/temperature` messages. The parsing and the sequence bookkeeping are `mtconnect`'s; this
//! is the thin shell around them: a background task asks the agent, and `poll` drains what it
//! found, so the machine loop never waits on the network.
//!
//! MTConnect is read-only: an agent publishes what the control does and takes no orders. This
//! link observes; `request_cycle` answers [`LinkError::ObserveOnly`], and cycles must be
//! ordered by another route. Without cycles the service still keeps the machine's phase, its
//! spindle and temperature series and recordings, and serves predictions from a thermal model
//! given with `thermal_model`.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use thiserror::Error;
use tokio::sync::{Notify, mpsc};
use tokio_util::sync::{CancellationToken, DropGuard};
use tracing::{error, info, warn};

use crate::link::{LinkError, LinkEvent, MachineLink};
use crate::mtconnect::{Document, FollowStats, Follower, Items, MtcError, Note, Request, parse};
use crate::nc_push::ClockTolerance;
use driftwatch_core::kinematics::Limits;

/// One answer may take this long; an agent that does not answer by then is asked again later.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);
/// The longest wait between attempts while the agent cannot be reached.
const MAX_BACKOFF: Duration = Duration::from_secs(30);
/// Batches of events waiting for the loop. When it is full the task waits: the agent's buffer
/// holds what comes meanwhile, and a buffer that overran is a gap, measured and logged.
const CHANNEL: usize = 64;

#[derive(Debug, Error)]
pub enum MtconnectLinkError {
    #[error("agent url '{url}': {message}")]
    Url { url: String, message: String },
    #[error("the HTTP client: {0}")]
    Client(String),
}

/// What the link is configured with (the `[[machines]]` entry's `link`).
#[derive(Debug, Clone)]
pub struct MtconnectSettings {
    pub agent: String,
    pub device: Option<String>,
    pub items: Items,
    pub poll: Duration,
    pub count: u32,
    pub tolerance: ClockTolerance,
}

/// How following the agent goes, for tests and operators.
#[derive(Debug, Clone, Default)]
pub struct MtconnectStatus {
    pub stats: FollowStats,
    pub instance: Option<String>,
    /// The last failure (network, HTTP status, a document that is not MTConnect), until an
    /// answer is taken again.
    pub last_error: Option<String>,
    /// Events refused because their time lay too far from the service clock.
    pub refused_clock_skew: u64,
}

/// The service side: a `MachineLink` fed by the background task.
pub struct MtconnectLink {
    rx: mpsc::Receiver<Vec<LinkEvent>>,
    /// Notified by the task after each batch it sends: the loop's wake.
    wake: Arc<Notify>,
    tolerance: ClockTolerance,
    status: Arc<Mutex<MtconnectStatus>>,
    /// Stops the task when the link goes.
    _stop: DropGuard,
}

/// `agent/[device/]what`, with the device as one path segment.
pub fn endpoint(
    agent: &str,
    device: Option<&str>,
    what: &str,
) -> Result<reqwest::Url, MtconnectLinkError> {
    let bad = |message: String| MtconnectLinkError::Url {
        url: agent.to_string(),
        message,
    };
    let mut url = reqwest::Url::parse(agent).map_err(|e| bad(e.to_string()))?;
    if !matches!(url.scheme(), "http" | "https") {
        return Err(bad(format!(
            "scheme '{}' is not http or https",
            url.scheme()
        )));
    }
    {
        let mut path = url
            .path_segments_mut()
            .map_err(|_| bad("cannot hold a path".into()))?;
        path.pop_if_empty();
        if let Some(d) = device {
            path.push(d);
        }
        path.push(what);
    }
    Ok(url)
}

impl MtconnectLink {
    /// Start following the agent (needs a tokio runtime).
    pub fn start(
        machine: &str,
        settings: MtconnectSettings,
        limits: Limits,
    ) -> Result<Self, MtconnectLinkError> {
        // Checked here, so that a bad URL fails the start instead of every request.
        endpoint(&settings.agent, settings.device.as_deref(), "current")?;
        let client = reqwest::Client::builder()
            .timeout(REQUEST_TIMEOUT)
            .build()
            .map_err(|e| MtconnectLinkError::Client(e.to_string()))?;
        let (tx, rx) = mpsc::channel(CHANNEL);
        let wake = Arc::new(Notify::new());
        let status = Arc::new(Mutex::new(MtconnectStatus::default()));
        let stop = CancellationToken::new();
        let follower = Follower::new(settings.items.clone(), limits, settings.count);
        tokio::spawn(follow(
            Task {
                machine: machine.to_string(),
                client,
                settings: settings.clone(),
                status: status.clone(),
                tx,
                wake: wake.clone(),
                stop: stop.clone(),
            },
            follower,
        ));
        Ok(MtconnectLink {
            rx,
            wake,
            tolerance: settings.tolerance,
            status,
            _stop: stop.drop_guard(),
        })
    }

    pub fn status(&self) -> MtconnectStatus {
        self.status.lock().map(|s| s.clone()).unwrap_or_default()
    }
}

struct Task {
    machine: String,
    client: reqwest::Client,
    settings: MtconnectSettings,
    status: Arc<Mutex<MtconnectStatus>>,
    tx: mpsc::Sender<Vec<LinkEvent>>,
    wake: Arc<Notify>,
    stop: CancellationToken,
}

impl Task {
    async fn ask(&self, asked: Request) -> Result<Document, String> {
        let s = &self.settings;
        let device = s.device.as_deref();
        let url = match asked {
            Request::Current => endpoint(&s.agent, device, "current"),
            Request::Sample { from, count } => endpoint(&s.agent, device, "sample").map(|mut u| {
                u.query_pairs_mut()
                    .append_pair("from", &from.to_string())
                    .append_pair("count", &count.to_string());
                u
            }),
        }
        .map_err(|e| e.to_string())?;
        let answer = self
            .client
            .get(url.clone())
            .send()
            .await
            .map_err(|e| format!("GET {url}: {e}"))?;
        let status = answer.status();
        let text = answer.text().await.map_err(|e| format!("GET {url}: {e}"))?;
        // An agent answers errors (OUT_OF_RANGE, NO_DEVICE) with an error document and a 4xx
        // status: the document says more than the status.
        match parse(&text, device) {
            Ok(doc) => Ok(doc),
            Err(e) if status.is_success() => Err(format!("GET {url}: {e}")),
            Err(_) => Err(format!("GET {url}: answered {status}")),
        }
    }

    fn log(&self, note: &Note) {
        let m = &self.machine;
        match note {
            Note::Restarted { old, new } => warn!(
                machine = %m, old_instance = %old, new_instance = %new,
                "the MTConnect agent restarted: current read again, following the new instance from its first sequence (observations taken before are not taken again)"
            ),
            Note::Gap { from, first, lost } => error!(
                machine = %m, from, first_sequence = first, lost,
                "MTConnect sequence gap: {lost} observations left the agent's buffer before they were read (data lost); resuming at its first sequence"
            ),
            Note::Rewound { from, next } => warn!(
                machine = %m, from, next_sequence = next,
                "the MTConnect agent's sequence lies behind the one asked for with the same instance: resuming at its next sequence"
            ),
            Note::Refused { item, message } => {
                warn!(machine = %m, item = %item, "MTConnect observation not taken: {message}")
            }
            Note::Unavailable { item } => info!(
                machine = %m, item = %item,
                "MTConnect data item UNAVAILABLE: the last value holds"
            ),
        }
    }
}

/// The background task: ask, take, hand over, wait; until the link is dropped.
async fn follow(task: Task, mut follower: Follower) {
    let mut failures: u32 = 0;
    loop {
        let asked = follower.request();
        let taken = match task.ask(asked).await {
            Ok(doc) => follower
                .take(asked, doc)
                .map_err(|e: MtcError| e.to_string()),
            Err(e) => Err(e),
        };
        let wait = match taken {
            Ok((events, notes)) => {
                if failures > 0 {
                    info!(machine = %task.machine, "the MTConnect agent answers again");
                }
                failures = 0;
                for n in &notes {
                    task.log(n);
                }
                if let Ok(mut s) = task.status.lock() {
                    s.stats = follower.stats;
                    s.instance = follower.instance().map(str::to_string);
                    s.last_error = None;
                }
                if !events.is_empty() {
                    tokio::select! {
                        sent = task.tx.send(events) => match sent {
                            Ok(()) => task.wake.notify_one(),
                            Err(_) => return,
                        },
                        _ = task.stop.cancelled() => return,
                    }
                }
                // More is waiting (a resync, or a full page): at once.
                if matches!(follower.request(), Request::Current) || follower.behind {
                    Duration::ZERO
                } else {
                    task.settings.poll
                }
            }
            Err(e) => {
                failures += 1;
                let wait = task
                    .settings
                    .poll
                    .saturating_mul(1 << failures.min(8))
                    .min(MAX_BACKOFF);
                // The first failure of a run is an error, the rest of it is repeated quietly.
                if failures == 1 {
                    error!(machine = %task.machine, error = %e, "the MTConnect agent could not be read; trying again with doubling waits");
                } else {
                    warn!(machine = %task.machine, error = %e, attempt = failures, "the MTConnect agent still cannot be read");
                }
                if let Ok(mut s) = task.status.lock() {
                    s.last_error = Some(e);
                }
                wait
            }
        };
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = task.stop.cancelled() => return,
        }
    }
}

impl MachineLink for MtconnectLink {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        let mut out = Vec::new();
        let mut refused = 0u64;
        let mut worst = 0i64;
        while let Ok(batch) = self.rx.try_recv() {
            for ev in batch {
                // The agent's clock, not the service's: an event stamped far from the service
                // clock is refused as nc_push refuses it (a state an hour ahead would hide
                // every correct one after it).
                let skew = ev.t_ns().saturating_sub(now_ns);
                let limit = if skew > 0 {
                    self.tolerance.ahead_ns
                } else {
                    self.tolerance.behind_ns
                };
                if skew.unsigned_abs() > limit.unsigned_abs() {
                    refused += 1;
                    if skew.unsigned_abs() > worst.unsigned_abs() {
                        worst = skew;
                    }
                } else {
                    out.push(ev);
                }
            }
        }
        out.sort_by_key(LinkEvent::t_ns);
        if refused > 0 {
            warn!(
                refused,
                worst_skew_s = worst as f64 / 1e9,
                "MTConnect observations refused for their time stamps: is the agent's clock synchronised?"
            );
            if let Ok(mut s) = self.status.lock() {
                s.refused_clock_skew += refused;
            }
            out.push(LinkEvent::ClockSkew {
                t_ns: now_ns,
                refused,
                worst_skew_ns: worst,
            });
        }
        out
    }

    fn request_cycle(&mut self, _number: i64, _now_ns: i64) -> Result<(), LinkError> {
        Err(LinkError::ObserveOnly("mtconnect"))
    }

    fn abort_cycle(&mut self, _number: i64, _now_ns: i64) {}

    fn next_event_ns(&self) -> Option<i64> {
        // The agent's news come when they come: the task wakes the loop.
        None
    }

    fn waker(&self) -> Option<Arc<Notify>> {
        Some(self.wake.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_put_the_device_in_the_path() {
        let u = endpoint("http://agent.plant:5000", Some("VMC 1"), "current").unwrap();
        assert_eq!(u.as_str(), "http://agent.plant:5000/VMC%201/current");
        let u = endpoint("http://agent.plant:5000/mtc/", None, "sample").unwrap();
        assert_eq!(u.as_str(), "http://agent.plant:5000/mtc/sample");
        assert!(endpoint("ftp://agent", None, "current").is_err());
        assert!(endpoint("agent:5000", None, "current").is_err());
    }
}
