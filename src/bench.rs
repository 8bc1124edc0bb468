//! `driftwatch bench year`: one simulated year of one machine through the service pipeline
//! (machine link, phase, scheduler, solve, validation, SQLite, MCAP), as fast as it runs.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};

use driftwatch::config::ServiceConfig;
use driftwatch::daemon::{MachineRuntime, Settings};
use driftwatch::kinematics::Kinematics;
use driftwatch::link::Simulated;
use driftwatch::plan::{Plan, PlanConfig};
use driftwatch::recorder::Recorder;
use driftwatch::recording::MachineInfo;
use driftwatch::scenario::Scenario;
use driftwatch::store::Store;

fn size_of(p: &Path) -> u64 {
    match std::fs::metadata(p) {
        Ok(m) if m.is_file() => m.len(),
        Ok(m) if m.is_dir() => std::fs::read_dir(p)
            .map(|d| d.filter_map(|e| e.ok()).map(|e| size_of(&e.path())).sum())
            .unwrap_or(0),
        _ => 0,
    }
}

pub async fn year(days: f64, dir: PathBuf) -> Result<ExitCode> {
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let cfg = ServiceConfig::load(None)?;
    let scn = Scenario::load("two_shift")?;
    let k = Kinematics::load(&scn.machine)?;
    let plan = Plan::build(&k, &PlanConfig::load(&scn.plan)?)?;
    let link = Simulated::new(k.clone(), plan.clone(), scn)?;
    let t0 = link.start_ns();
    let store = Store::open(&dir.join("driftwatch.db")).await?;
    let info = MachineInfo {
        machine_id: "sim-1".into(),
        kinematics: k.name.clone(),
        software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
    };
    let recorder = Recorder::new(&dir.join("mcap"), info, cfg.max_file_mib << 20)?;
    let settings = Settings::from_config(&cfg);
    let mut rt = MachineRuntime::new(
        "sim-1",
        k,
        plan,
        Box::new(link),
        &settings,
        store.clone(),
        recorder,
        t0,
    )
    .await?;
    let end = t0 + (days * 86_400e9) as i64;
    let wall = Instant::now();
    let mut now = t0;
    let mut steps = 0u64;
    while now < end {
        now = rt.step(now).await?.min(end).max(now + 1);
        steps += 1;
    }
    rt.shutdown(end).await?;
    let secs = wall.elapsed().as_secs_f64();
    let cycles = store.cycles("sim-1", i64::MAX).await?;
    store.close().await;
    let ok = cycles.iter().filter(|c| c.status == "ok").count();
    let db = size_of(&dir.join("driftwatch.db")) + size_of(&dir.join("driftwatch.db-wal"));
    let mcap = size_of(&dir.join("mcap"));
    println!(
        "{days} simulated days of one machine: {secs:.1} s wall, {steps} loop steps, {} cycles ({ok} ok), database {:.1} MB, MCAP {:.1} MB",
        cycles.len(),
        db as f64 / 1e6,
        mcap as f64 / 1e6
    );
    Ok(ExitCode::SUCCESS)
}
