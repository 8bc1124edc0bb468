//! `driftwatch rtest simulate|process|identify` and `driftwatch import rtest-csv`: the R-test
//! (seed 002) from the command line. The library (`driftwatch-rtest`) computes; this reads
//! and writes the files.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Subcommand, ValueEnum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::recording::{MachineInfo, TOPIC_INFO};
use driftwatch_recording::mcap_io::{ReadOptions, RecordingWriter, read_file};
use driftwatch_rtest::identify::{Identification, Options, identify};
use driftwatch_rtest::instrument::{Calibration, Imperfections, Instrument, Setting, calibrate};
use driftwatch_rtest::kinematic_test::{Run, Setup, TestKind, TestSpec, simulate};
use driftwatch_rtest::process::{Processed, process};
use driftwatch_rtest::recording::{
    TOPIC_READING, TOPIC_SETUP, from_csv, from_messages, to_messages,
};
use driftwatch_rtest::report;

#[derive(Clone, Copy, ValueEnum)]
pub enum SettingArg {
    /// Nest on the table, sensors inclined (ETH Zurich / FIDIA), ball on the spindle.
    E,
    /// Nest on the table, sensors along X, Y, Z, ball on the spindle.
    J,
    /// The E nest on the spindle (IBS style), ball on the table.
    Es,
}

impl From<SettingArg> for Setting {
    fn from(s: SettingArg) -> Setting {
        match s {
            SettingArg::E => Setting::E,
            SettingArg::J => Setting::J,
            SettingArg::Es => Setting::Es,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub enum TestArg {
    Bk1,
    Bk2,
    Xyc,
}

impl From<TestArg> for TestKind {
    fn from(t: TestArg) -> TestKind {
        match t {
            TestArg::Bk1 => TestKind::Bk1,
            TestArg::Bk2 => TestKind::Bk2,
            TestArg::Xyc => TestKind::Xyc,
        }
    }
}

#[derive(Subcommand)]
pub enum RtestCmd {
    /// Run BK1, BK2 and XYC with a simulated R-test on a virtual machine with the location
    /// errors given, and write the readings as a recording (`/rtest/setup`, `/rtest/reading`).
    Simulate(SimulateArgs),
    /// Readings -> radial, axial and tangential deviations and the ISO-style figures of each
    /// test; optionally the HTML report with the plots.
    Process(FromArgs),
    /// Location errors (apparent, relative to the spindle-side object) by least squares with
    /// uncertainties, and what these tests cannot separate.
    Identify(IdentifyArgs),
    /// Tool setter and R-test on the same drifting virtual machine through a scenario: at each
    /// cycle time a setter cycle, the R-test, a setter cycle; the setter moved to the R-test's
    /// time by the thermal model; the six errors compared with their combined uncertainty.
    Crosscheck(CrosscheckArgs),
}

#[derive(clap::Args)]
pub struct CrosscheckArgs {
    /// A built-in scenario or a scenario TOML.
    #[arg(long, default_value = "patent")]
    scenario: String,
    #[arg(long, value_enum, default_value = "e")]
    setting: SettingArg,
    /// R-test tests of each session.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "bk1,xyc")]
    tests: Vec<TestArg>,
    /// Agreement bound, combined standard uncertainties.
    #[arg(long, default_value_t = 2.0)]
    k: f64,
    #[arg(long, default_value_t = 18)]
    seed: u64,
    /// Print the whole comparison as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
pub struct SimulateArgs {
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c,
    /// head_d45_table_c, trunnion_ac).
    #[arg(long, default_value = "table_bc")]
    machine: String,
    #[arg(long, value_enum, default_value = "e")]
    setting: SettingArg,
    /// Tests to run, in order.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "bk1,bk2,xyc")]
    tests: Vec<TestArg>,
    /// A location error of the virtual machine, NAME=VALUE (um or urad); repeatable.
    #[arg(long = "error", value_name = "NAME=VALUE")]
    errors: Vec<String>,
    /// The device as designed: no misalignment, no gain error, a perfect ball.
    #[arg(long)]
    ideal: bool,
    /// Process with the design transform instead of a calibration motion.
    #[arg(long)]
    uncalibrated: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Where to write the recording.
    #[arg(long, default_value = "rtest.mcap")]
    out: PathBuf,
}

#[derive(clap::Args)]
pub struct FromArgs {
    /// A recording with R-test runs.
    #[arg(long)]
    from: PathBuf,
    /// Machine TOML or built-in name; default: the recording's `/machine/info` kinematics.
    #[arg(long)]
    machine: Option<String>,
    /// Write the HTML report (plots, figures) here.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct IdentifyArgs {
    #[command(flatten)]
    from: FromArgs,
    /// Errors to estimate (comma-separated); default the machine's identified six. `all`:
    /// every location error of the machine (what the tests cannot separate is named).
    #[arg(long, value_delimiter = ',')]
    errors: Vec<String>,
    /// Standard uncertainty of the spindle-side object's calibration (ball or nest centre
    /// against the tool reference point), um per axis.
    #[arg(long, default_value_t = 0.5)]
    head_sigma_um: f64,
    /// Estimate the drifts while the tests ran (the ball's, linear and quadratic; each
    /// error's, linear): for a machine that is warming or cooling.
    #[arg(long)]
    drift: bool,
    /// Write the result as a reference measurement (the body of
    /// `POST /api/v1/machines/{id}/verifications`) here.
    #[arg(long)]
    reference: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct ImportArgs {
    /// The device's export: a header, then `angle_deg,u_um,v_um,w_um` and optionally
    /// `x_mm,y_mm,z_mm` (commanded) and `t_s` per row.
    #[arg(long)]
    csv: PathBuf,
    #[arg(long)]
    machine: String,
    #[arg(long, value_enum)]
    test: TestArg,
    #[arg(long, value_enum)]
    setting: SettingArg,
    /// Programmed centre of the table-side object, table frame, mm (x,y,z); default the
    /// test's default for the machine.
    #[arg(long, value_delimiter = ',', num_args = 3)]
    ball_mm: Option<Vec<f64>>,
    /// Angle of another rotary axis held during the test, NAME=DEG (e.g. B=-45); repeatable.
    #[arg(long = "hold", value_name = "NAME=DEG")]
    hold: Vec<String>,
    /// The device's sensitivity (a JSON file of the calibration, as `rtest simulate` records
    /// it); default the setting's design transform with +-0.5 deg misalignment.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Reading standard uncertainty, um (with the design transform).
    #[arg(long, default_value_t = 0.05)]
    reading_sigma_um: f64,
    /// Start time of the readings (RFC 3339), for the reference time.
    #[arg(long, default_value = "2026-01-01T00:00:00Z")]
    start: String,
    #[arg(long)]
    out: PathBuf,
}

fn assignment(s: &str) -> Result<(String, f64)> {
    let (n, v) = s
        .split_once('=')
        .with_context(|| format!("'{s}' is not NAME=VALUE"))?;
    let v: f64 = v
        .trim()
        .parse()
        .with_context(|| format!("'{v}' in '{s}' is not a number"))?;
    if !v.is_finite() {
        bail!("'{s}': the value is not finite");
    }
    Ok((n.trim().to_string(), v))
}

pub fn cmd_rtest(cmd: RtestCmd) -> Result<()> {
    match cmd {
        RtestCmd::Simulate(a) => cmd_simulate(a),
        RtestCmd::Process(a) => {
            let (k, runs) = load(&a)?;
            let processed = process_all(&k, &runs)?;
            print_figures(&processed);
            write_report(a.report.as_deref(), &k, &processed, None)
        }
        RtestCmd::Identify(a) => cmd_identify(a),
        RtestCmd::Crosscheck(a) => cmd_crosscheck(a),
    }
}

fn cmd_crosscheck(a: CrosscheckArgs) -> Result<()> {
    use driftwatch_core::plan::{Plan, PlanConfig};
    use driftwatch_lab::rtest_crosscheck::{CrossOptions, run};
    let scn = driftwatch_sim::scenario::Scenario::load(&a.scenario)
        .with_context(|| format!("scenario '{}'", a.scenario))?;
    let k = Kinematics::load(&scn.machine).with_context(|| format!("machine '{}'", scn.machine))?;
    let plan = Plan::build(&k, &PlanConfig::load(&scn.plan)?)?;
    let opts = CrossOptions {
        setting: a.setting.into(),
        tests: a.tests.iter().map(|&t| t.into()).collect(),
        k: a.k,
        seed: a.seed,
        ..CrossOptions::default()
    };
    let c = run(&k, &scn, &plan, &opts)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&c)?);
        return Ok(());
    }
    for s in &c.sessions {
        println!(
            "{:5.0} min: setter {:.1} and {:.1}, R-test {:.1} min",
            s.t_min, s.setter_min[0], s.setter_min[1], s.rtest_min
        );
        for (n, e) in &s.errors {
            println!(
                "  {n:<5} setter {:>9.3} -> {:>9.3} +- {:.3}  R-test {:>9.3} +- {:.3}  diff {:>+7.3} (z {:>+5.2})",
                e.setter,
                e.setter_at_rtest,
                e.setter_at_rtest_sigma,
                e.rtest,
                e.rtest_sigma,
                e.difference,
                e.z
            );
        }
    }
    println!(
        "beyond {} combined sigma: {} of {} (largest |z| {:.2}, RMS z {:.2}); the setter's nearest cycle as it is: {} (RMS z {:.2}); its two cycles interpolated linearly: {} (RMS z {:.2})",
        c.k,
        c.beyond,
        c.total,
        c.max_abs_z,
        c.rms_z,
        c.beyond_without_transfer,
        c.rms_z_without_transfer,
        c.beyond_interpolated,
        c.rms_z_interpolated
    );
    println!(
        "sessions whose errors disagree jointly (sum of z^2 beyond the chi-square point of the same coverage): {} of {}",
        c.sessions_beyond_joint,
        c.sessions.len()
    );
    Ok(())
}

fn cmd_simulate(a: SimulateArgs) -> Result<()> {
    let k = Kinematics::load(&a.machine).with_context(|| format!("machine '{}'", a.machine))?;
    let mut truth = k.nominal_state();
    for e in &a.errors {
        let (name, v) = assignment(e)?;
        let id = k
            .error_id(&name)
            .with_context(|| format!("{} has no location error {name}", k.name))?;
        truth.loc[id.axis][id.slot] += v * id.scale();
    }
    let setting: Setting = a.setting.into();
    let mut rng = ChaCha8Rng::seed_from_u64(a.seed);
    let imp = if a.ideal {
        Imperfections::none()
    } else {
        Imperfections::seed()
    };
    let inst = Instrument::drawn(setting, &imp, &mut rng);
    let cal = if a.uncalibrated {
        Calibration::design(
            setting,
            inst.reading_sigma_um(),
            imp.stem_deg.max(imp.face_deg),
            imp.sphericity_um,
        )
    } else {
        calibrate(&inst, 0.05, 3, 0.0, imp.sphericity_um, &mut rng)?
    };
    let start_ns = chrono::DateTime::parse_from_rfc3339("2026-01-01T08:00:00Z")
        .map(|t| t.timestamp_nanos_opt().unwrap_or(0))
        .unwrap_or(0);
    let mut w = RecordingWriter::create_file(&a.out)
        .with_context(|| format!("creating {}", a.out.display()))?;
    w.write(
        TOPIC_INFO,
        start_ns,
        &MachineInfo {
            machine_id: "rtest-sim".into(),
            kinematics: k.name.clone(),
            software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        },
    )?;
    let mut t = start_ns;
    for (n, kind) in a.tests.iter().enumerate() {
        let spec = TestSpec::default_for(&k, (*kind).into())?;
        let run = simulate(
            &k,
            &spec,
            &inst,
            &mut |_, _| truth,
            t,
            &Setup::default(),
            &mut rng,
        )?;
        let (setup, readings) = to_messages(&k, &run, &cal, n as i64 + 1);
        w.write(TOPIC_SETUP, t, &setup)?;
        for (ts, m) in &readings {
            w.write(TOPIC_READING, *ts, m)?;
        }
        t = readings.last().map_or(t, |r| r.0) + 60_000_000_000;
        println!(
            "{} ({} setting): {} readings, turning {}",
            spec.kind.name(),
            setting.name(),
            run.points.len(),
            k.rotary[spec.axis].name
        );
    }
    w.finish()?;
    println!("wrote {} ({})", a.out.display(), cal.source);
    Ok(())
}

fn load(a: &FromArgs) -> Result<(Kinematics, Vec<(Run, Calibration)>)> {
    let rec = read_file(
        &a.from,
        &ReadOptions {
            keep_raw: true,
            ..Default::default()
        },
    )
    .with_context(|| format!("reading {}", a.from.display()))?;
    let name = match (&a.machine, &rec.info) {
        (Some(m), _) => m.clone(),
        (None, Some(info)) => info.kinematics.clone(),
        (None, None) => bail!(
            "{} has no /machine/info: say which machine with --machine",
            a.from.display()
        ),
    };
    let k = Kinematics::load(&name).with_context(|| format!("machine '{name}'"))?;
    let messages: Vec<(String, i64, Vec<u8>)> = rec
        .raw
        .into_iter()
        .map(|m| (m.topic, m.t_ns, m.data))
        .collect();
    let runs = from_messages(&k, &messages).with_context(|| format!("{}", a.from.display()))?;
    Ok((k, runs))
}

fn process_all(k: &Kinematics, runs: &[(Run, Calibration)]) -> Result<Vec<Processed>> {
    runs.iter()
        .map(|(r, c)| process(k, r, c).with_context(|| format!("{} run", r.spec.kind.name())))
        .collect()
}

fn print_figures(processed: &[Processed]) {
    println!(
        "{:<5} {:<3} {:<4} {:<11} {:>9} {:>9} {:>10} {:>9}",
        "test", "set", "axis", "direction", "range", "max|dev|", "1/rev", "reversal"
    );
    for p in processed {
        for (name, f) in [
            ("radial", &p.radial),
            ("axial", &p.axial),
            ("tangential", &p.tangential),
        ] {
            let opt = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.3}"));
            println!(
                "{:<5} {:<3} {:<4} {:<11} {:>9.3} {:>9.3} {:>10} {:>9}",
                p.test,
                p.setting.name(),
                p.axis,
                name,
                f.range_um,
                f.max_abs_um,
                opt(f.first_harmonic_um),
                opt(f.reversal_um)
            );
        }
    }
    println!("(um; 1/rev: the once-per-revolution amplitude over sweeps of 180 deg or more)");
}

fn write_report(
    path: Option<&Path>,
    k: &Kinematics,
    processed: &[Processed],
    id: Option<&Identification>,
) -> Result<()> {
    if let Some(p) = path {
        std::fs::write(p, report::html(&k.name, processed, id))
            .with_context(|| format!("writing {}", p.display()))?;
        println!("report: {}", p.display());
    }
    Ok(())
}

fn cmd_identify(a: IdentifyArgs) -> Result<()> {
    let (k, runs) = load(&a.from)?;
    let processed = process_all(&k, &runs)?;
    let errors = if a.errors.iter().any(|e| e == "all") {
        driftwatch_rtest::identify::all_errors(&k)
    } else {
        a.errors.clone()
    };
    if !(a.head_sigma_um.is_finite() && a.head_sigma_um > 0.0) {
        bail!("--head-sigma-um must be positive");
    }
    let id = identify(
        &k,
        &processed,
        &Options {
            errors,
            head_sigma_um: a.head_sigma_um,
            drift_rates: a.drift,
        },
    )?;
    println!("{:<18} {:>10} {:>8} unit", "error", "value", "u(k=1)");
    for (n, e) in &id.errors {
        println!("{n:<18} {:>10.3} {:>8.3} {}", e.value, e.sigma, e.unit);
    }
    let t = &id.table_object_um;
    println!(
        "table-side object off its programmed centre: ({:.2}, {:.2}, {:.2}) um",
        t[0].value, t[1].value, t[2].value
    );
    println!(
        "{} readings, chi-square {:.1} on {} dof (Birge {:.2}), residual RMS {:.3} um",
        id.n_readings, id.chi2, id.dof, id.birge, id.residual_rms_um
    );
    for n in &id.not_identifiable {
        println!("not identifiable: {n}");
    }
    if let Some(p) = &a.reference {
        std::fs::write(
            p,
            serde_json::to_string_pretty(&id.reference_json(&k.identify_names()))?,
        )
        .with_context(|| format!("writing {}", p.display()))?;
        println!("reference measurement: {}", p.display());
    }
    write_report(a.from.report.as_deref(), &k, &processed, Some(&id))
}

pub fn cmd_import(a: ImportArgs) -> Result<()> {
    let k = Kinematics::load(&a.machine).with_context(|| format!("machine '{}'", a.machine))?;
    let setting: Setting = a.setting.into();
    let mut spec = TestSpec::default_for(&k, a.test.into())?;
    if let Some(b) = &a.ball_mm {
        spec.ball_mm = Vec3::new(b[0], b[1], b[2]);
    }
    for h in &a.hold {
        let (name, v) = assignment(h)?;
        let i = k
            .rotary
            .iter()
            .position(|ax| ax.name == name)
            .with_context(|| format!("{} has no rotary axis {name}", k.name))?;
        spec.fixed_deg[i] = v;
    }
    let cal = match &a.calibration {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            serde_json::from_str::<Calibration>(&text)
                .with_context(|| format!("{} is not a calibration", p.display()))?
        }
        None => Calibration::design(setting, a.reading_sigma_um, 0.5, 0.13),
    };
    if cal.setting != setting {
        bail!(
            "the calibration is for the {} setting, the export for {}",
            cal.setting.name(),
            setting.name()
        );
    }
    let start_ns = chrono::DateTime::parse_from_rfc3339(&a.start)
        .with_context(|| format!("--start '{}'", a.start))?
        .timestamp_nanos_opt()
        .context("--start out of range")?;
    let text =
        std::fs::read_to_string(&a.csv).with_context(|| format!("reading {}", a.csv.display()))?;
    let run = from_csv(&text, &spec, setting, start_ns)
        .with_context(|| format!("{}", a.csv.display()))?;
    let mut w = RecordingWriter::create_file(&a.out)
        .with_context(|| format!("creating {}", a.out.display()))?;
    w.write(
        TOPIC_INFO,
        start_ns,
        &MachineInfo {
            machine_id: "rtest-import".into(),
            kinematics: k.name.clone(),
            software: format!("driftwatch {}", env!("CARGO_PKG_VERSION")),
        },
    )?;
    let (setup, readings) = to_messages(&k, &run, &cal, 1);
    w.write(TOPIC_SETUP, start_ns, &setup)?;
    for (t, m) in &readings {
        w.write(TOPIC_READING, *t, m)?;
    }
    w.finish()?;
    println!(
        "{}: {} readings of {} ({} setting) -> {}",
        a.csv.display(),
        readings.len(),
        spec.kind.name(),
        setting.name(),
        a.out.display()
    );
    Ok(())
}
