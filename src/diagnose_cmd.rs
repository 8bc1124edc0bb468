//! `driftwatch diagnose`: the diagnosis of recordings, written as `diagnosis.json` and
//! `report.html`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use driftwatch::diagnosis::{DiagnoseOptions, Diagnosis, Inputs, detection_rows, diagnose};
use driftwatch::effects::{EFFECTS, Effect};
use driftwatch::identify::SolveOptions;
use driftwatch::kinematics::Kinematics;
use driftwatch::recording::mcap_io::{ReadOptions, read_file};
use driftwatch::thermal_model::ThermalModel;

#[derive(clap::Args)]
pub struct DiagnoseArgs {
    /// Machine TOML, or a built-in name (table_bc).
    #[arg(long, required_unless_present = "list_effects")]
    machine: Option<String>,
    /// Recordings of that machine (one or more, e.g. one per day).
    #[arg(long, num_args = 1.., required_unless_present = "list_effects")]
    recording: Vec<PathBuf>,
    /// A fitted thermal model (`driftwatch fit`): its heat input (n_ref, gamma) drives the
    /// baseline.
    #[arg(long)]
    model: Option<PathBuf>,
    /// Where diagnosis.json and report.html go.
    #[arg(long, default_value = "out/diagnosis")]
    out: PathBuf,
    /// One-reading standard uncertainty, um (default: the machine's).
    #[arg(long)]
    sigma_um: Option<f64>,
    /// List the candidate effects and exit.
    #[arg(long)]
    list_effects: bool,
    /// With --list-effects: print JSON.
    #[arg(long)]
    json: bool,
}

/// `diagnosis.json`: what was read and the diagnosis.
#[derive(Serialize)]
pub struct DiagnosisFile<'a> {
    pub format: &'static str,
    pub machine: String,
    pub recordings: Vec<String>,
    /// Detections that could not be parsed (not used).
    pub unparsed_detections: usize,
    pub options: &'a DiagnoseOptions,
    #[serde(flatten)]
    pub diagnosis: &'a Diagnosis,
}

pub const DIAGNOSIS_FORMAT: &str = "driftwatch-diagnosis/1";

fn list(json: bool) -> Result<ExitCode> {
    if json {
        println!("{}", serde_json::to_string_pretty(EFFECTS)?);
        return Ok(ExitCode::SUCCESS);
    }
    for Effect {
        id,
        label,
        physics,
        signature,
        shapes,
        parameters,
        split_by,
        ..
    } in EFFECTS
    {
        println!(
            "{id}: {label}\n  physics:    {physics}\n  signature:  {signature}\n  shapes:     {shapes}\n  parameters: {parameters}\n  split by:   {split_by}\n"
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Run the diagnosis on already-read inputs.
pub fn run(
    k: &Kinematics,
    inputs: &Inputs,
    opts: &DiagnoseOptions,
) -> Result<Diagnosis, driftwatch::diagnosis::DiagnosisError> {
    let rows = detection_rows(k, &inputs.detections, &SolveOptions::new(opts.sigma_um))?;
    diagnose(&rows, &inputs.spindle, &inputs.temperatures, opts)
}

pub fn cmd_diagnose(a: DiagnoseArgs) -> Result<ExitCode> {
    if a.list_effects {
        return list(a.json);
    }
    let machine = a.machine.context("--machine is required")?;
    let k = Kinematics::load(&machine).with_context(|| format!("machine '{machine}'"))?;
    let mut inputs: Option<Inputs> = None;
    for path in &a.recording {
        let rec = read_file(path, &ReadOptions::default())
            .with_context(|| format!("reading {}", path.display()))?;
        let i = Inputs::of(&rec);
        match inputs.as_mut() {
            Some(all) => all.extend(i),
            None => inputs = Some(i),
        }
    }
    let Some(inputs) = inputs else {
        bail!("no --recording given");
    };
    if inputs.detections.is_empty() {
        bail!("the recordings hold no parseable /probe/detection message");
    }
    let mut opts = DiagnoseOptions::new(a.sigma_um.unwrap_or(k.setter.sigma_um));
    if let Some(path) = &a.model {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let m = ThermalModel::from_json(&text)
            .with_context(|| format!("thermal model {}", path.display()))?;
        opts.model.n_ref_rpm = m.config.n_ref_rpm;
        opts.model.gamma = m.config.gamma;
    }
    let d = run(&k, &inputs, &opts).context("diagnosis")?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let file = DiagnosisFile {
        format: DIAGNOSIS_FORMAT,
        machine: machine.clone(),
        recordings: a
            .recording
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        unparsed_detections: inputs.unparsed,
        options: &opts,
        diagnosis: &d,
    };
    let json_path = a.out.join("diagnosis.json");
    std::fs::write(&json_path, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", json_path.display()))?;
    let html_path = a.out.join("report.html");
    let title = format!("driftwatch diagnosis: {machine}");
    std::fs::write(&html_path, driftwatch::diagnosis_report::html(&d, &title))
        .with_context(|| format!("writing {}", html_path.display()))?;
    println!(
        "{} readings, {} cycles, {:.1} h; baseline chi2/dof {:.3}, held-out RMS {:.3} um -> {:.3} um",
        d.readings,
        d.cycles,
        d.span_h,
        d.baseline.chi2_dof,
        d.baseline.rms_heldout_um,
        d.final_fit.rms_heldout_um
    );
    for x in &d.accepted {
        println!("found: {}", x.statement);
    }
    for n in &d.not_identifiable {
        println!("not identifiable: {} ({})", n.label, n.reason);
    }
    for u in &d.unexplained {
        println!(
            "unexplained: chi2/dof {:.3}, {:.3} um RMS beyond the noise",
            u.chi2_dof, u.discrepancy_um
        );
    }
    println!("wrote {} and {}", json_path.display(), html_path.display());
    Ok(ExitCode::SUCCESS)
}
