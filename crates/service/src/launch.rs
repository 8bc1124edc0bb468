//! The one seam that starts the service: `launch(config, listener, shutdown)` wires the
//! configured machines, the store, the recorders, the webhooks and the HTTP API, runs each
//! machine's loop in its own task on the service clock, and returns a handle to wait on.
//! `driftwatch serve` and the integration tests start the service through it, so that a test
//! runs what a user runs (on a listener bound to port 0 that it keeps: no port race).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::MachineInfo;
use driftwatch_core::units::{NS_PER_MIN, NS_PER_S, min_to_ns};
use driftwatch_thermal::model::ThermalModel;

use crate::api::{ApiState, Auth, router};
use crate::clock::{ManualClock, ServiceClock};
use crate::config::{LinkConfig, MachineConfigEntry, ServiceConfig};
use crate::daemon::{
    DaemonError, MachineHandle, MachineRuntime, MachineView, Settings, run_machine,
};
use crate::link::MachineLink;
use crate::mtconnect_link::{MtconnectLink, MtconnectSettings};
use crate::nc_push::nc_push;
use crate::recorder::Recorder;
use crate::store::Store;
use crate::webhook::Notifier;

#[derive(Debug, Error)]
pub enum LaunchError {
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    #[error("machine '{machine}': {message}")]
    Machine { machine: String, message: String },
    #[error("creating the data directory {path}: {source}")]
    DataDir {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    #[error(transparent)]
    Daemon(#[from] DaemonError),
    #[error("webhooks: {0}")]
    Webhooks(String),
    #[error("the listener: {0}")]
    Listener(std::io::Error),
    #[error(transparent)]
    Lock(#[from] crate::dir_lock::LockError),
    #[error(
        "the database holds no machine, but {files} recording(s) under {mcap} hold this data \
         directory's history: the database was emptied or replaced, and starting on it would \
         begin the versions again at 1. Restore the database from a backup, or start with \
         --new-database to begin a new store (its sets get new ETags; the old history stays in \
         the recordings)"
    )]
    HistoryWithoutDatabase { mcap: PathBuf, files: usize },
    #[error(transparent)]
    Http(#[from] crate::http_server::ServerError),
    #[error("starting the API's runtime: {0}")]
    ApiRuntime(std::io::Error),
}

/// Which clock the machines run on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClockKind {
    /// The wall clock sped up by the configuration's `time_scale`.
    Configured,
    /// A clock that moves only when the [`ManualClock`] in [`Service::manual_clock`] moves it.
    Manual,
}

/// How to launch, beyond the configuration.
#[derive(Debug, Clone)]
pub struct LaunchOptions {
    pub clock: ClockKind,
    /// Stop by itself after this much machine time, min.
    pub until_min: Option<f64>,
    /// Start the clock here instead (a test that plays a real NC from a simulated start).
    pub start_ns: Option<i64>,
    /// Start on an empty database even though recordings of an earlier history lie in the
    /// data directory (refused otherwise: an emptied database would begin versions again).
    pub new_database: bool,
}

impl Default for LaunchOptions {
    fn default() -> Self {
        LaunchOptions {
            clock: ClockKind::Configured,
            until_min: None,
            start_ns: None,
            new_database: false,
        }
    }
}

/// The running service.
pub struct Service {
    /// Where the API listens.
    pub addr: std::net::SocketAddr,
    /// Machine time the clock started at.
    pub t0_ns: i64,
    pub clock: ServiceClock,
    /// Set for [`ClockKind::Manual`].
    pub manual_clock: Option<ManualClock>,
    /// Each machine's view (what the API shows of it).
    pub views: BTreeMap<String, Arc<std::sync::Mutex<MachineView>>>,
    /// What the API serves from (its diagnosis slots, its webhooks' counters).
    pub api: Arc<ApiState>,
    shutdown: CancellationToken,
    server: crate::http_server::ApartServer,
    machines: Vec<JoinHandle<()>>,
    deliveries: Vec<JoinHandle<()>>,
    store: Store,
    /// One process per data directory: held until the service is dropped.
    _lock: crate::dir_lock::DirLock,
    /// Outside a fleet on PostgreSQL: this process's machines, held until it is dropped.
    _hold: Option<crate::store::MachineHold>,
}

/// Launch the service with its configured clock, until `shutdown` is cancelled.
pub async fn launch(
    cfg: ServiceConfig,
    listener: TcpListener,
    shutdown: CancellationToken,
) -> Result<Service, LaunchError> {
    launch_with(cfg, listener, shutdown, LaunchOptions::default()).await
}

/// A machine ready to run: its loop and what the API holds of it.
struct Wired {
    runtime: MachineRuntime,
    handle: MachineHandle,
}

/// Launch the service: open the store, build every machine's loop, serve the API on
/// `listener`, and run the loops until `shutdown` is cancelled (or `until_min` has passed).
pub async fn launch_with(
    cfg: ServiceConfig,
    listener: TcpListener,
    shutdown: CancellationToken,
    opts: LaunchOptions,
) -> Result<Service, LaunchError> {
    cfg.validate("the configuration")?;
    cfg.check_environment("(its tokens from the environment)")?;
    // What this start makes, so that a start that fails leaves nothing behind.
    let made_dir = !cfg.data_dir.exists();
    let db_file = cfg
        .database_url
        .is_none()
        .then(|| cfg.data_dir.join("driftwatch.db"));
    let made_db = db_file.as_ref().is_some_and(|f| !f.exists());
    std::fs::create_dir_all(&cfg.data_dir).map_err(|source| LaunchError::DataDir {
        path: cfg.data_dir.clone(),
        source,
    })?;
    let who = format!(
        "pid {} on {}, API on {}, since {}",
        std::process::id(),
        hostname(),
        listener
            .local_addr()
            .map_or_else(|e| e.to_string(), |a| a.to_string()),
        chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true)
    );
    let lock = match crate::dir_lock::lock(&cfg.data_dir, &who) {
        Ok(l) => l,
        Err(e) => {
            if made_dir {
                let _ = std::fs::remove_dir_all(&cfg.data_dir);
            }
            return Err(e.into());
        }
    };
    let data_dir = cfg.data_dir.clone();
    match start(cfg, listener, shutdown, opts, lock, &who).await {
        Ok(service) => Ok(service),
        Err(e) => {
            // Nothing of a failed start stays: the directory or the database it made.
            if made_dir {
                let _ = std::fs::remove_dir_all(&data_dir);
            } else if made_db && let Some(f) = db_file {
                for suffix in ["", "-wal", "-shm"] {
                    let mut p = f.clone().into_os_string();
                    p.push(suffix);
                    let _ = std::fs::remove_file(PathBuf::from(p));
                }
            }
            Err(e)
        }
    }
}

/// This host's name, for the lock's note (empty where the system does not say).
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_default()
}

/// Recordings under `mcap` (one directory per machine): the history a database beside them
/// should hold.
fn recordings_in(mcap: &Path) -> usize {
    let Ok(machines) = std::fs::read_dir(mcap) else {
        return 0;
    };
    machines
        .flatten()
        .filter_map(|m| std::fs::read_dir(m.path()).ok())
        .flat_map(|files| files.flatten())
        .filter(|f| {
            let name = f.file_name();
            let name = name.to_string_lossy();
            name.ends_with(".mcap") || name.ends_with(".mcap.partial")
        })
        .count()
}

/// The store, refused when it is empty beside the recordings of an earlier history (unless
/// `new_database`), and outside a fleet on PostgreSQL this process's hold on its machines.
async fn open_store(
    cfg: &ServiceConfig,
    new_database: bool,
    who: &str,
) -> Result<(Store, Option<crate::store::MachineHold>), LaunchError> {
    let store = match &cfg.database_url {
        Some(url) => Store::connect(url).await?,
        None => Store::open(&cfg.data_dir.join("driftwatch.db")).await?,
    };
    let mcap = cfg.data_dir.join("mcap");
    let files = recordings_in(&mcap);
    if files > 0 && !new_database && store.is_empty().await? {
        store.close().await;
        return Err(LaunchError::HistoryWithoutDatabase { mcap, files });
    }
    // Outside a fleet, one process per machine on a shared PostgreSQL database too.
    let hold = match (&cfg.database_url, &cfg.fleet) {
        (Some(url), None) => {
            let ids: Vec<String> = cfg.machines.iter().map(|m| m.id.clone()).collect();
            store.hold_machines(url, &ids, who).await?
        }
        _ => None,
    };
    Ok((store, hold))
}

/// The start proper, in a data directory this process holds.
async fn start(
    cfg: ServiceConfig,
    listener: TcpListener,
    shutdown: CancellationToken,
    opts: LaunchOptions,
    lock: crate::dir_lock::DirLock,
    who: &str,
) -> Result<Service, LaunchError> {
    let (store, hold) = open_store(&cfg, opts.new_database, who).await?;
    let (links, t0) = links(&cfg, &store).await?;
    let mut t0 = opts.start_ns.unwrap_or(t0);
    // The processes of a simulated fleet share one machine time: the first sets it.
    if cfg.fleet.is_some() && matches!(opts.clock, ClockKind::Configured) {
        t0 = store.fleet_clock_now(t0, cfg.time_scale).await?;
    }
    let (clock, manual_clock) = match opts.clock {
        ClockKind::Configured => (ServiceClock::scaled(t0, cfg.time_scale), None),
        ClockKind::Manual => {
            let (c, m) = ServiceClock::manual(t0);
            (c, Some(m))
        }
    };
    let (hooks, missing) = cfg.resolved_webhooks();
    for m in &missing {
        warn!("{m}");
    }
    let (notifier, deliveries) = Notifier::start(hooks).map_err(LaunchError::Webhooks)?;
    let mut wired = Vec::new();
    let mut slots = Vec::new();
    for (id, k, plan, mut link, settings, nc) in links {
        link.set_clock(&clock);
        if cfg.fleet.is_some() {
            // Run only once its lease is taken (the fleet's supervisor).
            slots.push(crate::fleet::Slot::new(id, k, plan, settings, link, nc));
        } else {
            let mut runtime =
                start_machine(&cfg, &store, t0, id, k, &plan, link, &settings).await?;
            runtime.set_notifier(notifier.clone());
            let handle = MachineHandle {
                view: runtime.view.clone(),
                inbox: runtime.inbox.clone(),
                nc,
                kinematics: Some(Arc::new(runtime.kinematics().clone())),
            };
            wired.push(Wired { runtime, handle });
        }
    }
    let (tokens, disabled) = cfg.resolved_tokens();
    for d in &disabled {
        warn!("{d}");
    }
    let handles: BTreeMap<String, MachineHandle> = wired
        .iter()
        .map(|w| (w.runtime.id.clone(), w.handle.clone()))
        .chain(slots.iter().map(|s| (s.id.clone(), s.handle.clone())))
        .collect();
    let views = handles
        .iter()
        .map(|(id, h)| (id.clone(), h.view.clone()))
        .collect();
    let mut state = ApiState::new(
        handles,
        store.clone(),
        Auth {
            tokens,
            anonymous_read: cfg.http.anonymous_read,
        },
    );
    state.webhooks = notifier.stats.clone();
    state.diagnoses_kept = cfg.http.diagnoses_kept;
    state.request_timeout = std::time::Duration::from_secs_f64(cfg.http.request_timeout_s);
    state.validation = cfg.validation.clone();
    state.verification = cfg.verification.clone();
    state.clock = Some(clock.clone());
    state.simulated = cfg
        .machines
        .iter()
        .filter(|m| matches!(m.link, LinkConfig::Simulated { .. }))
        .map(|m| m.id.clone())
        .collect();
    let fleet = cfg.fleet.as_ref().map(|f| crate::fleet::Fleet {
        process: f.process_name(),
        url: f.advertise_url.clone(),
        ttl: Duration::from_secs_f64(f.lease_s),
        max_machines: f.max_machines.unwrap_or(usize::MAX),
        store: store.clone(),
        clock: clock.clone(),
        mcap_dir: cfg.data_dir.join("mcap"),
        max_file_bytes: cfg.max_file_mib << 20,
        notifier: notifier.clone(),
        slots,
    });
    state.fleet_process = fleet.as_ref().map(|f| f.process.clone());
    // The loops hold the only senders from here: the deliveries end when the loops do.
    drop(notifier);
    let addr = listener.local_addr().map_err(LaunchError::Listener)?;
    let api = Arc::new(state);
    let server = {
        // Timeouts and a cap on connections (crate::http_server), checked against the file limit.
        let limits = crate::http_server::ConnLimits::from_config(&cfg.http);
        let socket_links = cfg
            .machines
            .iter()
            .filter(|m| matches!(m.link, LinkConfig::Opcua(_) | LinkConfig::Mtconnect { .. }))
            .count();
        crate::http_server::prepare(&limits, cfg.machines.len(), socket_links)?;
        let app = router(api.clone());
        crate::http_server::serve_apart(listener, app, limits, shutdown.clone())
            .map_err(LaunchError::ApiRuntime)?
    };
    let end = opts.until_min.map(|m| t0.saturating_add(min_to_ns(m)));
    write_apart_where_worth(&mut wired);
    // Not `wired.into_iter().map(..).collect()`: that collects in place, and the handles
    // would keep the runtimes' buffer (some 5 KB a machine) for the life of the service.
    let mut machines: Vec<JoinHandle<()>> = Vec::with_capacity(wired.len() + 1);
    for w in wired {
        machines.push(tokio::spawn(run_machine(
            Box::new(w.runtime),
            clock.clone(),
            t0,
            end,
            shutdown.clone(),
        )));
    }
    if let Some(fleet) = fleet {
        machines.push(tokio::spawn(fleet.run(shutdown.clone())));
    }
    Ok(Service {
        addr,
        t0_ns: t0,
        clock,
        manual_clock,
        views,
        api,
        shutdown,
        server,
        machines,
        deliveries,
        store,
        _lock: lock,
        _hold: hold,
    })
}

/// A machine or two on a computer with cores to spare: each loop's writes on a thread of their
/// own (`daemon::writes_apart`), so that a loop decides while its last steps' rows are written.
fn write_apart_where_worth(wired: &mut [Wired]) {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if !crate::daemon::writes_apart(wired.len(), cores) {
        return;
    }
    for w in wired {
        if let Err(e) = w.runtime.write_apart() {
            warn!(machine = %w.runtime.id, error = %e, "the machine's writes stay on its loop's thread");
        }
    }
}

/// A machine's loop, started from what the store holds.
#[allow(clippy::too_many_arguments)]
async fn start_machine(
    cfg: &ServiceConfig,
    store: &Store,
    t0: i64,
    id: String,
    k: Kinematics,
    plan: &Plan,
    link: Box<dyn MachineLink>,
    settings: &Settings,
) -> Result<MachineRuntime, LaunchError> {
    let info = MachineInfo {
        machine_id: id.clone(),
        kinematics: k.name.clone(),
        software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
    };
    let recorder = Recorder::new(&cfg.data_dir.join("mcap"), info, cfg.max_file_mib << 20)
        .map_err(|e| LaunchError::Machine {
            machine: id.clone(),
            message: e.to_string(),
        })?;
    Ok(MachineRuntime::new(&id, k, plan, link, settings, store.clone(), recorder, t0).await?)
}

type Linked = (
    String,
    Kinematics,
    Arc<Plan>,
    Box<dyn MachineLink>,
    Settings,
    Option<crate::nc_push::NcPushHandle>,
);

/// A machine's link before the clock's start is known.
enum Pending {
    Simulated(Box<dyn MachineLink>),
    Nc(Box<dyn MachineLink>, crate::nc_push::NcPushHandle),
    /// A real machine's link the API has no door for (MTConnect observes; OPC UA: the service
    /// is the client).
    Real(Box<dyn MachineLink>),
}

/// Every error an alert rule watches is one the machine identifies: a rule on another
/// family's error would never fire, and silence is not a verdict.
fn alerts_fit(
    rules: &[driftwatch_machine::alerts::Rule],
    k: &Kinematics,
    own: bool,
) -> Result<(), String> {
    use driftwatch_machine::alerts::Rule;
    let names = k.identify_names();
    for r in rules {
        let (Rule::Threshold { error, .. } | Rule::Rate { error, .. }) = r else {
            continue;
        };
        if !names.contains(error) {
            return Err(format!(
                "the alert rule on {error} watches an error machine '{}' does not identify ({}); {}",
                k.name,
                names.join(", "),
                if own {
                    "correct its alerts"
                } else {
                    "give this machine its own alerts = [...] in its [[machines]] entry"
                }
            ));
        }
    }
    Ok(())
}

/// Every configured machine's link, and the machine time the clock starts at.
///
/// Simulated machines start just before their first power-on, so that a newcomer sees the
/// morning's warm-up at once; with a store that already holds a later time (a restart), the
/// clock resumes there and the simulated machines are brought to it without events, so that
/// a restart does not replay a day the store has seen. With a real NC the clock is the wall
/// clock and simulated machines beside it are moved to start now.
async fn links(cfg: &ServiceConfig, store: &Store) -> Result<(Vec<Linked>, i64), LaunchError> {
    let settings = crate::daemon::settings_from_config(cfg);
    let real = cfg.machines.iter().any(|m| m.link.is_real());
    let wall_now = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    let mut pending = Vec::new();
    let mut plans = std::collections::HashMap::new();
    let mut t0 = i64::MAX;
    let mut resume = i64::MIN;
    for m in &cfg.machines {
        let fail = |message: String| LaunchError::Machine {
            machine: m.id.clone(),
            message,
        };
        let k = Kinematics::load(&m.machine).map_err(|e| fail(e.to_string()))?;
        let plan_name = m.plan.as_deref().unwrap_or(&k.config.plan);
        let plan_cfg = PlanConfig::load(plan_name).map_err(|e| fail(e.to_string()))?;
        // One plan for every machine of the same kinematics file and plan: the NC doors
        // keep theirs for as long as the service runs (some 17 KB each).
        let plan = match plans.get(&(m.machine.clone(), plan_name.to_string())) {
            Some(plan) => Arc::clone(plan),
            None => {
                let plan = Arc::new(Plan::build(&k, &plan_cfg).map_err(|e| fail(e.to_string()))?);
                plans.insert(
                    (m.machine.clone(), plan_name.to_string()),
                    Arc::clone(&plan),
                );
                plan
            }
        };
        let mut settings = settings.clone();
        settings.alert_rules = m.alert_rules(&cfg.alerts).to_vec();
        alerts_fit(&settings.alert_rules, &k, m.alerts.is_some()).map_err(fail)?;
        if let Some(path) = &m.thermal_model {
            let model = initial_model(path, &k)
                .map_err(|e| fail(format!("thermal_model {}: {e}", path.display())))?;
            settings.initial_model = Some(Arc::new(model));
        }
        let link = match &m.link {
            LinkConfig::Simulated { scenario, seed } => {
                let (link, start_ns) =
                    simulated_link(m, scenario, *seed, (&k, &*plan), real, wall_now)
                        .map_err(fail)?;
                t0 = t0.min(start_ns);
                if let Some(t) = store.latest_time(&m.id).await? {
                    resume = resume.max(t);
                }
                Pending::Simulated(link)
            }
            LinkConfig::NcPush { .. } => {
                let tolerance = m.link.clock_tolerance().unwrap_or_default();
                let (link, handle) = nc_push(Arc::clone(&plan), k.config.limits, tolerance);
                t0 = t0.min(wall_now);
                Pending::Nc(Box::new(link), handle)
            }
            LinkConfig::Mtconnect {
                agent,
                device,
                items,
                poll_ms,
                count,
                ..
            } => {
                let settings = MtconnectSettings {
                    agent: agent.clone(),
                    device: device.clone(),
                    items: items.clone(),
                    poll: Duration::from_millis(*poll_ms),
                    count: *count,
                    tolerance: m.link.clock_tolerance().unwrap_or_default(),
                };
                let link = MtconnectLink::start(&m.id, settings, k.config.limits)
                    .map_err(|e| fail(e.to_string()))?;
                t0 = t0.min(wall_now);
                Pending::Real(Box::new(link))
            }
            LinkConfig::Opcua(c) => {
                let link = crate::opcua::OpcuaLink::start(
                    c,
                    (*plan).clone(),
                    k.config.limits,
                    &cfg.data_dir,
                    &m.id,
                )
                .map_err(|e| fail(e.to_string()))?;
                t0 = t0.min(wall_now);
                Pending::Real(Box::new(link))
            }
        };
        pending.push((m.id.clone(), k, plan, settings, link));
    }
    if t0 == i64::MAX {
        t0 = wall_now;
    }
    if !real && resume >= t0 {
        // A whole second past the last stored time, so that nothing lands on it twice.
        let at = (resume / NS_PER_S + 1) * NS_PER_S;
        info!(
            "the store's latest time lies {:.1} min after the simulated start: resuming there",
            (at - t0) as f64 / NS_PER_MIN as f64
        );
        t0 = at;
    }
    let linked = pending
        .into_iter()
        .map(|(id, k, plan, settings, link)| match link {
            Pending::Simulated(mut sim) => {
                sim.resume_at(t0);
                (id, k, plan, sim, settings, None)
            }
            Pending::Nc(link, handle) => (id, k, plan, link, settings, Some(handle)),
            Pending::Real(link) => (id, k, plan, link, settings, None),
        })
        .collect();
    Ok((linked, t0))
}

/// A simulated machine's link (the configured machine, whatever the scenario names) and the
/// machine time its clock would start at: five minutes before its first power-on.
#[cfg(feature = "simulated")]
fn simulated_link(
    m: &MachineConfigEntry,
    scenario: &str,
    seed: Option<u64>,
    (k, plan): (&Kinematics, &Plan),
    real: bool,
    wall_now: i64,
) -> Result<(Box<dyn MachineLink>, i64), String> {
    use driftwatch_core::recording::MachineStateKind;
    let mut scn = driftwatch_sim::scenario::Scenario::load(scenario).map_err(|e| e.to_string())?;
    scn.machine_id = m.id.clone();
    scn.machine = m.machine.clone();
    if let Some(seed) = seed {
        scn.seed = seed;
    }
    let first_on_min = scn
        .spindle
        .iter()
        .find(|s| s.state != MachineStateKind::Off)
        .map_or(0.0, |s| s.at_min);
    let lead_ns = min_to_ns((first_on_min - 5.0).max(0.0));
    if real {
        scn.start_utc = chrono::DateTime::from_timestamp_nanos(wall_now - lead_ns).to_rfc3339();
    }
    let link =
        crate::link::Simulated::new(k.clone(), plan.clone(), scn).map_err(|e| e.to_string())?;
    let start_ns = link.start_ns() + lead_ns;
    Ok((Box::new(link), start_ns))
}

/// Without the `simulated` feature the service has no truth simulator: a simulated machine in
/// the configuration is refused at start, with the reason.
#[cfg(not(feature = "simulated"))]
fn simulated_link(
    _m: &MachineConfigEntry,
    scenario: &str,
    _seed: Option<u64>,
    _machine: (&Kinematics, &Plan),
    _real: bool,
    _wall_now: i64,
) -> Result<(Box<dyn MachineLink>, i64), String> {
    Err(format!(
        "link kind \"simulated\" (scenario {scenario}) needs the simulated machine, which this build leaves out (built without the service's `simulated` feature): give the machine a real link, or use a build with the feature"
    ))
}

impl Service {
    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Stop everything: the API, then the loops.
    pub fn stop(&self) {
        self.shutdown.cancel();
    }

    /// Wait for the loops to end (on shutdown, or at `until_min`), then for the API to close
    /// its connections, the store to close, and queued webhook deliveries (up to a grace).
    pub async fn wait(self) {
        for m in self.machines {
            if let Err(e) = m.await {
                error!(error = %e, "a machine loop panicked");
            }
        }
        // With `until_min`, the loops end by themselves: the API goes with them.
        self.shutdown.cancel();
        let mut server = self.server;
        match server.ended().await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => error!(error = %e, "the HTTP server failed"),
            Err(e) => error!("{e}"),
        }
        if let Some(hold) = self._hold {
            hold.release().await;
        }
        self.store.close().await;
        server.release();
        let grace = tokio::time::sleep(Duration::from_secs(10));
        tokio::pin!(grace);
        for d in self.deliveries {
            tokio::select! {
                _ = d => {}
                _ = &mut grace => {
                    warn!("webhook deliveries still pending at shutdown were given up (the events are stored)");
                    break;
                }
            }
        }
    }
}

/// A model file to start a machine's predictions from: readable, and only of errors the
/// machine has.
fn initial_model(path: &Path, k: &Kinematics) -> Result<ThermalModel, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("reading the file: {e}"))?;
    let model = ThermalModel::from_json(&text).map_err(|e| e.to_string())?;
    let names = k.identify_names();
    let foreign: Vec<&str> = model
        .channels
        .iter()
        .map(|c| c.name.as_str())
        .filter(|n| !names.iter().any(|m| m == n))
        .collect();
    if foreign.is_empty() {
        Ok(model)
    } else {
        Err(format!(
            "the model has channels this machine ({}) does not: {}",
            k.name,
            foreign.join(", ")
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Machines of one kinematics file and plan share one plan (their NC doors keep it all
    /// day); another plan is built on its own.
    #[tokio::test]
    async fn machines_of_one_kinematics_and_plan_share_one_plan() {
        let (_tmp, dir) = crate::scratch_dir("plans");
        let store = Store::open(&dir.join("driftwatch.db")).await.unwrap();
        let mut cfg = ServiceConfig::load(None).unwrap();
        let nc = crate::config::LinkConfig::NcPush {
            max_ahead_s: crate::nc_push::default_max_ahead_s(),
            max_behind_s: crate::nc_push::default_max_behind_s(),
        };
        let base = cfg.machines[0].clone();
        cfg.machines = [("a", "patent"), ("b", "patent"), ("c", "patent_sequential")]
            .into_iter()
            .map(|(id, plan)| {
                let mut m = base.clone();
                m.id = id.into();
                m.machine = "table_bc".into();
                m.plan = Some(plan.into());
                m.link = nc.clone();
                m
            })
            .collect();
        let (linked, _) = links(&cfg, &store).await.unwrap();
        let plans: Vec<&Arc<Plan>> = linked.iter().map(|l| &l.2).collect();
        assert!(Arc::ptr_eq(plans[0], plans[1]));
        assert!(!Arc::ptr_eq(plans[0], plans[2]));
        assert_eq!(plans[2].config.name, "patent_sequential");
        store.close().await;
    }
}
