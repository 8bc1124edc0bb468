//! `driftwatch diagnose`: the diagnosis of recordings, written as `diagnosis.json` and
//! `report.html`.

use driftwatch_core::units;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::linear_axes::LinearGeometry;
use driftwatch_core::recording::Recording;
use driftwatch_diagnosis::cycles::{DiagnoseOptions, Diagnosis, Inputs, diagnose_inputs};
use driftwatch_diagnosis::displacement::{
    DisplacementDiagnosis, DisplacementOptions, diagnose_displacements,
};
use driftwatch_diagnosis::effects::{EFFECTS, Effect};
use driftwatch_recording::mcap_io::{ReadOptions, read_file};
use driftwatch_thermal::model::ThermalModel;
use driftwatch_thermal::model::{Event, ModelConfig, ModelInput, events_from};

#[derive(clap::Args)]
pub struct DiagnoseArgs {
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c, head_d45_table_c, trunnion_ac); needed for recordings of measurement
    /// cycles, not for displacement recordings.
    #[arg(long)]
    machine: Option<String>,
    /// Recordings of that machine (one or more, e.g. one per day).
    #[arg(long, num_args = 1.., required_unless_present = "list_effects")]
    recording: Vec<PathBuf>,
    /// A fitted thermal model (`driftwatch fit`): its heat input (n_ref, gamma) drives the
    /// baseline.
    #[arg(long)]
    model: Option<PathBuf>,
    /// The machine's measured linear-axis geometry (JSON or TOML, e.g. from `driftwatch
    /// diagonal solve --geometry-out`): the model the readings are compared with.
    #[arg(long)]
    geometry: Option<PathBuf>,
    /// Where diagnosis.json and report.html go.
    #[arg(long, default_value = "out/diagnosis")]
    out: PathBuf,
    /// One-reading standard uncertainty, um (default: the machine's).
    #[arg(long)]
    sigma_um: Option<f64>,
    /// Displacement recordings: the channels to diagnose (default: every displacement channel).
    #[arg(long, num_args = 1..)]
    channels: Vec<String>,
    /// Displacement recordings: hold out the readings from this many hours after the first
    /// (default: the last 15 %).
    #[arg(long)]
    holdout_from_h: Option<f64>,
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

/// A linear-axis geometry file: JSON (`.json`, as the API takes it under `geometry`) or TOML
/// (a machine file's `[linear]` section), checked.
pub fn read_geometry(path: &std::path::Path) -> Result<LinearGeometry> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let g: LinearGeometry = if path.extension().is_some_and(|e| e == "json") {
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
    } else {
        toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?
    };
    g.errors()
        .with_context(|| format!("geometry {}", path.display()))?;
    Ok(g)
}

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

pub fn cmd_diagnose(a: DiagnoseArgs) -> Result<ExitCode> {
    if a.list_effects {
        return list(a.json);
    }
    let mut recs = Vec::new();
    let mut inputs: Option<Inputs> = None;
    for path in &a.recording {
        let rec = read_file(path, &ReadOptions::default())
            .with_context(|| format!("reading {}", path.display()))?;
        let i = Inputs::of(&rec);
        match inputs.as_mut() {
            Some(all) => all.extend(i),
            None => inputs = Some(i),
        }
        recs.push(rec);
    }
    let Some(inputs) = inputs else {
        bail!("no --recording given");
    };
    if inputs.detections.is_empty() {
        if recs.iter().any(|r| !r.displacements.is_empty()) {
            return displacement(&a, &recs);
        }
        bail!(
            "the recordings hold no parseable /probe/detection message and no displacement reading"
        );
    }
    let machine = a
        .machine
        .clone()
        .context("--machine is required for recordings of measurement cycles")?;
    let mut k = Kinematics::load(&machine).with_context(|| format!("machine '{machine}'"))?;
    if let Some(path) = &a.geometry {
        let g = read_geometry(path)?;
        k = k
            .with_geometry(&g, &path.display().to_string())
            .with_context(|| format!("geometry {}", path.display()))?;
    }
    let mut opts = DiagnoseOptions::new(a.sigma_um.unwrap_or(k.setter.sigma_um));
    // The model version the accepted terms extend: the given one's configuration, else the
    // service's default.
    let mut base = ModelConfig::default();
    if let Some(path) = &a.model {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let m = ThermalModel::from_json(&text)
            .with_context(|| format!("thermal model {}", path.display()))?;
        opts.model.n_ref_rpm = m.config.n_ref_rpm;
        opts.model.gamma = m.config.gamma;
        base = m.config;
    }
    let d = diagnose_inputs(&k, &inputs, &opts).context("diagnosis")?;
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
    let title = format!("driftwatch diagnosis: {machine}");
    let (json_path, html_path) = write_report(
        &a.out,
        &file,
        &driftwatch_diagnosis::report::html(&d, &title),
    )?;
    println!(
        "{} readings, {} cycles, {:.1} h; baseline chi2/dof {:.3}, held-out RMS {:.3} um -> {:.3} um",
        d.readings,
        d.cycles,
        d.span_h,
        d.baseline.chi2_dof,
        d.baseline.rms_heldout_um,
        d.final_fit.rms_heldout_um
    );
    if d.baseline.heldout_extrapolates {
        println!(
            "note: the held-out block holds spindle history the training part never saw (under two days of data): its RMS measures extrapolation, not the fit"
        );
    }
    let carried: Vec<ModelInput> = d
        .accepted
        .iter()
        .map(|x| x.model_input.clone())
        .filter(|i| *i != ModelInput::None)
        .collect();
    let model_path = a.out.join("model.json");
    if carried.is_empty() {
        println!("no accepted term the thermal model can carry: no model.json");
    } else {
        println!(
            "{}",
            write_model(
                &base.with_inputs(&carried),
                &events_from(&recs),
                &model_path
            )?
        );
    }
    for x in &d.accepted {
        if x.model_input == ModelInput::None {
            println!(
                "not carried into the thermal model: {} (a measurement-model or clock term; correct it at its source: {})",
                x.term, x.split_by
            );
        }
    }
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
        if let Some(p) = &u.periodic {
            println!("unexplained: {}", p.statement);
        }
    }
    println!("wrote {} and {}", json_path.display(), html_path.display());
    Ok(ExitCode::SUCCESS)
}

pub const DISPLACEMENT_FORMAT: &str = "driftwatch-displacement-diagnosis/1";

/// `diagnosis.json` of displacement recordings.
#[derive(Serialize)]
pub struct DisplacementFile<'a> {
    pub format: &'static str,
    pub recordings: Vec<String>,
    pub options: &'a DisplacementOptions,
    #[serde(flatten)]
    pub diagnosis: &'a DisplacementDiagnosis,
}

/// The diagnosis of displacement recordings (imported thermal tests): `diagnosis.json`,
/// `report.html` and `model.json`, the thermal model refitted with every accepted term it can
/// carry (a model version a machine's `thermal_model` can point at).
fn displacement(a: &DiagnoseArgs, recs: &[Recording]) -> Result<ExitCode> {
    let mut channels: Vec<String> = recs
        .iter()
        .flat_map(|r| r.displacements.iter().map(|m| m.msg.sensor.clone()))
        .collect();
    channels.sort();
    channels.dedup();
    if !a.channels.is_empty() {
        if let Some(c) = a.channels.iter().find(|c| !channels.contains(c)) {
            bail!("channel '{c}' is not in the recordings (they have {channels:?})");
        }
        channels = a.channels.clone();
    }
    let events: Vec<Event> = events_from(recs)
        .into_iter()
        .filter(|e| match e {
            Event::Observation { channel, .. } => channels.contains(channel),
            _ => true,
        })
        .collect();
    let mut opts = DisplacementOptions::default();
    let mut given: Option<ModelConfig> = None;
    match &a.model {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let m = ThermalModel::from_json(&text)
                .with_context(|| format!("thermal model {}", path.display()))?;
            opts.n_ref_rpm = m.config.n_ref_rpm;
            opts.gamma = m.config.gamma;
            given = Some(m.config);
        }
        // Without a model, the top logged speed is the reference (it only scales the gains).
        None => {
            let top = recs
                .iter()
                .flat_map(|r| r.spindle.iter().map(|m| m.msg.rpm.abs()))
                .filter(|x| x.is_finite())
                .fold(0.0, f64::max);
            if top > 0.0 {
                opts.n_ref_rpm = top;
            }
        }
    }
    if let Some(h) = a.holdout_from_h {
        let t0 = events
            .iter()
            .find(|e| matches!(e, Event::Observation { .. }))
            .map_or(0, |e| e.t_ns());
        opts.holdout_from_ns = Some(t0 + units::h_to_ns(h));
    }
    let d = diagnose_displacements(&events, &channels, &opts).context("displacement diagnosis")?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let file = DisplacementFile {
        format: DISPLACEMENT_FORMAT,
        recordings: a
            .recording
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        options: &opts,
        diagnosis: &d,
    };
    let (json_path, html_path) = write_report(
        &a.out,
        &file,
        &driftwatch_diagnosis::report::displacement_html(
            &d,
            "driftwatch diagnosis: displacement recording",
        ),
    )?;
    // The new version extends the given model's configuration (its inputs and settings).
    let config = match given {
        Some(g) => g.with_inputs(
            &d.channels
                .iter()
                .flat_map(|c| {
                    c.baseline_mode
                        .as_ref()
                        .map(|m| ModelInput::SpindleLag { tau_min: m.tau_min })
                        .into_iter()
                        .chain(c.accepted.iter().map(|t| t.input.clone()))
                })
                .collect::<Vec<_>>(),
        ),
        None => d.model.clone(),
    };
    let model_path = a.out.join("model.json");
    let model_note = write_model(&config, &events, &model_path)?;
    for s in &d.skipped {
        println!("not diagnosed: {s}");
    }
    for c in &d.channels {
        for s in &c.statements {
            println!("{s}");
        }
    }
    for n in &d.not_carried {
        println!(
            "not carried into the model (a clock term, or a drift gated at an onset the thermal model has no input for): {n}"
        );
    }
    print_located(&d);
    println!(
        "wrote {} and {}; {model_note}",
        json_path.display(),
        html_path.display(),
    );
    Ok(ExitCode::SUCCESS)
}

/// Each located term of `d` in one line: where, its held-out RMS before and after, and its
/// verdict.
fn print_located(d: &DisplacementDiagnosis) {
    for c in &d.channels {
        // A thermal base the held-out veto dropped keeps its located terms beside it: what
        // was found on a baseline that models the warm-up, not in the final model.
        let vetoed = c.thermal_base.as_ref().filter(|b| !b.kept);
        let on_base = vetoed.into_iter().flat_map(|b| {
            b.located_term
                .iter()
                .map(|l| ("located term on the vetoed thermal base", l))
                .chain(
                    b.late_term
                        .iter()
                        .map(|l| ("later located term on the vetoed thermal base", l)),
                )
        });
        for (what, l) in c
            .located_term
            .iter()
            .map(|l| ("located term", l))
            .chain(c.late_term.iter().map(|l| ("later located term", l)))
            .chain(on_base)
        {
            println!(
                "{}: {what} {}: held-out RMS {:.2} -> {:.2} um, {}",
                c.channel,
                l.term,
                l.heldout_before_um,
                l.heldout_after_um,
                if l.accepted {
                    "accepted into the final model".to_string()
                } else {
                    format!(
                        "not confirmed ({}){}",
                        l.reason.map_or("", |r| r.words()),
                        l.split_by
                            .as_ref()
                            .map(|s| format!("; what would split it: {s}"))
                            .unwrap_or_default()
                    )
                }
            );
        }
    }
}

/// Fit `config` on `events` and write it to `path` as the new model version; a fit that
/// fails is a note, not an error (the diagnosis is already written).
fn write_model(config: &ModelConfig, events: &[Event], path: &std::path::Path) -> Result<String> {
    Ok(match driftwatch_thermal::model::fit(config, events, None) {
        Ok(model) => {
            std::fs::write(path, serde_json::to_string_pretty(&model)?)
                .with_context(|| format!("writing {}", path.display()))?;
            format!(
                "wrote {}: the thermal model with the accepted terms it can carry",
                path.display()
            )
        }
        Err(e) => format!("no model.json: {e}"),
    })
}

/// Write `diagnosis.json` and `report.html` into `out`; their paths.
fn write_report(
    out: &std::path::Path,
    file: &impl Serialize,
    html: &str,
) -> Result<(PathBuf, PathBuf)> {
    let json_path = out.join("diagnosis.json");
    std::fs::write(&json_path, serde_json::to_string_pretty(file)?)
        .with_context(|| format!("writing {}", json_path.display()))?;
    let html_path = out.join("report.html");
    std::fs::write(&html_path, html).with_context(|| format!("writing {}", html_path.display()))?;
    Ok((json_path, html_path))
}
