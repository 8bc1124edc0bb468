//! Service benchmarks (run and reported, never timed tests):
//! - `bench year`: one simulated year of one machine through the service pipeline (machine
//!   link, phase, scheduler, solve, validation, SQLite, MCAP), as fast as it runs;
//! - `bench http`: the NC's compensation endpoint under load on loopback, next to a trivial
//!   endpoint served by the same server in the same run, while the machine loop keeps
//!   solving and writing;
//! - `bench fleet` ([`fleet`]): N simulated machines through a simulated day in one process
//!   (the launched service, SQLite or PostgreSQL), as fast as the loops keep up, while a
//!   client polls the compensation endpoint: wall time, CPU per machine-day, database growth
//!   per machine-year, the endpoint's latency.

use driftwatch_core::units;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::MachineInfo;
use driftwatch_service::config::ServiceConfig;
use driftwatch_service::daemon::MachineRuntime;
use driftwatch_service::link::Simulated;
use driftwatch_service::recorder::Recorder;
use driftwatch_service::store::{CycleStatus, Store};
use driftwatch_sim::scenario::Scenario;

mod cpu_time;
mod fleet;
pub mod located;
mod nc_traffic;
pub mod served;
pub mod thermal;
pub mod unexplained;

/// `f` over `jobs` on every core (each job single-threaded and independent), the results in
/// job order whatever order they finish in.
pub fn par_map<J: Sync, R: Send>(jobs: &[J], f: impl Fn(&J) -> R + Sync) -> Vec<R> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let next = AtomicUsize::new(0);
    let done: Mutex<Vec<Option<R>>> = Mutex::new((0..jobs.len()).map(|_| None).collect());
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(jobs.len().max(1));
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    let Some(job) = jobs.get(k) else { break };
                    let r = f(job);
                    if let Ok(mut d) = done.lock() {
                        d[k] = Some(r);
                    }
                }
            });
        }
    });
    done.into_inner()
        .unwrap_or_default()
        .into_iter()
        .flatten()
        .collect()
}
pub use fleet::{FleetBackend, FleetLink, FleetOptions, fleet};

fn size_of(p: &Path) -> u64 {
    match std::fs::metadata(p) {
        Ok(m) if m.is_file() => m.len(),
        Ok(m) if m.is_dir() => std::fs::read_dir(p)
            .map(|d| d.filter_map(|e| e.ok()).map(|e| size_of(&e.path())).sum())
            .unwrap_or(0),
        _ => 0,
    }
}

/// One simulated machine of the shipped default (two-shift day) on a fresh store in `dir`.
async fn pipeline(dir: &Path, prediction: bool) -> Result<(MachineRuntime, Store, i64)> {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
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
    let mut settings = driftwatch_service::daemon::settings_from_config(&cfg);
    settings.prediction.enabled = prediction;
    let mut rt = MachineRuntime::new(
        "sim-1",
        k,
        &plan,
        Box::new(link),
        &settings,
        store.clone(),
        recorder,
        t0,
    )
    .await?;
    // As the service runs one machine: its writes on a thread of their own where the cores
    // allow it.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if driftwatch_service::daemon::writes_apart(1, cores) {
        rt.write_apart()?;
    }
    Ok((rt, store, t0))
}

pub async fn year(days: f64, dir: PathBuf, prediction: bool) -> Result<ExitCode> {
    let (mut rt, store, t0) = pipeline(&dir, prediction).await?;
    let end = t0 + units::h_to_ns(days * 24.0);
    let wall = Instant::now();
    let mut now = t0;
    let mut steps = 0u64;
    while now < end {
        now = rt.step(now).await?.min(end).max(now + 1);
        steps += 1;
    }
    rt.shutdown(end).await?;
    let secs = wall.elapsed().as_secs_f64();
    let cycles = store.cycles("sim-1", i64::MAX, None).await?;
    let sets = store.compensation_versions("sim-1").await?.len();
    store.close().await;
    let ok = cycles
        .iter()
        .filter(|c| c.status == CycleStatus::Ok)
        .count();
    let db = size_of(&dir.join("driftwatch.db")) + size_of(&dir.join("driftwatch.db-wal"));
    let mcap = size_of(&dir.join("mcap"));
    println!(
        "{days} simulated days of one machine{}: {secs:.1} s wall, {steps} loop steps, {} cycles ({ok} ok), {} compensation sets, database {:.1} MB, MCAP {:.1} MB",
        if prediction {
            ""
        } else {
            " (no predicted sets)"
        },
        cycles.len(),
        sets,
        db as f64 / 1e6,
        mcap as f64 / 1e6
    );
    Ok(ExitCode::SUCCESS)
}

/// The `q` quantile of sorted values (the nearest rank); NaN when there are none.
fn quantile(sorted: &[u64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 - 1.0) * q).round() as usize] as f64
}

/// Latencies of one endpoint, µs, and the time they were collected over.
struct Load {
    latencies_us: Vec<u64>,
    errors: u64,
    seconds: f64,
}

impl Load {
    fn quantile(&self, q: f64) -> f64 {
        let mut v = self.latencies_us.clone();
        v.sort_unstable();
        quantile(&v, q)
    }
    fn rate(&self) -> f64 {
        self.latencies_us.len() as f64 / self.seconds
    }
}

/// `connections` clients, each on its own keep-alive connection, GET `url` back to back for
/// `seconds`.
async fn load(url: &str, connections: usize, seconds: f64) -> Result<Load> {
    let until = Instant::now() + std::time::Duration::from_secs_f64(seconds);
    let mut tasks = Vec::new();
    for _ in 0..connections {
        let client = reqwest::Client::builder()
            .pool_max_idle_per_host(1)
            .build()?;
        let url = url.to_string();
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            let mut errors = 0u64;
            while Instant::now() < until {
                let t = Instant::now();
                match client.get(&url).send().await {
                    Ok(r) if r.status().is_success() => match r.bytes().await {
                        Ok(_) => lat.push(t.elapsed().as_micros() as u64),
                        Err(_) => errors += 1,
                    },
                    _ => errors += 1,
                }
            }
            (lat, errors)
        }));
    }
    let t0 = Instant::now();
    let mut out = Load {
        latencies_us: Vec::new(),
        errors: 0,
        seconds: 0.0,
    };
    for t in tasks {
        let (lat, errors) = t.await?;
        out.latencies_us.extend(lat);
        out.errors += errors;
    }
    out.seconds = t0.elapsed().as_secs_f64();
    Ok(out)
}

pub async fn http(connections: usize, seconds: f64, dir: PathBuf) -> Result<ExitCode> {
    use driftwatch_service::api::{ApiState, Auth, MachineHandle, router};
    anyhow::ensure!(connections > 0, "--connections must be at least 1");
    anyhow::ensure!(seconds > 0.0, "--seconds must be > 0");
    let (mut rt, store, t0) = pipeline(&dir, true).await?;
    // Run the morning until the first validated set exists.
    let mut now = t0;
    while rt.served().is_none() {
        anyhow::ensure!(now < t0 + 12 * units::NS_PER_H, "no validated set by noon");
        now = rt.step(now).await?.max(now + 1);
    }
    let version0 = rt.served().map_or(0, |c| c.version);
    let mut machines = std::collections::BTreeMap::new();
    machines.insert(
        rt.id.clone(),
        MachineHandle {
            view: rt.view.clone(),
            inbox: rt.inbox.clone(),
            nc: None,
            kinematics: None,
        },
    );
    let state = std::sync::Arc::new(ApiState::new(
        machines,
        store.clone(),
        Auth {
            tokens: Vec::new(),
            anonymous_read: true,
        },
    ));
    // The reference is the API's own cheapest read, `GET /api/v1/service` (the clock and the
    // simulated machines), through the same layers as the compensation: the token guard,
    // the metrics, the timeout, the error and trace layers. What the ratio then measures is
    // the compensation handler itself.
    let app = router(state);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    let server = tokio::spawn(async move { axum::serve(listener, app).await });
    let trivial = format!("http://{addr}/api/v1/service");
    let comp = format!("http://{addr}/api/v1/machines/sim-1/compensation");

    // The machine loop keeps running (600x: a cycle about every 3 s of wall time) so that the
    // endpoint is measured while solves and writes happen. Each endpoint is loaded twice,
    // alternating, so that drift in the machine's state affects both alike.
    let half = seconds / 2.0;
    let (tx, mut rx) = tokio::sync::oneshot::channel();
    let conns = connections;
    let (t_url, c_url) = (trivial.clone(), comp.clone());
    tokio::spawn(async move {
        let run = async {
            load(&t_url, conns, 0.5).await?; // warm-up, discarded
            let mut t = load(&t_url, conns, half).await?;
            let mut c = load(&c_url, conns, half).await?;
            let t2 = load(&t_url, conns, half).await?;
            let c2 = load(&c_url, conns, half).await?;
            for (a, b) in [(&mut t, t2), (&mut c, c2)] {
                a.latencies_us.extend(b.latencies_us);
                a.errors += b.errors;
                a.seconds += b.seconds;
            }
            anyhow::Ok((t, c))
        };
        let _ = tx.send(run.await);
    });
    let wall = Instant::now();
    let sim0 = now;
    let result = loop {
        if let Ok(r) = rx.try_recv() {
            break r?;
        }
        let target = sim0 + (wall.elapsed().as_secs_f64() * 600.0 * 1e9) as i64;
        while now < target {
            now = rt.step(now).await?.min(target).max(now + 1);
        }
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    };
    let (t, c) = result;
    rt.shutdown(now).await?;
    server.abort();
    let cycles = rt.served().map_or(0, |s| s.version) - version0;
    store.close().await;
    for (name, l) in [("GET /service", &t), ("GET /compensation", &c)] {
        println!(
            "{name:>18}: {:>9.0} req/s  p50 {:>6.0} us  p99 {:>6.0} us  p99.9 {:>6.0} us  ({} requests, {} errors)",
            l.rate(),
            l.quantile(0.5),
            l.quantile(0.99),
            l.quantile(0.999),
            l.latencies_us.len(),
            l.errors
        );
    }
    println!(
        "compensation / service (both through the API's layers): throughput {:.2}, p99 {:.2}; {connections} connections on loopback, {seconds} s per endpoint; \
         {cycles} cycles validated by the machine loop meanwhile",
        c.rate() / t.rate(),
        c.quantile(0.99) / t.quantile(0.99)
    );
    Ok(ExitCode::SUCCESS)
}

/// `bench compensation`: the three strategies on four scenarios, each prediction starting from
/// the service's model rebuilt from an earlier simulated day of the same machine, and the
/// schedules: the default (minute offsets), the tool-tip rule (the model's band in the loop)
/// and a fixed cadence with as many cycles as each.
pub fn compensation(
    json: bool,
    after_stop: Option<Vec<f64>>,
    tip_sigma: Option<f64>,
    only: Option<Vec<String>>,
) -> Result<ExitCode> {
    use crate::strategies::{BENCH_SCENARIOS, ScheduleComparison, bench_scenario};
    // The shipped policy with the tool-tip rule at the tuned limit unless told otherwise.
    let mut policy = driftwatch_machine::scheduler::SchedulePolicy {
        tip_sigma_um: crate::strategies::TUNED_TIP_SIGMA_UM,
        ..Default::default()
    };
    if let Some(t) = tip_sigma {
        anyhow::ensure!(t.is_finite() && t >= 0.0, "--tip-sigma takes um >= 0");
        policy.tip_sigma_um = t;
    }
    let own_schedule = after_stop.is_none();
    if let Some(a) = after_stop {
        anyhow::ensure!(
            a.iter().all(|x| x.is_finite() && *x > 0.0),
            "--after-stop takes minutes > 0"
        );
        policy.after_stop_min = a;
    }
    let mut all: Vec<(String, String, ScheduleComparison)> = Vec::new();
    if let Some(only) = &only
        && let Some(bad) = only
            .iter()
            .find(|n| !BENCH_SCENARIOS.iter().any(|(b, _)| b == n))
    {
        anyhow::bail!("--scenarios: {bad} is not a benchmark scenario");
    }
    let chosen = BENCH_SCENARIOS
        .into_iter()
        .filter(|(n, _)| only.as_ref().is_none_or(|o| o.iter().any(|x| x == n)));
    for (name, start) in chosen {
        let c = bench_scenario(name, &policy, own_schedule)
            .with_context(|| format!("scenario {name}"))?;
        all.push((name.to_string(), start.to_string(), c));
    }
    if json {
        let v: Vec<serde_json::Value> = all
            .iter()
            .map(|(n, s, c)| {
                serde_json::json!({"scenario": n, "model_from": s, "schedules": c.summary(), "result": c})
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "residual against the truth, every minute; tool tip at ({}, {}, {}) mm on the table at B {} C {} deg",
        crate::strategies::REFERENCE_POINT_MM[0],
        crate::strategies::REFERENCE_POINT_MM[1],
        crate::strategies::REFERENCE_POINT_MM[2],
        crate::strategies::REFERENCE_POSE_DEG[0],
        crate::strategies::REFERENCE_POSE_DEG[1]
    );
    for (name, start, sc) in &all {
        print_scenario(name, start, sc);
    }
    println!(
        "\nschedules: cycles per day, and the largest tool-tip residual of the prediction while cutting (* over the whole day: a program that never cuts), um"
    );
    println!(
        "  {:<14} {:>18} {:>18} {:>18} {:>18}",
        "", "minute offsets", "tool tip", "fixed, as tip", "fixed, as offsets"
    );
    for (name, _, sc) in &all {
        let s = sc.summary();
        let cell = |l: crate::strategies::ScheduleLine| {
            format!(
                "{:>5.1}/d {:>6.2}{}",
                l.cycles_per_day,
                l.max_tip_predicted_um,
                if l.while_cutting { " " } else { "*" }
            )
        };
        println!(
            "  {:<14} {:>18} {:>18} {:>18} {:>18}",
            name,
            cell(s.old),
            cell(s.new),
            cell(s.fixed),
            cell(s.fixed_old)
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// One scenario of `bench compensation`: each channel's residual by strategy, the tool tip,
/// and the service's schedule against a fixed cadence.
fn print_scenario(name: &str, start: &str, sc: &crate::strategies::ScheduleComparison) {
    let c = sc.day();
    println!(
        "\n{name}: {} min, {} cycles ({} ok); model from {start}",
        c.minutes, c.cycles, c.cycles_ok
    );
    println!(
        "  {:<9} {:>19} {:>19} {:>19} {:>9} {:>14} {:>22}",
        "",
        "none rms / max",
        "last meas. rms/max",
        "predicted rms/max",
        "removed",
        "served (end)",
        "band vs truth: z rms, <1s, <2s"
    );
    let names: Vec<&String> = c.none.errors.keys().collect();
    for n in names {
        let f = |r: &crate::strategies::StrategyResult| {
            let s = r.errors[n];
            format!("{:>8.2} / {:>8.2}", s.rms, s.max)
        };
        let served = c
            .served
            .iter()
            .find(|g| &g.channel == n)
            .map_or("-", |g| g.source.as_str());
        let band = c.band.get(n.as_str()).map_or("-".to_string(), |b| {
            format!(
                "{:.2}, {:.0} %, {:.0} %",
                b.z_rms,
                100.0 * b.within_1_sigma,
                100.0 * b.within_2_sigma
            )
        });
        let removed = c.removed(n);
        println!(
            "  {:<9} {:>19} {:>19} {:>19} {:>8.1}% {:>14} {:>22}{}",
            n,
            f(&c.none),
            f(&c.last_measured),
            f(&c.predicted),
            100.0 * removed,
            served,
            band,
            if removed < 0.0 {
                "  WORSE THAN NONE"
            } else {
                ""
            }
        );
    }
    println!(
        "  held-out cycles (each scored before it corrected the model), at the end of the day:"
    );
    for g in &c.served {
        println!("    {g}");
    }
    let t = |s: crate::strategies::Stats| format!("{:>8.2} / {:>8.2}", s.rms, s.max);
    println!(
        "  {:<9} {:>19} {:>19} {:>19}",
        "tool tip",
        t(c.none.tool_tip),
        t(c.last_measured.tool_tip),
        t(c.predicted.tool_tip)
    );
    println!(
        "  thermal error RMS removed at the tool tip: last measured {:.1} %, predicted {:.1} %",
        100.0 * (1.0 - c.last_measured.tool_tip.rms / c.none.tool_tip.rms),
        100.0 * c.tool_tip_reduction()
    );
    print_schedule(sc);
}

/// The schedules side by side: the default (minute offsets), the policy's, and a fixed cadence with as
/// many cycles as each.
fn print_schedule(sc: &crate::strategies::ScheduleComparison) {
    let ez = |r: &crate::strategies::ScheduleRun| {
        r.result
            .predicted
            .errors
            .get("EZ0B")
            .map_or(f64::NAN, |s| s.max)
    };
    println!(
        "  schedules (idle minutes only): cycles, per day, within 30 min after a stop; largest tool-tip residual while cutting (predicted, last measured; * the whole day: no cutting), EZ0B predicted max"
    );
    for (label, r) in [
        ("minute offsets (the default)", &sc.old),
        ("the model's tool-tip band", &sc.new),
        ("fixed cadence, as many as tip", &sc.fixed),
        ("fixed cadence, as many as min.", &sc.fixed_old),
    ] {
        let l = crate::strategies::ScheduleLine::from(r);
        println!(
            "    {:<30} {:>3} cycles {:>5.1}/d {:>2} after stops; tool tip {:>6.2} / {:>6.2} um{} ; EZ0B {:>5.2} um",
            label,
            l.cycles,
            l.cycles_per_day,
            r.after_stops,
            l.max_tip_predicted_um,
            l.max_tip_last_measured_um,
            if l.while_cutting { "" } else { " *" },
            ez(r)
        );
    }
    for (label, r) in [
        ("minute offsets", &sc.old),
        ("tool tip", &sc.new),
        ("fixed as tip", &sc.fixed),
        ("fixed as offsets", &sc.fixed_old),
    ] {
        println!("    cycle times (min), {label}: {:?}", r.times_min);
    }
}

/// The diagnosis on `days` production days of the ambient-swing hall (logged), a cycle every
/// 30 min, 0.5-um noise: simulation and diagnosis timed apart, on one thread.
pub fn diagnosis(days: f64) -> Result<ExitCode> {
    use driftwatch_diagnosis::cycles::{DiagnoseOptions, Inputs, detection_rows, diagnose};
    let days = if days >= 365.0 {
        3
    } else {
        days.max(1.0).round() as usize
    };
    let mut scn = Scenario::load("ambient_swing")?
        .repeated_days(days)
        .with_cycles_every(30.0);
    scn.noise.sigma_um = 0.5;
    let k = Kinematics::load(&scn.machine)?;
    let plan = driftwatch_core::plan::Plan::build(
        &k,
        &driftwatch_core::plan::PlanConfig::load(&scn.plan)?,
    )?;
    let t = std::time::Instant::now();
    let sim = driftwatch_sim::simulator::simulate(&scn, &k, &plan)?;
    let t_sim = t.elapsed();
    let inputs = Inputs::of(&sim.recording());
    let t = std::time::Instant::now();
    let opts = DiagnoseOptions::new(0.5);
    let rows = detection_rows(
        &k,
        &inputs.detections,
        &driftwatch_core::identify::SolveOptions::new(0.5),
    )?;
    let t_rows = t.elapsed();
    let d = diagnose(&rows, &inputs.spindle, &inputs.temperatures, &opts)?;
    let t_all = t.elapsed();
    let n_cands = driftwatch_diagnosis::effects::candidates(
        &rows,
        &driftwatch_diagnosis::effects::Drivers::new(
            &rows,
            &inputs.spindle,
            &inputs.temperatures,
            &opts.model,
        ),
        opts.model.n_ref_rpm,
    )
    .len();
    println!(
        "{days} days, {} cycles, {} readings, {n_cands} library candidates: simulation {:.2} s; rows {:.2} s; rows + diagnosis {:.2} s (goal 10 s); accepted {:?}",
        d.cycles,
        d.readings,
        t_sim.as_secs_f64(),
        t_rows.as_secs_f64(),
        t_all.as_secs_f64(),
        d.accepted.iter().map(|a| &a.term).collect::<Vec<_>>()
    );
    Ok(ExitCode::SUCCESS)
}

/// Two days of production (`ambient_swing`'s program), a cycle every 30 min, 0.5-um noise,
/// no thermal truth beyond the effect under test.
fn power_scenario(seed: u64) -> Result<Scenario> {
    let mut scn = Scenario::load("ambient_swing")?
        .repeated_days(2)
        .with_cycles_every(30.0);
    scn.seed = seed;
    scn.noise.sigma_um = 0.5;
    scn.ambient.amplitude_k = 0.0;
    scn.truth.channels.clear();
    Ok(scn)
}

/// The power curve: for skip latency (a feed change after day 1) and the speed-dependent
/// tool radius (cycles alternating 20000 and 8000 min^-1), the share of `trials` recordings
/// in which the diagnosis names the effect, at multiples of the detection threshold the
/// diagnosis itself reports for that plan (docs/physics.md 4.3: 50 % power at delta-BIC 10).
pub fn power(trials: usize) -> Result<ExitCode> {
    use driftwatch_diagnosis::cycles::{DiagnoseOptions, Inputs, diagnose_inputs};
    use driftwatch_sim::scenario::FeedChange;
    type Setup = fn(&mut Scenario, f64);
    let effects: [(&str, &str, Setup); 2] = [
        ("skip_latency", "ms", |s, a| {
            s.cycles.feed_changes = vec![FeedChange {
                at_min: 1440.0,
                feed_mm_min: 200.0,
            }];
            s.skip.latency_ms = a;
        }),
        ("radius_speed", "um", |s, a| {
            s.cycles.rpm_sequence = vec![20000.0, 8000.0];
            if a != 0.0 {
                let ch: driftwatch_core::thermal::Channel =
                    toml::from_str(&format!("instant = {a}")).unwrap_or_default();
                s.truth.channels.insert("radius".into(), ch);
            }
        }),
    ];
    let run = |scn: &Scenario| -> Result<driftwatch_diagnosis::cycles::Diagnosis> {
        let k = Kinematics::load(&scn.machine)?;
        let plan = driftwatch_core::plan::Plan::build(
            &k,
            &driftwatch_core::plan::PlanConfig::load(&scn.plan)?,
        )?;
        let sim = driftwatch_sim::simulator::simulate(scn, &k, &plan)?;
        Ok(diagnose_inputs(
            &k,
            &Inputs::of(&sim.recording()),
            &DiagnoseOptions::new(scn.noise.sigma_um),
        )?)
    };
    println!("effect        amplitude   x threshold   detected (of {trials})   false other terms");
    for (effect, unit, setup) in effects {
        // The plan's threshold, from a recording without the effect.
        let mut scn = power_scenario(1000)?;
        setup(&mut scn, 0.0);
        let d = run(&scn)?;
        let threshold = d
            .thresholds
            .iter()
            .filter(|t| t.effect == effect)
            .map(|t| t.amplitude)
            .fold(f64::INFINITY, f64::min);
        println!("{effect}: detection threshold {threshold:.3} {unit} (delta-BIC 10, 50 % power)");
        for m in [0.5, 1.0, 1.5, 2.0, 3.0] {
            let a = m * threshold;
            let (mut hit, mut other) = (0, 0);
            for trial in 0..trials {
                let mut scn = power_scenario(trial as u64 + 1)?;
                setup(&mut scn, a);
                let d = run(&scn)?;
                if d.accepted.iter().any(|x| {
                    x.effect == effect || x.ambiguity_group.iter().any(|g| g.effect == effect)
                }) {
                    hit += 1;
                }
                other += d.accepted.iter().filter(|x| x.effect != effect).count();
            }
            println!(
                "{effect:<13} {a:>7.3} {unit:<3} {m:>8.1}     {hit:>3} ({:>3.0} %)            {other}",
                100.0 * hit as f64 / trials as f64
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// A shipped real data set for `bench thermal`: a CSV under the data directory, its columns
/// and where its hold-out starts.
struct RealSet {
    name: &'static str,
    csv: &'static str,
    time_column: &'static str,
    spindle: Option<&'static str>,
    temperatures: Vec<String>,
    channels: Vec<String>,
}

fn real_sets() -> Vec<RealSet> {
    let temps: Vec<String> = (1..=16).map(|i| format!("t{i}_C")).collect();
    let chans: Vec<String> = (1..=5).map(|i| format!("ch{i}_um")).collect();
    vec![
        RealSet {
            name: "fl-thermal",
            csv: "fl-thermal/fl_thermal.csv",
            time_column: "time_s",
            spindle: Some("spindle_rpm"),
            temperatures: temps.clone(),
            channels: chans.clone(),
        },
        // The same test with the spindle log left out at import: temperatures alone.
        RealSet {
            name: "fl-thermal, no spindle column",
            csv: "fl-thermal/fl_thermal.csv",
            time_column: "time_s",
            spindle: None,
            temperatures: temps,
            channels: chans,
        },
    ]
}

/// A shipped real data set's events (from t = 0).
fn real_events(data: &Path, set: &RealSet) -> Result<Vec<driftwatch_thermal::model::Event>> {
    use driftwatch_recording::csv_import::{CsvOptions, RowTime, import_csv};
    let path = data.join(set.csv);
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("reading {} (give --data DIR)", path.display()))?;
    let im = import_csv(
        &text,
        &CsvOptions {
            time: RowTime::Column(set.time_column.into()),
            start_ns: 0,
            spindle: set.spindle.map(String::from),
            temperatures: set.temperatures.clone(),
            displacements: set.channels.clone(),
            machine_id: set.name.into(),
        },
    )
    .with_context(|| format!("importing {}", path.display()))?;
    Ok(driftwatch_thermal::model::events_from(&[im.recording]))
}

/// The displacement diagnosis on every shipped real data set and on null recordings made
/// from the first: the terms that worsen the held-out end, the false positives on `n_nulls`
/// nulls, and the power on injected temperature effects; each under the acceptance rules
/// in force before and now.
pub fn nulls(data: &Path, n_nulls: usize, json: bool) -> Result<ExitCode> {
    use crate::calibration::{null_trial, power_trial, worsening_terms};
    use crate::null_recordings::Null;
    use driftwatch_diagnosis::displacement::{DisplacementOptions, diagnose_displacements};
    let rules = [
        ("before", DisplacementOptions::earlier_rules()),
        ("now", DisplacementOptions::default()),
    ];
    let sets = real_sets();
    let mut report = serde_json::Map::new();
    // 1. Real data: held-out end, and terms that worsen it.
    let mut real = Vec::new();
    for set in &sets {
        let events = real_events(data, set)?;
        for (rule, opts) in &rules {
            let mut opts = opts.clone();
            opts.n_ref_rpm = top_speed(&events);
            let d = diagnose_displacements(&events, &set.channels, &opts)?;
            let worse = worsening_terms(&d);
            for c in &d.channels {
                let w = worse.iter().filter(|w| w.0 == c.channel).count();
                if !json {
                    println!(
                        "{:<30} {:<7} {:<7} held-out {:>6.2} um baseline, {:>6.2} um final; {} terms accepted, {} worsen the held-out end",
                        set.name,
                        rule,
                        c.channel,
                        c.baseline.rms_heldout_um,
                        c.final_fit.rms_heldout_um,
                        c.accepted.len(),
                        w
                    );
                }
                real.push(serde_json::json!({
                    "set": set.name, "rule": rule, "channel": c.channel,
                    "baseline_heldout_um": c.baseline.rms_heldout_um,
                    "final_heldout_um": c.final_fit.rms_heldout_um,
                    "accepted": c.accepted.len(), "worsening": w,
                }));
            }
        }
    }
    report.insert("real".into(), real.into());
    // 2. Nulls from the first set (with its spindle log): four kinds in turn, the channels
    // in turn, one seed each.
    let base = real_events(data, &sets[0])?;
    let n_ref = top_speed(&base);
    let rules = rules.map(|(rule, opts)| {
        (
            rule,
            DisplacementOptions {
                n_ref_rpm: n_ref,
                ..opts
            },
        )
    });
    let mut null_rows = Vec::new();
    for (rule, opts) in &rules {
        let mut hits = 0;
        for i in 0..n_nulls {
            let kind = Null::ALL[i % Null::ALL.len()];
            let ch = &sets[0].channels[(i / Null::ALL.len()) % sets[0].channels.len()];
            let o = null_trial(&base, kind, ch, i as u64, opts)?;
            hits += usize::from(!o.false_terms.is_empty());
            if !json && !o.false_terms.is_empty() {
                println!(
                    "null {i:>3} {rule:<7} {:<17} {:<7} false: {}",
                    o.null,
                    o.channel,
                    o.false_terms.join(", ")
                );
            }
            null_rows.push(serde_json::json!({"rule": rule, "outcome": o}));
        }
        if !json {
            println!(
                "nulls, rule {rule}: {hits} of {n_nulls} with a false term ({:.1} %)",
                100.0 * hits as f64 / n_nulls.max(1) as f64
            );
        }
    }
    report.insert("nulls".into(), null_rows.into());
    // 3. Power: t11_C's change injected into AR-noise nulls of ch1, by size.
    let mut power_rows = Vec::new();
    let trials = 10;
    for rms in [0.25, 0.5, 1.0, 2.0, 4.0] {
        for (rule, opts) in &rules {
            let mut found = 0;
            for seed in 0..trials {
                found += usize::from(power_trial(
                    &base,
                    "ch1_um",
                    "t11_C",
                    rms,
                    1000 + seed,
                    opts,
                )?);
            }
            if !json {
                println!(
                    "power, rule {rule:<7} t11_C effect of {rms:>4} um RMS in {} um AR noise: found {found} of {trials}",
                    crate::calibration::NULL_NOISE_UM
                );
            }
            power_rows.push(
                serde_json::json!({"rule": rule, "rms_um": rms, "found": found, "trials": trials}),
            );
        }
    }
    report.insert("power".into(), power_rows.into());
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}

/// The top logged spindle speed (1 without a spindle log): the diagnosis' reference speed.
pub(crate) fn top_speed(events: &[driftwatch_thermal::model::Event]) -> f64 {
    events
        .iter()
        .filter_map(|e| match e {
            driftwatch_thermal::model::Event::Spindle { rpm, .. } => Some(rpm.abs()),
            _ => None,
        })
        .fold(0.0, f64::max)
        .max(1.0)
}
