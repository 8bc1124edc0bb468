//! `driftwatch serve`: wire the configured machines, the store, the recorder and the HTTP API,
//! and run the machine loops on the service clock until stopped.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::{MachineInfo, MachineStateKind};
use driftwatch_service::api::{ApiState, Auth, MachineHandle, router};
use driftwatch_service::config::{LinkConfig, ServiceConfig};
use driftwatch_service::daemon::{MachineRuntime, Settings};
use driftwatch_service::link::{MachineLink, Simulated};
use driftwatch_service::nc_push::nc_push;
use driftwatch_service::recorder::Recorder;
use driftwatch_service::store::Store;
use driftwatch_service::webhook::Notifier;
use driftwatch_sim::scenario::Scenario;

pub struct Options {
    pub config: Option<PathBuf>,
    pub time_scale: Option<f64>,
    pub until: Option<f64>,
    pub listen: Option<std::net::SocketAddr>,
    pub data_dir: Option<PathBuf>,
}

/// The service clock: machine time advancing `scale` times faster than the wall clock.
struct Clock {
    t0_ns: i64,
    wall0: Instant,
    scale: f64,
}

impl Clock {
    fn now_ns(&self) -> i64 {
        self.t0_ns + (self.wall0.elapsed().as_secs_f64() * self.scale * 1e9) as i64
    }
    fn wall_until(&self, t_ns: i64) -> Duration {
        let dt = (t_ns - self.now_ns()) as f64 / 1e9 / self.scale;
        Duration::from_secs_f64(dt.clamp(0.0, 3600.0))
    }
}

pub async fn run(o: Options) -> Result<ExitCode> {
    let mut cfg = ServiceConfig::load(o.config.as_deref())?;
    if let Some(s) = o.time_scale {
        anyhow::ensure!(s.is_finite() && s > 0.0, "--time-scale must be > 0");
        cfg.time_scale = s;
    }
    if let Some(l) = o.listen {
        cfg.http.listen = l;
    }
    if let Some(d) = o.data_dir {
        cfg.data_dir = d;
    }
    cfg.validate("the configuration with the command line's options")?;
    std::fs::create_dir_all(&cfg.data_dir)
        .with_context(|| format!("creating data directory {}", cfg.data_dir.display()))?;
    let store = Store::open(&cfg.data_dir.join("driftwatch.db")).await?;
    let settings = Settings::from_config(&cfg);
    // Simulated machines start just before their first power-on, so that a newcomer sees the
    // morning's warm-up at once. With a real NC the clock is the wall clock and simulated
    // machines beside it are moved to start now.
    let real = cfg
        .machines
        .iter()
        .any(|m| matches!(m.link, LinkConfig::NcPush { .. }));
    let wall_now = chrono::Utc::now().timestamp_nanos_opt().unwrap_or(0);
    type Machine = (String, Kinematics, Plan, Box<dyn MachineLink>, Settings);
    let mut machines: Vec<Machine> = Vec::new();
    let mut nc_handles = BTreeMap::new();
    let mut t0 = i64::MAX;
    for m in &cfg.machines {
        let k = Kinematics::load(&m.machine).with_context(|| format!("machine '{}'", m.id))?;
        let plan = Plan::build(&k, &PlanConfig::load(&m.plan)?)
            .with_context(|| format!("machine '{}'", m.id))?;
        let mut settings = settings.clone();
        if let Some(path) = &m.thermal_model {
            let model = initial_model(path, &k)
                .with_context(|| format!("machine '{}': thermal_model {}", m.id, path.display()))?;
            settings.initial_model = Some(std::sync::Arc::new(model));
        }
        match &m.link {
            LinkConfig::Simulated { scenario } => {
                let mut scn =
                    Scenario::load(scenario).with_context(|| format!("machine '{}'", m.id))?;
                scn.machine_id = m.id.clone();
                let lead_ns = ((scn
                    .spindle
                    .iter()
                    .find(|s| s.state != MachineStateKind::Off)
                    .map(|s| s.at_min)
                    .unwrap_or(0.0)
                    - 5.0)
                    .max(0.0)
                    * 60e9) as i64;
                if real {
                    scn.start_utc =
                        chrono::DateTime::from_timestamp_nanos(wall_now - lead_ns).to_rfc3339();
                }
                let link = Simulated::new(k.clone(), plan.clone(), scn)?;
                t0 = t0.min(link.start_ns() + lead_ns);
                machines.push((m.id.clone(), k, plan, Box::new(link), settings));
            }
            LinkConfig::NcPush { .. } => {
                let tolerance = m.link.clock_tolerance().unwrap_or_default();
                let (link, handle) = nc_push(plan.clone(), k.config.limits, tolerance);
                nc_handles.insert(m.id.clone(), handle);
                t0 = t0.min(wall_now);
                machines.push((m.id.clone(), k, plan, Box::new(link), settings));
            }
        }
    }
    let mut runtimes = Vec::new();
    for (id, k, plan, link, settings) in machines {
        let info = MachineInfo {
            machine_id: id.clone(),
            kinematics: k.name.clone(),
            software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        };
        let recorder = Recorder::new(&cfg.data_dir.join("mcap"), info, cfg.max_file_mib << 20)?;
        let rt =
            MachineRuntime::new(&id, k, plan, link, &settings, store.clone(), recorder, t0).await?;
        runtimes.push(rt);
    }
    let (tokens, disabled) = cfg.resolved_tokens();
    for d in &disabled {
        tracing::warn!("{d}");
    }
    let (hooks, missing) = cfg.resolved_webhooks();
    for m in &missing {
        tracing::warn!("{m}");
    }
    let (notifier, deliveries) = Notifier::start(hooks).map_err(anyhow::Error::msg)?;
    for rt in &mut runtimes {
        rt.set_notifier(notifier.clone());
    }
    let handles: BTreeMap<String, MachineHandle> = runtimes
        .iter()
        .map(|rt| {
            (
                rt.id.clone(),
                MachineHandle {
                    view: rt.view.clone(),
                    inbox: rt.inbox.clone(),
                    nc: nc_handles.get(&rt.id).cloned(),
                    kinematics: Some(Arc::new(rt.kinematics().clone())),
                },
            )
        })
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
    drop(notifier);
    let state = Arc::new(state);
    let listener = tokio::net::TcpListener::bind(cfg.http.listen)
        .await
        .with_context(|| format!("listening on {}", cfg.http.listen))?;
    let addr = listener.local_addr()?;
    let (stop_tx, mut stop_rx) = tokio::sync::watch::channel(false);
    let mut server_stop = stop_rx.clone();
    let server = tokio::spawn(async move {
        axum::serve(listener, router(state))
            .with_graceful_shutdown(async move {
                let _ = server_stop.wait_for(|s| *s).await;
            })
            .await
    });
    tokio::spawn(async move {
        shutdown_signal().await;
        let _ = stop_tx.send(true);
    });
    let first = cfg
        .machines
        .first()
        .map(|m| m.id.clone())
        .unwrap_or_default();
    println!(
        "driftwatch serving {} machine(s) on http://{addr} ({}x machine time, data in {})",
        runtimes.len(),
        cfg.time_scale,
        cfg.data_dir.display()
    );
    println!("  compensation: curl http://{addr}/api/v1/machines/{first}/compensation");
    println!("  machines:     curl http://{addr}/api/v1/machines");
    let clock = Clock {
        t0_ns: t0,
        wall0: Instant::now(),
        scale: cfg.time_scale,
    };
    let end = o.until.map(|m| t0 + (m * 60e9) as i64);
    loop {
        let now = clock.now_ns();
        let now = end.map_or(now, |e| now.min(e));
        let mut wake = i64::MAX;
        for rt in &mut runtimes {
            wake = wake.min(rt.step(now).await?);
        }
        if end.is_some_and(|e| now >= e) || *stop_rx.borrow() {
            break;
        }
        // Look again at least every 200 ms of wall time, for operator requests.
        let nap = clock.wall_until(wake).min(Duration::from_millis(200));
        tokio::select! {
            _ = tokio::time::sleep(nap) => {}
            _ = stop_rx.changed() => {}
        }
    }
    let now = clock.now_ns();
    for rt in &mut runtimes {
        rt.shutdown(end.map_or(now, |e| now.min(e))).await?;
    }
    store.close().await;
    server.abort();
    // Alert events still queued get a short grace to reach their webhooks.
    drop(runtimes);
    let grace = tokio::time::sleep(Duration::from_secs(10));
    tokio::pin!(grace);
    for d in deliveries {
        tokio::select! {
            _ = d => {}
            _ = &mut grace => {
                tracing::warn!("webhook deliveries still pending at shutdown were given up (the events are stored)");
                break;
            }
        }
    }
    println!("driftwatch stopped; data in {}", cfg.data_dir.display());
    Ok(ExitCode::SUCCESS)
}

/// `driftwatch healthcheck`: one GET of a running service's health endpoint.
pub async fn healthcheck(url: &str, timeout_s: f64) -> Result<ExitCode> {
    anyhow::ensure!(
        timeout_s.is_finite() && timeout_s > 0.0,
        "--timeout-s must be > 0"
    );
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs_f64(timeout_s))
        .build()
        .context("building the HTTP client")?;
    match client.get(url).send().await {
        Ok(r) if r.status().is_success() => {
            println!("{url}: {}", r.status());
            Ok(ExitCode::SUCCESS)
        }
        Ok(r) => {
            eprintln!("{url}: {}", r.status());
            Ok(ExitCode::FAILURE)
        }
        Err(e) => {
            eprintln!("{url}: {e}");
            Ok(ExitCode::FAILURE)
        }
    }
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(s) => s,
                Err(_) => {
                    let _ = tokio::signal::ctrl_c().await;
                    return;
                }
            };
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// A model file to start a machine's predictions from: readable, and only of errors the
/// machine has.
fn initial_model(
    path: &std::path::Path,
    k: &Kinematics,
) -> Result<driftwatch_core::thermal_model::ThermalModel> {
    let text = std::fs::read_to_string(path).context("reading the file")?;
    let model = driftwatch_core::thermal_model::ThermalModel::from_json(&text)?;
    let names = k.identify_names();
    let foreign: Vec<&str> = model
        .channels
        .iter()
        .map(|c| c.name.as_str())
        .filter(|n| !names.iter().any(|m| m == n))
        .collect();
    anyhow::ensure!(
        foreign.is_empty(),
        "the model has channels this machine ({}) does not: {}",
        k.name,
        foreign.join(", ")
    );
    Ok(model)
}
