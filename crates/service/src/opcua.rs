//! The `opcua` machine link: driftwatch is an OPC UA client of the NC (or of the PLC or gateway
//! that publishes it). It subscribes to the spindle speed, the program state and temperatures,
//! orders a cycle by writing a node, reads each latched position back from a node the NC
//! program updates per approach, and may write each served compensation set to nodes.
//!
//! The cycle bookkeeping is `nc_push`'s, not a copy: the link owns an [`NcPushLink`] and feeds
//! what it reads through the same door ([`NcPushHandle::post`]), so an OPC UA machine is held
//! to the same checks (the machine file's limits, the clock tolerance, detections against the
//! order) and a cycle closes by the same rules (every measurement tripped, or the NC leaving
//! `measuring` after detections). All network I/O runs in a background task; the service loop's
//! `poll` only takes what that task has queued, so a slow or dead server never holds it up.
//!
//! The node contract (docs/integrate-nc.md, "The node contract"):
//! - `cycle_request` (String, written by driftwatch): the order as JSON, the shape of nc_push's
//!   `GET .../nc/request` answer (`cycle`, `plan`, `spindle_rpm`, `steps`), or `""` when
//!   nothing is asked (written when the cycle closes or is aborted). The NC runs a cycle number
//!   at most once (driftwatch writes an open order again after a reconnect if it has read no
//!   detection of it yet).
//! - `detections` (String, written by the NC): `{"cycle": N, "detections": [{"t_ns": ..,
//!   "msg": {<a /probe/detection message>}}, ...]}`, one entry appended per approach (a
//!   `no_trip` one included), a new document for a new cycle. The document is cumulative, so a
//!   change coalesced by the subscription or missed during a reconnect loses nothing: entries
//!   are taken by position, once each.
//! - `execution` (any scalar): the program state, mapped to the NC state by `states`; while an
//!   order is open a state mapped to `cutting` is the measurement program running, and is
//!   reported as `measuring`.
//! - `spindle_speed` (number, min^-1) and each `temperatures` entry (number, deg C).
//! - each `compensation` entry (Double; `version`: Int64): written from the served set, the
//!   version last, so an NC that reacts to the version reads a complete set.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use opcua::client::{ClientBuilder, DataChangeCallback, IdentityToken, MonitoredItem, Session};
use opcua::crypto::SecurityPolicy;
use opcua::types::{
    AttributeId, DataValue, MessageSecurityMode, MonitoredItemCreateRequest, NodeId, NumericRange,
    ReadValueId, StatusCode, TimestampsToReturn, UAString, UserTokenPolicy, Variant, WriteValue,
};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use thiserror::Error;
use tokio::sync::mpsc;
use tracing::{info, warn};

use crate::link::{LinkError, LinkEvent, MachineLink};
use crate::nc_push::{
    ClockTolerance, CycleOrder, EventBatch, NcPushHandle, NcPushLink, PostedEvent, nc_push,
};
use driftwatch_core::kinematics::Limits;
use driftwatch_core::plan::Plan;
use driftwatch_core::recording::{self as rec, MachineStateKind};
use driftwatch_machine::compensation::CompensationSet;

#[derive(Debug, Error)]
pub enum OpcuaError {
    #[error("opcua link: endpoint '{0}' is not an opc.tcp:// URL")]
    Endpoint(String),
    #[error(
        "opcua link: nodes.{key} = '{id}' is not a node id (e.g. ns=2;s=Spindle/Speed): {status}"
    )]
    NodeId {
        key: String,
        id: String,
        status: StatusCode,
    },
    #[error(
        "opcua link: security.policy '{0}' is not an OPC UA security policy this client supports (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss)"
    )]
    Policy(String),
    #[error("opcua link: {0}")]
    Invalid(String),
    #[error("opcua link: the client: {0}")]
    Client(String),
}

/// How the messages between driftwatch and the server are protected.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SecurityMode {
    /// No signing, no encryption: a lab, or a machine network already closed.
    #[default]
    None,
    Sign,
    SignAndEncrypt,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SecurityConfig {
    #[serde(default)]
    pub mode: SecurityMode,
    /// The security policy for `sign` and `sign_and_encrypt` (ignored for `none`).
    #[serde(default = "default_policy")]
    pub policy: String,
    /// The client's application instance certificate (DER) and its private key (PEM). Without
    /// them a self-signed pair is made in `pki_dir` at the first start, for the server's
    /// administrator to trust.
    #[serde(default)]
    pub certificate: Option<PathBuf>,
    #[serde(default)]
    pub private_key: Option<PathBuf>,
    /// The client's certificate store (own, private, trusted and rejected server
    /// certificates); default `<data_dir>/opcua-pki/<machine id>`.
    #[serde(default)]
    pub pki_dir: Option<PathBuf>,
    /// Trust the server's certificate without it being in `pki_dir/trusted` (a lab; in a
    /// plant copy the server's certificate there instead).
    #[serde(default)]
    pub trust_server: bool,
}

fn default_policy() -> String {
    "Basic256Sha256".into()
}

impl Default for SecurityConfig {
    fn default() -> Self {
        SecurityConfig {
            mode: SecurityMode::None,
            policy: default_policy(),
            certificate: None,
            private_key: None,
            pki_dir: None,
            trust_server: false,
        }
    }
}

/// The node ids the link reads and writes. The defaults spell the companion specifications'
/// browse paths as string node ids in namespace 2 (OPC 40501 machine tools fixes browse names,
/// not node ids): on a real machine look each node up (e.g. in UaExpert) and configure it.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeMap {
    /// The spindle's actual speed, min^-1 (OPC 40502 CNC `CncSpindle/ActSpeed`; OPC 40501's
    /// `Monitoring/Spindle` has only `IsRotating` and `Override`).
    pub spindle_speed: String,
    /// The active program's state (OPC 40501 `Production/ActiveProgram/State/CurrentState`:
    /// Initializing, Running, Ended, Interrupted, Aborted).
    pub execution: String,
    /// Temperature sensors by the name they are recorded under, deg C.
    pub temperatures: BTreeMap<String, String>,
    /// driftwatch writes the order here (String).
    pub cycle_request: String,
    /// The NC's detections document (String).
    pub detections: String,
    /// Nodes the served set is written to: an NC offset name (`C_pivot_x_um`), an error name
    /// (`EX0B`) or `version`. Empty: nothing is written.
    pub compensation: BTreeMap<String, String>,
}

impl Default for NodeMap {
    fn default() -> Self {
        NodeMap {
            spindle_speed: "ns=2;s=CncInterface/CncSpindleList/Spindle/ActSpeed".into(),
            execution: "ns=2;s=Production/ActiveProgram/State/CurrentState".into(),
            temperatures: BTreeMap::new(),
            cycle_request: "ns=2;s=Driftwatch/CycleRequest".into(),
            detections: "ns=2;s=Driftwatch/Detections".into(),
            compensation: BTreeMap::new(),
        }
    }
}

/// OPC 40501's program states as NC states: a program running is cutting, one ended or
/// aborted leaves the machine idle, an interrupted one (feed hold) is still under way.
fn default_states() -> BTreeMap<String, MachineStateKind> {
    [
        ("Initializing", MachineStateKind::Idle),
        ("Running", MachineStateKind::Cutting),
        ("Ended", MachineStateKind::Idle),
        ("Interrupted", MachineStateKind::Cutting),
        ("Aborted", MachineStateKind::Idle),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpcuaConfig {
    /// `opc.tcp://host:port[/path]`.
    pub endpoint: String,
    #[serde(default)]
    pub security: SecurityConfig,
    #[serde(default)]
    pub nodes: NodeMap,
    /// The `execution` node's values (its text, or its number written out) as NC states.
    #[serde(default = "default_states")]
    pub states: BTreeMap<String, MachineStateKind>,
    /// The subscription's publishing interval, ms.
    #[serde(default = "default_publishing_ms")]
    pub publishing_ms: u64,
    /// The first wait before a reconnect, s; it doubles after each failure up to
    /// `reconnect_max_s` (with up to 20 % jitter), and starts again after a good session.
    #[serde(default = "default_reconnect_first_s")]
    pub reconnect_first_s: f64,
    #[serde(default = "default_reconnect_max_s")]
    pub reconnect_max_s: f64,
    /// As for `nc_push`: how far ahead of / behind the service clock a value may be stamped, s.
    #[serde(default = "crate::nc_push::default_max_ahead_s")]
    pub max_ahead_s: f64,
    #[serde(default = "crate::nc_push::default_max_behind_s")]
    pub max_behind_s: f64,
}

fn default_publishing_ms() -> u64 {
    250
}

fn default_reconnect_first_s() -> f64 {
    1.0
}

fn default_reconnect_max_s() -> f64 {
    30.0
}

fn node(key: &str, id: &str) -> Result<NodeId, OpcuaError> {
    NodeId::from_str(id).map_err(|status| OpcuaError::NodeId {
        key: key.to_string(),
        id: id.to_string(),
        status,
    })
}

/// The configuration with its node ids parsed.
#[derive(Debug, Clone)]
struct Prepared {
    cfg: OpcuaConfig,
    policy: SecurityPolicy,
    spindle: NodeId,
    execution: NodeId,
    temperatures: Vec<(String, NodeId)>,
    request: NodeId,
    detections: NodeId,
    compensation: Vec<(String, NodeId)>,
    pki_dir: PathBuf,
    app_name: String,
}

impl OpcuaConfig {
    /// Everything that can be checked without the server.
    pub fn check(&self) -> Result<(), OpcuaError> {
        self.prepare(Path::new("."), "check").map(|_| ())
    }

    fn prepare(&self, data_dir: &Path, machine: &str) -> Result<Prepared, OpcuaError> {
        if !self.endpoint.starts_with("opc.tcp://") {
            return Err(OpcuaError::Endpoint(self.endpoint.clone()));
        }
        let policy = match self.security.mode {
            SecurityMode::None => SecurityPolicy::None,
            _ => match SecurityPolicy::from_str(&self.security.policy) {
                Ok(p) if p.is_supported() && p != SecurityPolicy::None => p,
                _ => return Err(OpcuaError::Policy(self.security.policy.clone())),
            },
        };
        if self.security.certificate.is_some() != self.security.private_key.is_some() {
            return Err(OpcuaError::Invalid(
                "security.certificate and security.private_key go together".into(),
            ));
        }
        let first = self.reconnect_first_s;
        if !(first > 0.0 && first <= self.reconnect_max_s && self.reconnect_max_s <= 3600.0) {
            return Err(OpcuaError::Invalid(format!(
                "reconnect_first_s ({first}) must be > 0 and at most reconnect_max_s ({}), at most 3600",
                self.reconnect_max_s
            )));
        }
        if !(self.max_ahead_s > 0.0
            && self.max_ahead_s <= 86_400.0
            && self.max_behind_s > 0.0
            && self.max_behind_s <= 30.0 * 86_400.0)
        {
            return Err(OpcuaError::Invalid(format!(
                "max_ahead_s ({}) must be in (0, 86400] and max_behind_s ({}) in (0, 2592000]",
                self.max_ahead_s, self.max_behind_s
            )));
        }
        if !(10..=60_000).contains(&self.publishing_ms) {
            return Err(OpcuaError::Invalid(format!(
                "publishing_ms must be from 10 to 60000, not {}",
                self.publishing_ms
            )));
        }
        let n = &self.nodes;
        let map = |prefix: &str, m: &BTreeMap<String, String>| {
            m.iter()
                .map(|(k, v)| Ok((k.clone(), node(&format!("{prefix}.{k}"), v)?)))
                .collect::<Result<Vec<_>, OpcuaError>>()
        };
        Ok(Prepared {
            cfg: self.clone(),
            policy,
            spindle: node("spindle_speed", &n.spindle_speed)?,
            execution: node("execution", &n.execution)?,
            temperatures: map("temperatures", &n.temperatures)?,
            request: node("cycle_request", &n.cycle_request)?,
            detections: node("detections", &n.detections)?,
            compensation: map("compensation", &n.compensation)?,
            pki_dir: self
                .security
                .pki_dir
                .clone()
                .unwrap_or_else(|| data_dir.join("opcua-pki").join(machine)),
            app_name: format!("driftwatch {machine}"),
        })
    }

    /// The clock tolerance the link judges values by.
    pub fn clock_tolerance(&self) -> ClockTolerance {
        ClockTolerance {
            ahead_ns: (self.max_ahead_s * 1e9) as i64,
            behind_ns: (self.max_behind_s * 1e9) as i64,
        }
    }
}

/// What the service loop asks of the background task.
#[derive(Debug)]
enum Command {
    /// Write this order to the NC.
    Order(CycleOrder),
    /// The cycle closed or was aborted: no order any more.
    Clear(i64),
    /// The set now served.
    Serve(Box<CompensationSet>),
}

/// What the task says of the session.
#[derive(Debug, Default)]
struct Status {
    connected: AtomicBool,
    last_error: Mutex<String>,
}

/// The service side: a `MachineLink` whose I/O runs in a background task.
pub struct OpcuaLink {
    inner: NcPushLink,
    handle: NcPushHandle,
    commands: mpsc::UnboundedSender<Command>,
    status: Arc<Status>,
}

impl OpcuaLink {
    /// Start the link's task (on the current tokio runtime): it connects, and reconnects
    /// whenever the session is lost, until the link is dropped.
    pub fn start(
        cfg: &OpcuaConfig,
        plan: Plan,
        limits: Limits,
        data_dir: &Path,
        machine: &str,
    ) -> Result<OpcuaLink, OpcuaError> {
        let prepared = prepare_client(cfg.prepare(data_dir, machine)?)?;
        let (inner, handle) = nc_push(Arc::new(plan), limits, cfg.clock_tolerance());
        let (commands, rx) = mpsc::unbounded_channel();
        let status = Arc::new(Status::default());
        // Not aborted when the link is dropped: the closed command channel tells the task to
        // close its session politely (the server frees it at once) and end.
        tokio::spawn(run(prepared, handle.clone(), rx, status.clone()));
        Ok(OpcuaLink {
            inner,
            handle,
            commands,
            status,
        })
    }

    /// Whether a session with the server is up now.
    pub fn connected(&self) -> bool {
        self.status.connected.load(Ordering::Relaxed)
    }
}

impl MachineLink for OpcuaLink {
    fn poll(&mut self, now_ns: i64) -> Vec<LinkEvent> {
        let events = self.inner.poll(now_ns);
        for e in &events {
            if let LinkEvent::CycleDone { cycle, .. } = e {
                let _ = self.commands.send(Command::Clear(*cycle));
            }
        }
        events
    }

    fn request_cycle(&mut self, number: i64, now_ns: i64) -> Result<(), LinkError> {
        // An order the NC cannot be told of would only time out: say why now instead.
        if !self.connected() {
            let why = self
                .status
                .last_error
                .lock()
                .map(|e| e.clone())
                .unwrap_or_default();
            return Err(LinkError::Unavailable(format!(
                "no OPC UA session with the NC ({why})"
            )));
        }
        self.inner.request_cycle(number, now_ns)?;
        match self.handle.order() {
            Some(order) if order.cycle == number => {
                let _ = self.commands.send(Command::Order(order));
                Ok(())
            }
            _ => {
                self.inner.abort_cycle(number, now_ns);
                Err(LinkError::Unavailable(
                    "the order was not kept by the cycle bookkeeping".into(),
                ))
            }
        }
    }

    fn abort_cycle(&mut self, number: i64, now_ns: i64) {
        self.inner.abort_cycle(number, now_ns);
        let _ = self.commands.send(Command::Clear(number));
    }

    fn next_event_ns(&self) -> Option<i64> {
        None
    }

    fn waker(&self) -> Option<Arc<tokio::sync::Notify>> {
        self.inner.waker()
    }

    fn serve(&mut self, set: &CompensationSet) {
        let _ = self.commands.send(Command::Serve(Box::new(set.clone())));
    }

    fn set_clock(&mut self, clock: &crate::clock::ServiceClock) {
        self.inner.set_clock(clock);
    }
}

/// The configuration and the client built from it (once: it holds the certificate store).
struct Client {
    p: Prepared,
    client: opcua::client::Client,
}

fn prepare_client(p: Prepared) -> Result<Client, OpcuaError> {
    let sec = &p.cfg.security;
    let mut b = ClientBuilder::new()
        .application_name(p.app_name.clone())
        .application_uri(format!("urn:driftwatch:{}", p.app_name.replace(' ', ":")))
        .product_uri("urn:driftwatch")
        .pki_dir(p.pki_dir.clone())
        .trust_server_certs(sec.trust_server)
        // The link reconnects itself, with a fresh session and subscription: one place that
        // decides, and a server restart (its sessions gone) handled like any other loss.
        .session_retry_limit(0)
        .session_timeout(60_000)
        .keep_alive_interval(Duration::from_secs(2))
        .max_failed_keep_alive_count(3)
        .request_timeout(Duration::from_secs(10));
    b = match (&sec.certificate, &sec.private_key) {
        (Some(c), Some(k)) => b
            .certificate_path(c.clone())
            .private_key_path(k.clone())
            .create_sample_keypair(false),
        // Without a configured pair, one is made in the pki directory, as OPC UA clients do;
        // with security `none` it is never sent.
        _ => b.create_sample_keypair(true),
    };
    let client = b.client().map_err(|e| OpcuaError::Client(e.join("; ")))?;
    Ok(Client { p, client })
}

/// Reconnect waits: doubling from `first` to `max`, jittered up to 20 % so that the machines
/// of a plant do not all knock at once after a network outage.
#[derive(Debug, Clone)]
pub struct Backoff {
    first: Duration,
    max: Duration,
    next: Duration,
}

impl Backoff {
    pub fn new(first: Duration, max: Duration) -> Self {
        Backoff {
            first,
            max,
            next: first,
        }
    }

    /// The wait before the next attempt, given a jitter share in [0, 1).
    pub fn next_wait(&mut self, jitter: f64) -> Duration {
        let base = self.next;
        self.next = (self.next * 2).min(self.max);
        base.mul_f64(1.0 + 0.2 * jitter.clamp(0.0, 1.0))
    }

    pub fn reset(&mut self) {
        self.next = self.first;
    }
}

/// A jitter share from the wall clock's nanoseconds: no random generator is needed for it.
fn jitter() -> f64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    f64::from(nanos % 1000) / 1000.0
}

fn wall_ns() -> i64 {
    chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0)
}

/// Why a session ended.
enum Ended {
    /// The link was dropped: stop.
    Closed,
    /// Lost or never made: try again after a wait. `connected`: it had been up.
    Lost { reason: String, connected: bool },
}

/// The background task: sessions one after another, with waits between.
async fn run(
    mut client: Client,
    handle: NcPushHandle,
    mut commands: mpsc::UnboundedReceiver<Command>,
    status: Arc<Status>,
) {
    let mut flow = Flow::default();
    let mut backoff = Backoff::new(
        Duration::from_secs_f64(client.p.cfg.reconnect_first_s),
        Duration::from_secs_f64(client.p.cfg.reconnect_max_s),
    );
    loop {
        let ended = session(&mut client, &handle, &mut commands, &status, &mut flow).await;
        status.connected.store(false, Ordering::Relaxed);
        match ended {
            Ended::Closed => return,
            Ended::Lost { reason, connected } => {
                if connected {
                    backoff.reset();
                }
                let wait = backoff.next_wait(jitter());
                warn!(
                    endpoint = %client.p.cfg.endpoint,
                    "OPC UA session: {reason}; trying again in {:.1} s",
                    wait.as_secs_f64()
                );
                if let Ok(mut e) = status.last_error.lock() {
                    *e = reason;
                }
                // Orders cannot come while disconnected (the link refuses them), but a
                // cycle's end or a new served set can: keep them for the next session.
                let sleep = tokio::time::sleep(wait);
                tokio::pin!(sleep);
                loop {
                    tokio::select! {
                        _ = &mut sleep => break,
                        c = commands.recv() => match c {
                            None => return,
                            Some(c) => flow.remember(c),
                        },
                    }
                }
            }
        }
    }
}

/// What the task knows across sessions.
#[derive(Default)]
struct Flow {
    /// The order written to the NC and not yet closed.
    order: Option<CycleOrder>,
    /// The detections document's cycle and how many of its entries were taken.
    taken: Option<(i64, usize)>,
    /// The set to write to the compensation nodes, and whether it was written.
    served: Option<(Box<CompensationSet>, bool)>,
    /// The last spindle speed, posted again every minute while it holds (the contract's
    /// heartbeat: a subscription reports changes only).
    spindle: Option<f64>,
    /// The wall time this session came up: a value unchanged since before it is stamped with
    /// it (the value holds now; its own stamp may be days old, beyond the clock tolerance).
    session_ns: i64,
}

impl Flow {
    fn remember(&mut self, c: Command) {
        match c {
            Command::Order(o) => self.order = Some(o),
            Command::Clear(n) => {
                if self.order.as_ref().is_some_and(|o| o.cycle == n) {
                    self.order = None;
                }
            }
            Command::Serve(set) => self.served = Some((set, false)),
        }
    }
}

fn lost(reason: impl std::fmt::Display, connected: bool) -> Ended {
    Ended::Lost {
        reason: reason.to_string(),
        connected,
    }
}

/// One session: connect, subscribe, then follow the server and the service until either ends.
async fn session(
    client: &mut Client,
    handle: &NcPushHandle,
    commands: &mut mpsc::UnboundedReceiver<Command>,
    status: &Status,
    flow: &mut Flow,
) -> Ended {
    let p = client.p.clone();
    let mode = match p.cfg.security.mode {
        SecurityMode::None => MessageSecurityMode::None,
        SecurityMode::Sign => MessageSecurityMode::Sign,
        SecurityMode::SignAndEncrypt => MessageSecurityMode::SignAndEncrypt,
    };
    let endpoint = (
        p.cfg.endpoint.as_str(),
        p.policy.to_uri(),
        mode,
        UserTokenPolicy::anonymous(),
    );
    let connecting = client
        .client
        .connect_to_matching_endpoint(endpoint, IdentityToken::Anonymous);
    let (session, event_loop) =
        match tokio::time::timeout(Duration::from_secs(20), connecting).await {
            Ok(Ok(s)) => s,
            Ok(Err(e)) => return lost(format!("connecting: {e}"), false),
            Err(_) => return lost("connecting: no answer within 20 s", false),
        };
    let mut events = event_loop.spawn();
    let up = tokio::select! {
        up = session.wait_for_connection() => up,
        r = &mut events => return lost(format!("the session did not come up: {r:?}"), false),
        _ = tokio::time::sleep(Duration::from_secs(20)) => false,
    };
    if !up {
        events.abort();
        return lost("the session did not come up within 20 s", false);
    }
    let (tx, mut changes) = mpsc::unbounded_channel::<(NodeId, DataValue)>();
    if let Err(e) = subscribe(&session, &p, tx).await {
        events.abort();
        return lost(format!("subscribing: {e}"), false);
    }
    info!(endpoint = %p.cfg.endpoint, mode = ?p.cfg.security.mode, "OPC UA session up");
    status.connected.store(true, Ordering::Relaxed);
    flow.session_ns = wall_ns();
    // What the NC may have missed while the session was down, or forgotten in a restart: the
    // open order and the served set are written again.
    if let Some((_, written)) = &mut flow.served {
        *written = false;
    }
    if let Err(e) = catch_up(&session, &p, flow).await {
        events.abort();
        return lost(e, true);
    }
    let mut minute = tokio::time::interval(Duration::from_secs(60));
    minute.tick().await;
    loop {
        let step: Result<(), String> = tokio::select! {
            r = &mut events => return lost(format!("the session ended ({r:?})"), true),
            Some((id, dv)) = changes.recv() => on_change(&session, &p, handle, flow, &id, dv).await,
            c = commands.recv() => match c {
                None => {
                    let _ = tokio::time::timeout(CALL_TIMEOUT, session.disconnect()).await;
                    events.abort();
                    return Ended::Closed;
                }
                Some(c) => {
                    flow.remember(c);
                    catch_up(&session, &p, flow).await
                }
            },
            _ = minute.tick() => {
                if let Some(rpm) = flow.spindle {
                    post(handle, rec::TOPIC_SPINDLE, wall_ns(), serde_json::json!({"rpm": rpm}));
                }
                Ok(())
            }
        };
        if let Err(e) = step {
            let _ = tokio::time::timeout(CALL_TIMEOUT, session.disconnect()).await;
            events.abort();
            return lost(e, true);
        }
    }
}

/// How long one service call may take. A call on a session whose connection has just died
/// may never be answered, and while the task awaits it nothing else is looked at: the bound
/// turns it into a lost session.
const CALL_TIMEOUT: Duration = Duration::from_secs(5);

async fn within<T, E: std::fmt::Display>(
    what: &str,
    call: impl std::future::Future<Output = Result<T, E>>,
) -> Result<T, String> {
    match tokio::time::timeout(CALL_TIMEOUT, call).await {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(format!("{what}: {e}")),
        Err(_) => Err(format!(
            "{what}: no answer within {} s",
            CALL_TIMEOUT.as_secs()
        )),
    }
}

/// Subscribe to every node the NC reports through; each change goes to `tx`.
async fn subscribe(
    session: &Arc<Session>,
    p: &Prepared,
    tx: mpsc::UnboundedSender<(NodeId, DataValue)>,
) -> Result<(), String> {
    let interval = Duration::from_millis(p.cfg.publishing_ms);
    let sub = within(
        "creating the subscription",
        session.create_subscription(
            interval,
            // Lifetime and keep-alive counts: the server drops the subscription after 60
            // silent intervals, and says it is alive every 10.
            60,
            10,
            0,
            0,
            true,
            DataChangeCallback::new(move |dv: DataValue, item: &MonitoredItem| {
                let _ = tx.send((item.item_to_monitor().node_id.clone(), dv));
            }),
        ),
    )
    .await?;
    let mut ids = vec![
        ("spindle_speed".to_string(), p.spindle.clone()),
        ("execution".to_string(), p.execution.clone()),
        ("detections".to_string(), p.detections.clone()),
    ];
    ids.extend(
        p.temperatures
            .iter()
            .map(|(k, id)| (format!("temperatures.{k}"), id.clone())),
    );
    let items: Vec<MonitoredItemCreateRequest> = ids
        .iter()
        .map(|(_, id)| {
            let mut r: MonitoredItemCreateRequest = id.clone().into();
            r.requested_parameters.sampling_interval = interval.as_secs_f64() * 1e3;
            // A burst of changes (a state through Running and back) is queued, not coalesced.
            r.requested_parameters.queue_size = 32;
            r.requested_parameters.discard_oldest = true;
            r
        })
        .collect();
    let created = within(
        "creating the monitored items",
        session.create_monitored_items(sub, TimestampsToReturn::Both, items),
    )
    .await?;
    for ((key, id), c) in ids.iter().zip(created) {
        let s = c.result.status_code;
        if !s.is_good() {
            // A node that is not there is named; the others are followed all the same.
            warn!("OPC UA nodes.{key} = {id}: cannot be monitored ({s})");
        }
    }
    Ok(())
}

/// After a (re)connect or a command: write the open order (or its absence) and the served set
/// where it is not written yet. (What the NC wrote meanwhile comes as the subscription's first
/// values.)
async fn catch_up(session: &Session, p: &Prepared, flow: &mut Flow) -> Result<(), String> {
    let request = match &flow.order {
        // An order the NC has begun (a detection of it taken) is not written again: an NC that
        // still runs it goes on, and one that lost it in a restart reports its program ended,
        // which closes the cycle with what was read (nc_push's rule), missing measurements
        // named. Writing it again would have a restarted NC run a cycle already closing.
        Some(o) if flow.taken.is_some_and(|(c, n)| c == o.cycle && n > 0) => None,
        Some(o) => Some(serde_json::to_string(o).map_err(|e| e.to_string())?),
        None => Some(String::new()),
    };
    if let Some(request) = request {
        write(
            session,
            &[(p.request.clone(), Variant::String(UAString::from(request)))],
        )
        .await?;
    }
    if let Some((set, written @ false)) = &mut flow.served {
        let values = compensation_values(set, &p.compensation);
        if !values.is_empty() {
            write(session, &values).await?;
        }
        *written = true;
    }
    Ok(())
}

/// The served set's values for the configured nodes, the version last.
fn compensation_values(
    set: &CompensationSet,
    nodes: &[(String, NodeId)],
) -> Vec<(NodeId, Variant)> {
    let mut out = Vec::new();
    let mut version = None;
    for (name, id) in nodes {
        if name == "version" {
            version = Some((id.clone(), Variant::Int64(set.version as i64)));
            continue;
        }
        let v = set.offsets.get(name).or_else(|| {
            set.errors
                .iter()
                .find(|(e, _)| e.to_string() == *name)
                .map(|(_, v)| v)
        });
        match v {
            Some(v) => out.push((id.clone(), Variant::Double(*v))),
            None => warn!("OPC UA nodes.compensation.{name}: the served set has no such value"),
        }
    }
    out.extend(version);
    out
}

async fn write(session: &Session, values: &[(NodeId, Variant)]) -> Result<(), String> {
    let nodes: Vec<WriteValue> = values
        .iter()
        .map(|(id, v)| WriteValue {
            node_id: id.clone(),
            attribute_id: AttributeId::Value as u32,
            index_range: NumericRange::None,
            // The value alone: many servers refuse a client's timestamps.
            value: DataValue::value_only(v.clone()),
        })
        .collect();
    let results = within("writing", session.write(&nodes)).await?;
    for ((id, _), s) in values.iter().zip(results) {
        if !s.is_good() {
            return Err(format!("writing {id}: {s}"));
        }
    }
    Ok(())
}

/// A value's time: its source stamp (the NC's), else the server's, else now; never before the
/// session came up (a value unchanged for days holds now, not then).
fn stamp(dv: &DataValue, session_ns: i64) -> i64 {
    let ns = |t: &Option<opcua::types::DateTime>| {
        t.as_ref()
            .and_then(|t| t.as_chrono().timestamp_nanos_opt())
            .filter(|n| *n > 0)
    };
    ns(&dv.source_timestamp)
        .or_else(|| ns(&dv.server_timestamp))
        .unwrap_or_else(wall_ns)
        .max(session_ns)
}

/// A number from any numeric variant.
pub fn number(v: &Variant) -> Option<f64> {
    Some(match v {
        Variant::Double(x) => *x,
        Variant::Float(x) => f64::from(*x),
        Variant::SByte(x) => f64::from(*x),
        Variant::Byte(x) => f64::from(*x),
        Variant::Int16(x) => f64::from(*x),
        Variant::UInt16(x) => f64::from(*x),
        Variant::Int32(x) => f64::from(*x),
        Variant::UInt32(x) => f64::from(*x),
        Variant::Int64(x) => *x as f64,
        Variant::UInt64(x) => *x as f64,
        _ => return None,
    })
}

/// A state value as the text the `states` map is keyed by.
pub fn state_text(v: &Variant) -> Option<String> {
    match v {
        Variant::String(s) => s.value().clone(),
        Variant::LocalizedText(t) => t.text.value().clone(),
        Variant::Boolean(b) => Some(b.to_string()),
        other => number(other).map(|x| x.to_string()),
    }
}

/// The NC state for a state text (exact, else ignoring case).
pub fn map_state(
    states: &BTreeMap<String, MachineStateKind>,
    text: &str,
) -> Option<MachineStateKind> {
    states.get(text).copied().or_else(|| {
        states
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(text))
            .map(|(_, v)| *v)
    })
}

/// The NC's detections document.
#[derive(Debug, Deserialize)]
pub struct DetectionsDoc {
    pub cycle: i64,
    #[serde(default)]
    pub detections: Vec<DocEntry>,
}

#[derive(Debug, Deserialize)]
pub struct DocEntry {
    pub t_ns: i64,
    pub msg: Value,
}

/// The entries of `doc` not taken yet, given what was taken (document cycle, count); and
/// what is taken after them.
pub fn new_entries(
    doc: DetectionsDoc,
    taken: Option<(i64, usize)>,
) -> (Vec<DocEntry>, (i64, usize)) {
    // A document of the same cycle shorter than what was taken is a new one (an NC that lost
    // its memory in a restart ran the order again): taken from its start.
    let already = match taken {
        Some((c, n)) if c == doc.cycle && n <= doc.detections.len() => n,
        _ => 0,
    };
    let total = doc.detections.len();
    let fresh = doc.detections.into_iter().skip(already).collect();
    (fresh, (doc.cycle, total))
}

fn post(handle: &NcPushHandle, topic: &str, t_ns: i64, msg: Value) {
    let batch = EventBatch {
        events: vec![PostedEvent {
            topic: topic.to_string(),
            t_ns,
            msg,
        }],
    };
    if let Err(e) = handle.post(&batch) {
        // Refused as nc_push refuses it (a limit, the clock, the order): named in the log.
        warn!("OPC UA value refused: {e}");
    }
}

/// Take the detections document's new entries into the loop's queue.
fn take_detections(handle: &NcPushHandle, flow: &mut Flow, v: Option<&Variant>) {
    let text = match v {
        Some(Variant::String(s)) => s.value().clone().unwrap_or_default(),
        _ => String::new(),
    };
    if text.trim().is_empty() {
        return;
    }
    let doc: DetectionsDoc = match serde_json::from_str(&text) {
        Ok(d) => d,
        Err(e) => {
            warn!("OPC UA detections document is not {{\"cycle\", \"detections\"}} JSON: {e}");
            return;
        }
    };
    let (fresh, taken) = new_entries(doc, flow.taken);
    flow.taken = Some(taken);
    for e in fresh {
        post(handle, rec::TOPIC_DETECTION, e.t_ns, e.msg);
    }
}

async fn on_change(
    session: &Session,
    p: &Prepared,
    handle: &NcPushHandle,
    flow: &mut Flow,
    id: &NodeId,
    dv: DataValue,
) -> Result<(), String> {
    let t_ns = stamp(&dv, flow.session_ns);
    let value = dv.value.as_ref();
    if *id == p.detections {
        take_detections(handle, flow, value);
    }
    if *id == p.spindle {
        match value.and_then(number) {
            Some(rpm) => {
                flow.spindle = Some(rpm);
                post(
                    handle,
                    rec::TOPIC_SPINDLE,
                    t_ns,
                    serde_json::json!({"rpm": rpm}),
                );
            }
            None => warn!("OPC UA spindle_speed {id}: {value:?} is not a number"),
        }
    }
    if *id == p.execution {
        let Some(text) = value.and_then(state_text) else {
            warn!("OPC UA execution {id}: {value:?} is no state");
            return Ok(());
        };
        let Some(mut state) = map_state(&p.cfg.states, &text) else {
            warn!("OPC UA execution '{text}' is not in the link's states map: not reported");
            return Ok(());
        };
        if flow.order.is_some() {
            if state == MachineStateKind::Cutting {
                state = MachineStateKind::Measuring;
            } else {
                // The program ends: take every detection it wrote before saying so, since the
                // state ends the cycle and its notification may come before the document's.
                let read = ReadValueId {
                    node_id: p.detections.clone(),
                    attribute_id: AttributeId::Value as u32,
                    ..Default::default()
                };
                let got = within(
                    "reading the detections",
                    session.read(&[read], TimestampsToReturn::Both, 0.0),
                )
                .await?;
                if let Some(d) = got.first() {
                    take_detections(handle, flow, d.value.as_ref());
                }
            }
        }
        post(
            handle,
            rec::TOPIC_STATE,
            t_ns,
            serde_json::json!({"state": state, "program": Value::Null}),
        );
    }
    for (name, tid) in &p.temperatures {
        if tid == id {
            match value.and_then(number) {
                Some(c) => post(
                    handle,
                    rec::TOPIC_TEMPERATURE,
                    t_ns,
                    serde_json::json!({"sensor": name, "celsius": c}),
                ),
                None => warn!("OPC UA temperatures.{name} {id}: {value:?} is not a number"),
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opcua::types::LocalizedText;

    fn cfg(text: &str) -> OpcuaConfig {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn the_defaults_parse_and_bad_settings_are_named() {
        let c = cfg(r#"endpoint = "opc.tcp://127.0.0.1:4840""#);
        c.check().unwrap();
        assert_eq!(c.security.mode, SecurityMode::None);
        assert_eq!(
            map_state(&c.states, "Running"),
            Some(MachineStateKind::Cutting)
        );
        assert_eq!(map_state(&c.states, "ended"), Some(MachineStateKind::Idle));
        assert_eq!(map_state(&c.states, "Dancing"), None);

        let e = cfg(r#"endpoint = "http://x""#).check().unwrap_err();
        assert!(e.to_string().contains("not an opc.tcp"), "{e}");
        let e = cfg("endpoint = \"opc.tcp://x:4840\"\nnodes = { spindle_speed = \"spindle\" }")
            .check()
            .unwrap_err();
        assert!(
            e.to_string().contains("nodes.spindle_speed = 'spindle'"),
            "{e}"
        );
        let e = cfg(
            "endpoint = \"opc.tcp://x:4840\"\nsecurity = { mode = \"sign\", policy = \"Rot13\" }",
        )
        .check()
        .unwrap_err();
        assert!(e.to_string().contains("'Rot13'"), "{e}");
        let e = cfg(
            "endpoint = \"opc.tcp://x:4840\"\nsecurity = { mode = \"sign_and_encrypt\", certificate = \"c.der\" }",
        )
        .check()
        .unwrap_err();
        assert!(e.to_string().contains("go together"), "{e}");
        assert!(
            toml::from_str::<OpcuaConfig>(
                "endpoint = \"opc.tcp://x\"\nnodes = { spindle = \"ns=2;s=a\" }"
            )
            .is_err(),
            "an unknown node key is refused"
        );
    }

    /// The shipped default documents every key: its commented OPC UA block parses, as the
    /// link of a machine, to the defaults (bar the endpoint and the examples' maps).
    #[test]
    fn the_default_configs_documented_block_parses() {
        let doc = crate::config::DEFAULT_CONFIG;
        let (a, b) = (
            doc.find("# opcua-begin").unwrap(),
            doc.find("# opcua-end").unwrap(),
        );
        let mut text = String::new();
        for line in doc[a..b].lines().skip(1) {
            let line = line.strip_prefix("# ").unwrap_or("");
            // Commented-out keys (a second '#') stay out; so do continuation comments.
            if !line.starts_with('#') && !line.trim_start().starts_with('#') {
                text.push_str(line);
                text.push('\n');
            }
        }
        let parsed: toml::Value = toml::from_str(&text).unwrap();
        let link = parsed["machines"]["link"].clone();
        let c: crate::config::LinkConfig = link.try_into().unwrap();
        let crate::config::LinkConfig::Opcua(c) = c else {
            panic!("not an opcua link")
        };
        c.check().unwrap();
        let d = cfg(r#"endpoint = "opc.tcp://x:4840""#);
        assert_eq!(c.states, d.states);
        assert_eq!(c.nodes.spindle_speed, d.nodes.spindle_speed);
        assert_eq!(c.nodes.execution, d.nodes.execution);
        assert_eq!(c.nodes.cycle_request, d.nodes.cycle_request);
        assert_eq!(c.nodes.detections, d.nodes.detections);
        assert_eq!(
            (c.publishing_ms, c.reconnect_first_s, c.reconnect_max_s),
            (d.publishing_ms, d.reconnect_first_s, d.reconnect_max_s)
        );
        assert_eq!(
            (c.max_ahead_s, c.max_behind_s),
            (d.max_ahead_s, d.max_behind_s)
        );
        assert_eq!(c.security.mode, d.security.mode);
        assert_eq!(c.security.policy, d.security.policy);
        assert_eq!(c.security.trust_server, d.security.trust_server);
    }

    #[test]
    fn the_backoff_doubles_to_its_cap_jitters_and_starts_again() {
        let mut b = Backoff::new(Duration::from_secs(1), Duration::from_secs(5));
        let waits: Vec<f64> = (0..5).map(|_| b.next_wait(0.0).as_secs_f64()).collect();
        assert_eq!(waits, [1.0, 2.0, 4.0, 5.0, 5.0]);
        assert!((b.next_wait(0.999).as_secs_f64() - 5.0 * 1.1998).abs() < 1e-3);
        b.reset();
        assert_eq!(b.next_wait(0.0), Duration::from_secs(1));
    }

    #[test]
    fn values_of_any_numeric_or_text_type_are_read() {
        assert_eq!(number(&Variant::Float(1.5)), Some(1.5));
        assert_eq!(number(&Variant::UInt32(20000)), Some(20000.0));
        assert_eq!(number(&Variant::String(UAString::from("1"))), None);
        let lt = Variant::LocalizedText(Box::new(LocalizedText::new("en", "Running")));
        assert_eq!(state_text(&lt).as_deref(), Some("Running"));
        assert_eq!(state_text(&Variant::Int32(2)).as_deref(), Some("2"));
    }

    #[test]
    fn detections_are_taken_once_each_by_position_per_cycle() {
        let doc = |cycle: i64, n: usize| DetectionsDoc {
            cycle,
            detections: (0..n)
                .map(|i| DocEntry {
                    t_ns: i as i64,
                    msg: Value::Null,
                })
                .collect(),
        };
        let (fresh, taken) = new_entries(doc(3, 2), None);
        assert_eq!((fresh.len(), taken), (2, (3, 2)));
        // The same document again (a reconnect, a coalesced change): nothing new.
        let (fresh, taken) = new_entries(doc(3, 2), Some(taken));
        assert_eq!((fresh.len(), taken), (0, (3, 2)));
        let (fresh, taken) = new_entries(doc(3, 5), Some(taken));
        assert_eq!(fresh.iter().map(|e| e.t_ns).collect::<Vec<_>>(), [2, 3, 4]);
        // The same cycle's document begun again: taken from its start.
        let (fresh, _) = new_entries(doc(3, 1), Some(taken));
        assert_eq!(fresh.len(), 1);
        // A new cycle's document starts again.
        let (fresh, taken) = new_entries(doc(4, 1), Some(taken));
        assert_eq!((fresh.len(), taken), (1, (4, 1)));
    }
}
