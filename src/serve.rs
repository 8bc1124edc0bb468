//! `driftwatch serve`: the configuration with the command line's options, the listener and the
//! signals, around the service crate's `launch`; and `driftwatch healthcheck`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use tokio_util::sync::CancellationToken;

use driftwatch_service::config::ServiceConfig;
use driftwatch_service::launch::{LaunchOptions, launch_with};

pub struct Options {
    pub config: Option<PathBuf>,
    pub time_scale: Option<f64>,
    pub until: Option<f64>,
    pub listen: Option<std::net::SocketAddr>,
    pub data_dir: Option<PathBuf>,
    pub new_database: bool,
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
    let listener = tokio::net::TcpListener::bind(cfg.http.listen)
        .await
        .with_context(|| format!("listening on {}", cfg.http.listen))?;
    let shutdown = CancellationToken::new();
    tokio::spawn({
        let shutdown = shutdown.clone();
        async move {
            shutdown_signal().await;
            shutdown.cancel();
        }
    });
    let (machines, first, scale, data_dir) = (
        cfg.machines.len(),
        cfg.machines
            .first()
            .map(|m| m.id.clone())
            .unwrap_or_default(),
        cfg.time_scale,
        cfg.data_dir.clone(),
    );
    let opts = LaunchOptions {
        until_min: o.until,
        new_database: o.new_database,
        ..Default::default()
    };
    let service = launch_with(cfg, listener, shutdown, opts).await?;
    let addr = service.addr;
    println!(
        "driftwatch serving {machines} machine(s) on http://{addr} ({scale}x machine time, data in {})",
        data_dir.display()
    );
    println!("  compensation: curl http://{addr}/api/v1/machines/{first}/compensation");
    println!("  machines:     curl http://{addr}/api/v1/machines");
    service.wait().await;
    println!("driftwatch stopped; data in {}", data_dir.display());
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

/// `fleet-audit`: each machine's lease terms and the breaches its stored data shows.
pub async fn fleet_audit(
    config: Option<&std::path::Path>,
    database_url: Option<String>,
) -> Result<ExitCode> {
    use driftwatch_service::store::Store;
    let cfg = ServiceConfig::load(config)?;
    let store = match database_url.or(cfg.database_url.clone()) {
        Some(url) => Store::connect(&url).await?,
        None => Store::open(&cfg.data_dir.join("driftwatch.db")).await?,
    };
    let mut problems = 0;
    for m in &cfg.machines {
        let audit = store.lease_audit(&m.id).await?;
        println!(
            "{}: {} cycles, {} compensation sets, {} lease terms",
            m.id,
            audit.cycles.len(),
            audit.sets.len(),
            audit.terms.len()
        );
        for t in &audit.terms {
            let cycles = audit.cycles.iter().filter(|c| c.3 == Some(t.term)).count();
            let sets = audit.sets.iter().filter(|s| s.2 == Some(t.term)).count();
            println!(
                "  term {} '{}': {} .. {} ({}), wrote {cycles} cycles and {sets} sets",
                t.term,
                t.holder,
                ms_utc(t.acquired_ms),
                ms_utc(t.released_ms.unwrap_or(t.expires_ms)),
                if t.released_ms.is_some() {
                    "released"
                } else {
                    "expired or held"
                }
            );
        }
        for p in audit.problems() {
            println!("  PROBLEM {p}");
            problems += 1;
        }
    }
    store.close().await;
    println!("{problems} problems");
    Ok(if problems == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn ms_utc(ms: i64) -> String {
    chrono::DateTime::from_timestamp_millis(ms).map_or_else(
        || ms.to_string(),
        |t| t.format("%Y-%m-%d %H:%M:%S%.3f").to_string(),
    )
}
