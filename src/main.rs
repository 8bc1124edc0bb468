//! The `driftwatch` command: a thin shell over the library.

#[cfg(feature = "jemalloc")]
#[global_allocator]
static ALLOC: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};

use driftwatch_core::cycle::{CycleChecks, group_by_cycle, infer_expected, process_cycle};
use driftwatch_core::identify::{Identifier, Observation, SolveOptions};
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::plan::{Plan, PlanConfig};
use driftwatch_core::recording::{self as rec, Timed};
use driftwatch_lab::bench;
use driftwatch_recording::mcap_io::{ReadOptions, RecordingWriter, read_file};
use driftwatch_sim::experiment;
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::simulate;

mod diagnose_cmd;
mod linear_cmd;
mod model_cmd;
mod nc_cmd;
mod nc_program_cmd;
mod plan_design_cmd;
mod prediction_plot;
mod rtest_cmd;
mod serve;

/// Print to stdout; a closed pipe (`driftwatch solve ... | head`) ends the command quietly.
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        write!(std::io::stdout().lock(), $($arg)*)?
    }};
}

macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)?
    }};
}

#[derive(Parser)]
#[command(
    name = "driftwatch",
    version,
    about = "Keeps a 5-axis machine's rotary-axis compensation true while it heats and cools"
)]
struct Cli {
    /// Log as JSON lines instead of text.
    #[arg(long, global = true)]
    log_json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the service: machines, scheduler, storage, HTTP API (the shipped default runs one
    /// simulated machine through a two-shift day at 60x).
    Serve {
        /// Configuration TOML (default: the built-in `config/default.toml`).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Simulated seconds per wall second (overrides the configuration).
        #[arg(long)]
        time_scale: Option<f64>,
        /// Stop after this many minutes of machine time.
        #[arg(long)]
        until: Option<f64>,
        /// Listen address (overrides the configuration).
        #[arg(long)]
        listen: Option<std::net::SocketAddr>,
        /// Data directory (overrides the configuration).
        #[arg(long)]
        data_dir: Option<PathBuf>,
        /// Start on an empty database although recordings of an earlier history lie in the
        /// data directory (refused without it: the database was emptied or replaced, and the
        /// versions would begin again at 1; the new store's sets get new ETags).
        #[arg(long)]
        new_database: bool,
    },
    /// Ask a running service whether it answers (exit 0 on 200 from the URL, 1 otherwise):
    /// the container image's HEALTHCHECK, which has no curl.
    Healthcheck {
        /// The service's health endpoint.
        #[arg(long, default_value = "http://127.0.0.1:8080/healthz")]
        url: String,
        /// Seconds to wait for the answer.
        #[arg(long, default_value_t = 5.0)]
        timeout_s: f64,
    },
    /// A fleet's leases and the audit of its stored data: who ran each machine in which term,
    /// and every breach of one-process-at-a-time or versions-only-forward the data shows
    /// (exit 1 if any).
    FleetAudit {
        /// Configuration TOML whose database to read (default: the built-in one).
        #[arg(long)]
        config: Option<PathBuf>,
        /// The database instead (postgres://... or sqlite://PATH).
        #[arg(long)]
        database_url: Option<String>,
    },
    /// Run the truth simulator over a scenario and write a contract recording (MCAP).
    Simulate {
        /// Scenario TOML, or a built-in name (patent, warmup).
        #[arg(long)]
        scenario: String,
        #[arg(long)]
        out: PathBuf,
        /// Use this plan instead of the scenario's (built-in name or TOML path).
        #[arg(long)]
        plan: Option<String>,
        /// Repeat the scenario's first day (its spindle program) this many days.
        #[arg(long)]
        days: Option<usize>,
    },
    /// Identify every cycle of a contract recording.
    Solve {
        /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c, head_d45_table_c, trunnion_ac).
        #[arg(long)]
        machine: String,
        #[arg(long)]
        recording: PathBuf,
        /// Print JSON lines shaped like /cycle/result instead of a table.
        #[arg(long)]
        json: bool,
        /// Check each cycle against this plan's measurements, matched by pose, approach and feed
        /// (else against the measurements most cycles share). Step labels are free.
        #[arg(long)]
        plan: Option<String>,
        /// Read a recording cut short up to its last complete chunk.
        #[arg(long)]
        recover: bool,
        /// Also print each cycle's estimate from the patent's first-order sum and difference
        /// relations (derived for every built-in family) and its difference from the exact
        /// solve: an independent cross-check of the model.
        #[arg(long)]
        relations: bool,
        #[command(flatten)]
        solver: SolverArgs,
    },
    /// The NC side: a plan as a program in the control's own language, a compensation set
    /// in its variables.
    Nc {
        #[command(subcommand)]
        what: nc_cmd::NcCmd,
    },
    /// The R-test (ISO 10791-6; seed 002): simulate BK1, BK2 and XYC, process readings to
    /// radial, axial and tangential deviations, identify the location errors.
    Rtest {
        #[command(subcommand)]
        what: rtest_cmd::RtestCmd,
    },
    /// The laser step diagonal (seed 004): simulate an interferometer log, or solve one
    /// with the conventional and the set-up-robust formulations.
    Diagonal {
        #[command(subcommand)]
        what: linear_cmd::DiagonalCmd,
    },
    /// Seed 003's correction table of a faced part: from a measured section, or the
    /// cut-measure-correct loop on a simulated face.
    CorrectionTable(linear_cmd::CorrectionArgs),
    /// Turn a table from another tool into a contract recording.
    Import {
        #[command(subcommand)]
        what: ImportWhat,
    },
    /// Fit the thermal model to recordings (spindle, temperatures, displacements, cycle results).
    Fit(model_cmd::FitArgs),
    /// Replay a recording causally through a fitted model: the prediction at every step.
    Predict(model_cmd::PredictArgs),
    /// Locate where the model and the recordings differ, name the physics left out, model it
    /// and show the fit improve (diagnosis.json and report.html).
    Diagnose(diagnose_cmd::DiagnoseArgs),
    /// Reproduce an experiment of the source documents end to end.
    Experiment {
        #[arg(value_enum)]
        which: Which,
        /// Where the CSV, SVG and recording go.
        #[arg(long, default_value = "out/experiment")]
        out_dir: PathBuf,
        /// Scenario to run instead of the built-in one.
        #[arg(long, conflicts_with = "machine")]
        scenario: Option<String>,
        /// Run the built-in patent scenario of this machine family (`patent_<machine>`;
        /// `table_bc`: `patent`).
        #[arg(long)]
        machine: Option<String>,
    },
    /// Print a plan's moves, its machine time and the Cramer-Rao bound of each error
    /// (`plan design`: search for a plan instead).
    Plan(PlanArgs),
    /// Benchmarks (run and report; not tests).
    Bench(BenchArgs),
}

/// `plan --machine M [--plan P]` prints a plan; `plan design ...` designs one. The flags of
/// the first form do not mix with the subcommand.
#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
struct PlanArgs {
    #[command(subcommand)]
    design: Option<PlanWhat>,
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c,
    /// head_d45_table_c, trunnion_ac).
    #[arg(long, required = true)]
    machine: Option<String>,
    /// Plan TOML or built-in name (patent, patent_sequential, patent_both_sides, a family's
    /// own); default the machine file's `plan`.
    #[arg(long)]
    plan: Option<String>,
    /// One-reading standard uncertainty, um (default: the machine's).
    #[arg(long)]
    sigma_um: Option<f64>,
    /// Also estimate tool-tip drift rates within the cycle.
    #[arg(long)]
    drift_rates: bool,
}

#[derive(Subcommand)]
enum PlanWhat {
    /// Search poses, approaches, repeats and order for the smallest worst Cramer-Rao sigma
    /// within a machine-time budget; print the Pareto front, write the chosen plan.
    Design(plan_design_cmd::DesignArgs),
}

#[derive(Subcommand)]
enum ImportWhat {
    /// A CSV of a thermal test: spindle speed, temperatures, displacements per row.
    Csv(model_cmd::ImportCsvArgs),
    /// An R-test device's export (angle and the three sensors per row) as `/rtest/*`.
    RtestCsv(rtest_cmd::ImportArgs),
}

#[derive(clap::Args, Clone)]
struct SolverArgs {
    /// One-reading standard uncertainty, um (default: the machine's).
    #[arg(long)]
    sigma_um: Option<f64>,
    /// Huber weighting with this threshold in sigmas (e.g. 1.5).
    #[arg(long)]
    huber: Option<f64>,
    /// Also estimate tool-tip drift rates within each cycle from the timestamps.
    #[arg(long)]
    drift_rates: bool,
    /// Largest distance of a reading from its nominal value, mm.
    #[arg(long, default_value_t = 1.0)]
    max_deviation_mm: f64,
    /// Service configuration whose `[validation]` limits judge each result, as the service
    /// would (default: the built-in config/default.toml).
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(Clone, Copy, ValueEnum)]
enum Which {
    Patent,
}

/// `bench WHICH` and every bench's options (each bench reads its own).
#[derive(clap::Args)]
struct BenchArgs {
    #[arg(value_enum)]
    which: BenchWhich,
    /// Machine whose cycles `bench solve` solves (built-in name or path).
    #[arg(long, default_value = "table_bc")]
    machine: String,
    /// Plan to solve (built-in or path); default the machine's own plan in its listed order
    /// (one pass: `patent_sequential` on table_bc).
    #[arg(long)]
    plan: Option<String>,
    /// Number of solves.
    #[arg(long, default_value_t = 20000)]
    n: usize,
    /// Simulated days (bench year: default 365; bench fleet: 1; bench diagnosis takes 3
    /// unless given below 365).
    #[arg(long)]
    days: Option<f64>,
    /// Scratch directory (bench year, http and fleet; emptied first).
    #[arg(long, default_value = "out/bench")]
    dir: PathBuf,
    /// Machines (bench fleet).
    #[arg(long, default_value_t = 10)]
    machines: usize,
    /// What the fleet's machines are (bench fleet): the simulator in the service, or nc_push
    /// doors driven over HTTP by a recorded day of NC traffic (a plant's NCs).
    #[arg(long, value_enum, default_value = "simulated")]
    link: bench::FleetLink,
    /// With --link nc-push: after the rest, this many seconds at 1x with every NC silent and
    /// no client (the loops' own CPU).
    #[arg(long, default_value_t = 60.0)]
    idle_s: f64,
    /// The fleet's database (bench fleet): SQLite in --dir, or PostgreSQL (a throwaway server
    /// under --dir unless --database-url is given).
    #[arg(long, value_enum, default_value = "sqlite")]
    backend: bench::FleetBackend,
    /// An empty PostgreSQL database for bench fleet, postgres://...
    #[arg(long)]
    database_url: Option<String>,
    /// Spread the fleet's days over this many minutes (bench fleet; 0: every machine's day
    /// starts in the same instant).
    #[arg(long, default_value_t = 60.0)]
    stagger_min: f64,
    /// After the simulated days, run this many minutes with the clock at 1x (bench fleet):
    /// the CPU the fleet keeps busy in real time and how far its loops fall behind.
    #[arg(long, default_value_t = 0.0)]
    realtime_min: f64,
    /// Concurrent keep-alive connections (bench http).
    #[arg(long, default_value_t = 64)]
    connections: usize,
    /// Seconds of load per endpoint (bench http).
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Print JSON (bench compensation, bench thermal, bench located).
    #[arg(long)]
    json: bool,
    /// Directory of thermal-test data sets (bench thermal: every manifest*.toml in it and
    /// its subfolders, docs/thermal-sets.md; bench nulls: the shipped fl-thermal).
    #[arg(long, default_value = "tests/data")]
    data: PathBuf,
    /// Grid step of the thermal families, min (bench thermal; default: each set's own).
    #[arg(long)]
    step_min: Option<f64>,
    /// Minutes between the validated cycles replayed (bench served).
    #[arg(long, default_value_t = 120.0)]
    cycle_every_min: f64,
    /// Replay the service's schedule, with its tool-tip rule (at --tip-sigma, the
    /// configuration's, or 0.5 um) and without it, each against a fixed cadence with as many
    /// cycles, instead of one fixed cadence (bench served).
    #[arg(long)]
    schedules: bool,
    /// Service configuration whose `[thermal]` policy the live model runs with, and with
    /// --schedules whose `[schedule]` and `[phase]` the scheduler runs with (bench served;
    /// default: the built-in config/default.toml). Its temperature inputs are replaced by
    /// each set's sensors.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Leave the simulated scenarios out (bench thermal).
    #[arg(long)]
    no_simulated: bool,
    /// Serve predicted sets between cycles (bench year): on or off.
    #[arg(long, default_value = "on", value_parser = ["on", "off"])]
    prediction: String,
    /// Cycles after a spindle stop, min, for the day under test (bench compensation;
    /// default: the shipped policy). The patent scenario then uses the scheduler too.
    #[arg(long, value_delimiter = ',')]
    after_stop: Option<Vec<f64>>,
    /// The tool-tip limit of the schedule under test, um (bench compensation, bench served
    /// --schedules; default: the tuned 0.5; 0: the minute offsets alone, not for bench served).
    #[arg(long)]
    tip_sigma: Option<f64>,
    /// Only these of the benchmark's scenarios (bench compensation; default: all four).
    #[arg(long, value_delimiter = ',')]
    scenarios: Option<Vec<String>>,
}

#[derive(Clone, Copy, ValueEnum)]
enum BenchWhich {
    /// Solves per second of one thread.
    Solve,
    /// One simulated year of one machine through the service pipeline.
    Year,
    /// GET /compensation under load next to the API's cheapest read (GET /service, through the
    /// same layers), on loopback.
    Http,
    /// N simulated machines through a simulated day in one process, as fast as they keep up,
    /// with the compensation endpoint polled meanwhile.
    Fleet,
    /// No compensation, last measured and predicted against the truth on four scenarios.
    Compensation,
    /// The diagnosis with the full library on a three-day recording, a cycle every 30 min.
    Diagnosis,
    /// Detection rate against amplitude for two effects, next to the detection threshold
    /// (--n trials per amplitude; 20 unless given below 20000).
    Power,
    /// Every thermal model family against persistence, regression, key-temperature
    /// regression and ARX on every shipped real data set (--data, default tests/data).
    Thermal,
    /// The displacement diagnosis on the shipped real data and on null recordings made from
    /// it: terms that worsen the held-out end, false positives on --n nulls (40 unless given
    /// below 20000), power on injected effects; under the earlier acceptance rules and now.
    Nulls,
    /// The located term's power on every data set under --data: a drift that follows one
    /// temperature after an onset injected into each run's real readings at 1.5, 3 and 6 um
    /// RMS, and the run as it is as the null.
    Located,
    /// The service's live model replayed on every data set under --data (the runs one a
    /// day, a validated cycle every --cycle-every-min): what it serves between cycles
    /// against the last cycle held and least squares on the cycles so far.
    Served,
    /// How often the cycle diagnosis flags a clean simulated recording "unexplained" (--n
    /// recordings, 200 unless given below 20000), and the same seeds read 20 % noisier.
    Unexplained,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let sub = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if cli.log_json {
        sub.json().init();
    } else {
        sub.init();
    }
    match run(cli.command) {
        Ok(code) => code,
        Err(e)
            if e.chain().any(|c| {
                c.downcast_ref::<std::io::Error>()
                    .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
            }) =>
        {
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn checks(k: &Kinematics, args: &SolverArgs) -> Result<CycleChecks> {
    let mut c = CycleChecks::new(k);
    let sigma = args.sigma_um.unwrap_or(k.setter.sigma_um);
    c.solve = SolveOptions::new(sigma);
    if args.drift_rates {
        c.solve = c.solve.with_drift_rates();
    }
    c.solve.huber_k = args.huber;
    if !(args.max_deviation_mm.is_finite() && args.max_deviation_mm > 0.0) {
        bail!("--max-deviation-mm must be > 0");
    }
    c.max_deviation_mm = args.max_deviation_mm;
    Ok(c)
}

fn run(cmd: Command) -> Result<ExitCode> {
    match cmd {
        Command::Healthcheck { url, timeout_s } => {
            current_thread()?.block_on(serve::healthcheck(&url, timeout_s))
        }
        Command::FleetAudit {
            config,
            database_url,
        } => current_thread()?.block_on(serve::fleet_audit(config.as_deref(), database_url)),
        Command::Serve {
            config,
            time_scale,
            until,
            listen,
            data_dir,
            new_database,
        } => {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()
                .context("starting the async runtime")?;
            rt.block_on(serve::run(serve::Options {
                config,
                time_scale,
                until,
                listen,
                data_dir,
                new_database,
            }))
        }
        Command::Simulate {
            scenario,
            out,
            plan,
            days,
        } => cmd_simulate(&scenario, &out, plan.as_deref(), days),
        Command::Import { what } => match what {
            ImportWhat::Csv(a) => model_cmd::cmd_import_csv(a),
            ImportWhat::RtestCsv(a) => rtest_cmd::cmd_import(a).map(|()| ExitCode::SUCCESS),
        },
        Command::Rtest { what } => rtest_cmd::cmd_rtest(what).map(|()| ExitCode::SUCCESS),
        Command::Diagonal { what } => linear_cmd::cmd_diagonal(what),
        Command::CorrectionTable(a) => linear_cmd::cmd_correction_table(a),
        Command::Nc { what } => nc_cmd::cmd_nc(what),
        Command::Fit(a) => model_cmd::cmd_fit(a),
        Command::Predict(a) => model_cmd::cmd_predict(a),
        Command::Diagnose(a) => diagnose_cmd::cmd_diagnose(a),
        Command::Solve {
            machine,
            recording,
            json,
            plan,
            recover,
            relations,
            solver,
        } => cmd_solve(
            &machine,
            &recording,
            json,
            plan.as_deref(),
            recover,
            relations,
            &solver,
        ),
        Command::Experiment {
            which: Which::Patent,
            out_dir,
            scenario,
            machine,
        } => {
            let scenario = match (scenario, machine.as_deref()) {
                (Some(s), _) => s,
                (None, None | Some("table_bc")) => "patent".to_string(),
                (None, Some(m)) => format!("patent_{m}"),
            };
            cmd_experiment(&scenario, &out_dir)
        }
        Command::Plan(PlanArgs {
            design: Some(PlanWhat::Design(a)),
            ..
        }) => plan_design_cmd::cmd_plan_design(a),
        Command::Plan(PlanArgs {
            design: None,
            machine,
            plan,
            sigma_um,
            drift_rates,
        }) => {
            let machine = machine.context("--machine is required")?;
            cmd_plan(&machine, plan.as_deref(), sigma_um, drift_rates)
        }
        Command::Bench(b) => run_bench(b),
    }
}

/// `bench WHICH`: each bench on its own runtime, if it needs one.
fn run_bench(b: BenchArgs) -> Result<ExitCode> {
    let multi = || {
        tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()
            .context("starting the async runtime")
    };
    match b.which {
        BenchWhich::Solve => cmd_bench_solve(&b.machine, b.plan.as_deref(), b.n),
        BenchWhich::Year => tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("starting the async runtime")?
            .block_on(bench::year(
                b.days.unwrap_or(365.0),
                b.dir,
                b.prediction == "on",
            )),
        BenchWhich::Compensation => {
            bench::compensation(b.json, b.after_stop, b.tip_sigma, b.scenarios)
        }
        BenchWhich::Diagnosis => bench::diagnosis(b.days.unwrap_or(365.0)),
        BenchWhich::Thermal => {
            bench::thermal::thermal(&b.data, b.step_min, b.json, !b.no_simulated)
        }
        BenchWhich::Nulls => {
            bench::nulls(&b.data, if b.n >= 20000 { 40 } else { b.n.max(1) }, b.json)
        }
        BenchWhich::Located => bench::located::located(&b.data, b.json),
        BenchWhich::Served => {
            let cfg = driftwatch_service::config::ServiceConfig::load(b.config.as_deref())?;
            let schedules = b.schedules.then(|| {
                let mut policy = cfg.schedule.clone();
                policy.tip_sigma_um = b.tip_sigma.unwrap_or(if policy.tip_sigma_um > 0.0 {
                    policy.tip_sigma_um
                } else {
                    driftwatch_lab::strategies::TUNED_TIP_SIGMA_UM
                });
                bench::served::Schedules {
                    policy,
                    phase: cfg.phase.clone(),
                }
            });
            bench::served::served(
                &b.data,
                cfg.thermal,
                b.step_min,
                b.cycle_every_min,
                schedules,
                b.json,
            )
        }
        BenchWhich::Unexplained => {
            bench::unexplained::unexplained(if b.n >= 20000 { 200 } else { b.n.max(1) }, b.json)
        }
        BenchWhich::Power => bench::power(if b.n >= 20000 { 20 } else { b.n.max(1) }),
        BenchWhich::Http => multi()?.block_on(bench::http(b.connections, b.seconds, b.dir)),
        BenchWhich::Fleet => multi()?.block_on(bench::fleet(bench::FleetOptions {
            machines: b.machines,
            link: b.link,
            idle_s: b.idle_s,
            backend: b.backend,
            database_url: b.database_url,
            days: b.days.unwrap_or(1.0),
            dir: b.dir,
            stagger_min: b.stagger_min,
            realtime_min: b.realtime_min,
        })),
    }
}

fn load_scenario(name: &str, plan_override: Option<&str>) -> Result<(Scenario, Kinematics, Plan)> {
    let scn = Scenario::load(name)?;
    let k = Kinematics::load(&scn.machine)?;
    let plan_cfg = PlanConfig::load(plan_override.unwrap_or(&scn.plan))?;
    let plan = Plan::build(&k, &plan_cfg)?;
    Ok((scn, k, plan))
}

/// Write a simulation with the truth-free results of its cycles.
fn write_recording(
    path: &Path,
    sim: &driftwatch_sim::simulator::Simulation,
    outcomes: &[driftwatch_core::cycle::CycleOutcome],
) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut w = RecordingWriter::create_file(path)
        .with_context(|| format!("creating recording {}", path.display()))?;
    let t0 = sim.truth.first().map(|t| t.t_ns).unwrap_or(0);
    w.write(rec::TOPIC_INFO, t0, &sim.info)?;
    // Merge everything in time order so that readers see one timeline.
    let mut items: Vec<(i64, u8, usize)> = Vec::new();
    items.extend(sim.states.iter().enumerate().map(|(i, m)| (m.t_ns, 0, i)));
    items.extend(sim.spindle.iter().enumerate().map(|(i, m)| (m.t_ns, 1, i)));
    items.extend(
        sim.temperatures
            .iter()
            .enumerate()
            .map(|(i, m)| (m.t_ns, 2, i)),
    );
    items.extend(sim.truth.iter().enumerate().map(|(i, m)| (m.t_ns, 3, i)));
    let dets: Vec<&Timed<rec::DetectionMsg>> = sim
        .cycles
        .iter()
        .flat_map(|c| c.detections.iter())
        .collect();
    items.extend(dets.iter().enumerate().map(|(i, m)| (m.t_ns, 4, i)));
    let mut results: Vec<(i64, rec::CycleResultMsg)> = Vec::new();
    for (o, c) in outcomes.iter().zip(&sim.cycles) {
        // A result is known once its cycle's last detection is in.
        let t = c.detections.last().map(|d| d.t_ns).unwrap_or(o.t_ref_ns);
        results.push((t, o.message()));
    }
    items.extend(results.iter().enumerate().map(|(i, m)| (m.0, 5, i)));
    items.extend(
        sim.cycles
            .iter()
            .enumerate()
            .map(|(i, c)| (c.truth.t_ns, 6, i)),
    );
    items.sort();
    let mut since_flush = 0;
    for (t, kind, i) in items {
        match kind {
            0 => w.write(rec::TOPIC_STATE, t, &sim.states[i].msg)?,
            1 => w.write(rec::TOPIC_SPINDLE, t, &sim.spindle[i].msg)?,
            2 => w.write(rec::TOPIC_TEMPERATURE, t, &sim.temperatures[i].msg)?,
            3 => w.write(rec::TOPIC_TRUTH, t, &sim.truth[i])?,
            4 => w.write(rec::TOPIC_DETECTION, t, &dets[i].msg)?,
            5 => {
                w.write(rec::TOPIC_RESULT, t, &results[i].1)?;
                since_flush = 0;
                w.flush()?;
            }
            _ => w.write(rec::TOPIC_TRUTH, t, &sim.cycles[i].truth)?,
        }
        since_flush += 1;
        let _ = since_flush;
    }
    w.finish()?;
    Ok(())
}

fn cmd_simulate(
    scenario: &str,
    out: &Path,
    plan: Option<&str>,
    days: Option<usize>,
) -> Result<ExitCode> {
    let (mut scn, k, plan) = load_scenario(scenario, plan)?;
    if let Some(d) = days {
        anyhow::ensure!(d >= 1, "--days takes 1 or more");
        scn = scn.repeated_days(d);
    }
    // A scenario that lists no cycles gets the service's schedule: warm-up and after
    // spindle stops, never while cutting.
    if scn.cycle_times_min().is_empty() {
        scn.cycles.at_min = driftwatch_lab::strategies::scheduled_cycles(
            &scn,
            &plan,
            &driftwatch_machine::scheduler::SchedulePolicy::default(),
        );
    }
    let sim = simulate(&scn, &k, &plan)?;
    let dets = sim.detection_stream();
    let mut checks = CycleChecks::new(&k);
    checks.expected = Some(driftwatch_core::cycle::plan_measurements(&plan));
    let (outcomes, _) = driftwatch_core::cycle::process_all(&k, &dets, &checks);
    write_recording(out, &sim, &outcomes)?;
    let ok = outcomes.iter().filter(|o| o.is_ok()).count();
    outln!(
        "wrote {}: scenario '{}', {} cycles ({} ok), {} detections, {:.0} min",
        out.display(),
        scn.name,
        outcomes.len(),
        ok,
        dets.len(),
        scn.duration_min
    );
    Ok(ExitCode::SUCCESS)
}

fn cmd_solve(
    machine: &str,
    path: &Path,
    json: bool,
    plan: Option<&str>,
    recover: bool,
    relations: bool,
    args: &SolverArgs,
) -> Result<ExitCode> {
    let k = Kinematics::load(machine)?;
    let recording = read_file(
        path,
        &ReadOptions {
            recover_truncated: recover,
            ..Default::default()
        },
    )?;
    if let Some(t) = &recording.truncated {
        eprintln!("warning: {}: {t}", path.display());
    }
    if let Some(info) = &recording.info
        && info.kinematics != k.name
    {
        bail!(
            "{} was recorded on machine kinematics '{}', but --machine is '{}'",
            path.display(),
            info.kinematics,
            k.name
        );
    }
    for p in &recording.problems {
        eprintln!("warning: {}: {p}", path.display());
    }
    let mut checks = checks(&k, args)?;
    let (groups, unassigned) = group_by_cycle(&recording.detections);
    for p in &unassigned.problems {
        eprintln!("warning: {}: {p}", path.display());
    }
    if let Some(plan) = plan {
        let p = Plan::build(&k, &PlanConfig::load(plan)?)?;
        checks.expected = Some(driftwatch_core::cycle::plan_measurements(&p));
    } else if let Some((expected, n)) = infer_expected(&groups) {
        if !json {
            outln!(
                "expected measurements: the {} (pose, approach, feed) shared by {n} of {} cycles",
                expected.values().sum::<usize>(),
                groups.len()
            );
        }
        checks.expected = Some(expected);
    }
    if groups.is_empty() {
        bail!("{} has no /probe/detection messages", path.display());
    }
    let limits =
        driftwatch_service::config::ServiceConfig::load(args.config.as_deref())?.validation;
    let names = k.identify_names();
    if !json {
        out!(
            "{:>5} {:>30} {:>8}",
            "cycle",
            "reference time (UTC)",
            "status"
        );
        for n in &names {
            out!(" {:>18}", n);
        }
        outln!(" {:>8} {:>6} {:>6}", "rms/um", "chi2", "point");
    }
    // Each result is judged as the service would judge it: against the set the cycles before
    // it would have made, at the time its cycle closed.
    let layout = driftwatch_machine::nc_offsets::NcLayout::of(&k);
    let mut served = None;
    let mut rejected = 0;
    for (c, entries) in &groups {
        let o = process_cycle(&k, *c, entries, &checks);
        let closed_ns = entries.iter().map(|e| e.t_ns).max().unwrap_or(o.t_ref_ns);
        // Offline there are no predicted sets: the served set is the last measured one.
        let (result, set) = driftwatch_machine::compensation::admit(
            o.message(),
            served.as_ref(),
            served.as_ref(),
            &limits,
            closed_ns,
            &layout,
        );
        if let Some(a) = set {
            served = Some(a.measured);
        } else {
            rejected += 1;
        }
        if json {
            outln!("{}", serde_json::to_string(&result)?);
            continue;
        }
        let t = chrono::DateTime::from_timestamp_nanos(result.t_ns).format("%Y-%m-%d %H:%M:%S%.3f");
        let status = if result.status == rec::ResultStatus::Ok {
            "ok"
        } else {
            "rejected"
        };
        match &o.solution {
            Some(s) => {
                out!("{:>5} {:>30} {:>8}", c, t, status);
                for e in &s.errors {
                    out!(" {:>18}", format!("{:.2}+-{:.2}", e.value, e.sigma));
                }
                let point = result
                    .chi2_point
                    .map_or("-".to_string(), |p| format!("{p:.2}"));
                outln!(" {:>8.3} {:>6.2} {:>6}", s.residual_rms_um(), s.chi2, point);
                if let Some(r) = &result.reason {
                    outln!("{:>5} refused: {r}", "");
                }
                if relations {
                    print_relations(&k, entries, s)?;
                }
            }
            None => outln!(
                "{:>5} {:>30} {:>8} {}",
                c,
                t,
                status,
                result.reason.clone().unwrap_or_default()
            ),
        }
        for n in &o.notes {
            outln!("{:>5} note: {n}", "");
        }
    }
    if !json {
        outln!(
            "{} cycles, {} rejected (by the checks of the detections, the solve or the service's \
             validation); errors in um and urad (apparent, tool-relative)",
            groups.len(),
            rejected
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// One cycle's estimate from the patent's first-order relations, and its difference from
/// the exact solve `s`, under the cycle's row.
fn print_relations(
    k: &Kinematics,
    entries: &[rec::Timed<Result<rec::DetectionMsg, rec::DetectionIssue>>],
    s: &driftwatch_core::identify::Solution,
) -> Result<()> {
    let obs: Vec<Observation> = entries
        .iter()
        .filter_map(|e| e.msg.as_ref().ok().map(|m| (e.t_ns, m)))
        .filter(|(_, m)| m.status() == rec::DetectionStatus::Ok)
        .map(|(t, m)| driftwatch_core::cycle::observation(k, t, m))
        .collect();
    match driftwatch_core::patent_relations::estimate(k, &obs) {
        Ok(f) => {
            out!("{:>5} {:>39}", "", "first order (minus exact):");
            for e in &s.errors {
                let v = f.errors.get(&e.name).copied().unwrap_or(f64::NAN);
                out!(" {:>18}", format!("{v:.2} ({:+.2})", v - e.value));
            }
            outln!();
        }
        Err(e) => outln!("{:>5} first-order relations: {e}", ""),
    }
    Ok(())
}

fn cmd_experiment(scenario: &str, out_dir: &Path) -> Result<ExitCode> {
    let (scn, k, plan) = load_scenario(scenario, None)?;
    let mut checks = CycleChecks::new(&k);
    checks.expected = Some(driftwatch_core::cycle::plan_measurements(&plan));
    let stop = scn
        .spindle
        .iter()
        .find(|s| s.rpm == 0.0 && s.at_min > 0.0)
        .map(|s| s.at_min)
        .unwrap_or(scn.duration_min);
    let ex = experiment::run(&scn, &k, &plan, &checks, stop)?;
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    outln!(
        "scenario '{}': {} on {}, plan '{}' ({} approaches, {:.1} s machine time), seed {}",
        scn.name,
        scn.description,
        k.name,
        plan.name,
        plan.steps.len(),
        plan.machine_time_s,
        scn.seed
    );
    out!("{}", ex.table());
    let s = &ex.summary;
    outln!(
        "{} rise over 0..{stop:.0} min: {:.1} um (the patent's EZ0B: about 80); drop in 30 min after the stop: {:.1} um (about 45)",
        s.main,
        s.main_rise_um,
        s.main_drop_um
    );
    outln!(
        "{} rise: {:.1} um (the patent's EX0B: about 20)",
        s.second,
        s.second_rise_um
    );
    outln!(
        "largest |identified - truth| / sigma: {:.2} over {} values; {} of {} cycles ok",
        s.max_abs_z,
        ex.rows.iter().map(|r| r.values.len()).sum::<usize>(),
        s.cycles_ok,
        s.cycles
    );
    let csv = out_dir.join("patent_experiment.csv");
    let file =
        std::fs::File::create(&csv).with_context(|| format!("creating {}", csv.display()))?;
    ex.write_csv(std::io::BufWriter::new(file))
        .with_context(|| format!("writing {}", csv.display()))?;
    let svg = out_dir.join("patent_experiment.svg");
    let plot = ex
        .svg(&format!(
            "patent experiment on {}: identified (2 sigma) vs truth",
            k.name
        ))
        .map_err(|e| anyhow::anyhow!("plotting: {e}"))?;
    std::fs::write(&svg, plot).with_context(|| format!("writing {}", svg.display()))?;
    let mcap = out_dir.join("patent_experiment.mcap");
    write_recording(&mcap, &ex.simulation, &ex.outcomes)?;
    let summary = out_dir.join("summary.json");
    std::fs::write(&summary, serde_json::to_string_pretty(&ex.summary)?)?;
    outln!(
        "wrote {}, {}, {}, {}",
        csv.display(),
        svg.display(),
        mcap.display(),
        summary.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn template(k: &Kinematics, plan: &Plan) -> Result<Vec<Observation>> {
    Ok(plan.observations(k, &k.nominal_state())?)
}

fn cmd_plan(
    machine: &str,
    plan: Option<&str>,
    sigma: Option<f64>,
    drift_rates: bool,
) -> Result<ExitCode> {
    let k = Kinematics::load(machine)?;
    let plan = Plan::build(&k, &PlanConfig::load(plan.unwrap_or(&k.config.plan))?)?;
    outln!("plan '{}': {}", plan.name, plan.description);
    outln!(
        "{:>8} {:>7} {:>9} {:>9} {:>9} {:>8} {:>8}  {}",
        "t/s",
        "dur/s",
        "x/mm",
        "y/mm",
        "z/mm",
        format!("{}/deg", k.rotary.first().map_or("-", |a| a.name.as_str())),
        format!("{}/deg", k.rotary.get(1).map_or("-", |a| a.name.as_str())),
        "move"
    );
    for m in &plan.moves {
        outln!(
            "{:>8.2} {:>7.2} {:>9.3} {:>9.3} {:>9.3} {:>8.1} {:>8.1}  {:?} {}",
            m.t_start_s,
            m.duration_s,
            m.to[0],
            m.to[1],
            m.to[2],
            m.angles_deg[0],
            m.angles_deg[1],
            m.kind,
            m.note
        );
    }
    outln!(
        "{} approaches; machine time {:.1} s (rapid {} mm/min, probing {} mm/min, clearance {} mm, dwell {} s, {} {} deg/min, {} {} deg/min, clamp {} s)",
        plan.steps.len(),
        plan.machine_time_s,
        k.motion.rapid_mm_min,
        plan.config.feed_mm_min,
        plan.config.clearance_mm,
        plan.config.dwell_s,
        k.rotary[0].name,
        k.rotary[0].speed_deg_min,
        k.rotary.get(1).map_or("-", |a| a.name.as_str()),
        k.rotary.get(1).map(|a| a.speed_deg_min).unwrap_or(0.0),
        k.motion.clamp_s
    );
    let sigma = sigma.unwrap_or(k.setter.sigma_um);
    let mut opts = SolveOptions::new(sigma);
    if drift_rates {
        opts = opts.with_drift_rates();
    }
    let obs = template(&k, &plan)?;
    let id = Identifier::new(&k, &obs, &opts)?;
    outln!("Cramer-Rao standard deviations at sigma = {sigma} um:");
    for e in id.cramer_rao(&obs)? {
        outln!("  {:>28} {:>9.3} {}", e.name, e.sigma, e.unit);
    }
    Ok(ExitCode::SUCCESS)
}

fn cmd_bench_solve(machine: &str, plan: Option<&str>, n: usize) -> Result<ExitCode> {
    let k = Kinematics::load(machine)?;
    let cfg = match plan {
        Some(p) => PlanConfig::load(p)?,
        None => {
            let mut cfg = PlanConfig::load(&k.config.plan)?;
            cfg.order = driftwatch_core::plan::Order::AsListed;
            cfg
        }
    };
    let plan = Plan::build(&k, &cfg)?;
    let obs = template(&k, &plan)?;
    let opts = SolveOptions::new(k.setter.sigma_um);
    let id = Identifier::new(&k, &obs, &opts)?;
    // Distinct noisy cycles, made before timing.
    let cycles: Vec<Vec<Observation>> = (0..n.min(1000))
        .map(|i| {
            obs.iter()
                .enumerate()
                .map(|(j, o)| {
                    let mut o = o.clone();
                    let a = o.approach.axis.index();
                    let h = ((i * 7919 + j * 104729) % 1000) as f64 / 1000.0 - 0.5;
                    o.position[a] += h * 1e-3;
                    o
                })
                .collect()
        })
        .collect();
    let t = Instant::now();
    let mut sum = 0.0;
    for i in 0..n {
        let s = id.solve(&cycles[i % cycles.len()])?;
        sum += s.errors[0].value;
    }
    let dt = t.elapsed().as_secs_f64();
    outln!(
        "{} solves of the {}-detection plan '{}' ({}) on machine '{}' in {:.3} s on one thread: {:.0} solves/s (checksum {:.3})",
        n,
        obs.len(),
        plan.name,
        match plan.config.order {
            driftwatch_core::plan::Order::AsListed => "as listed",
            driftwatch_core::plan::Order::TimeSymmetric => "time-symmetric",
        },
        k.name,
        dt,
        n as f64 / dt,
        sum
    );
    Ok(ExitCode::SUCCESS)
}

/// A single-threaded async runtime for a command that only waits on the network.
fn current_thread() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}
