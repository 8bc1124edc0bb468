//! `driftwatch import csv`, `fit` and `predict`: the thermal model on recordings.

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};

use driftwatch::csv_import::{CsvOptions, RowTime, import_csv, split_columns};
use driftwatch::kinematics::Kinematics;
use driftwatch::recording::Recording;
use driftwatch::recording::mcap_io::{ReadOptions, read_file, write_recording_file};
use driftwatch::thermal_model::{
    DEFAULT_MODEL_CONFIG, Event, ModelConfig, TemperatureInput, ThermalModel, events_from, fit,
    replay,
};

#[derive(clap::Args)]
pub struct ImportCsvArgs {
    /// The CSV file (a header row, then one row per sample time).
    #[arg(long = "in")]
    input: PathBuf,
    /// The recording to write.
    #[arg(long)]
    out: PathBuf,
    /// Column of the sample time: seconds after --start, or RFC 3339 times.
    #[arg(
        long,
        conflicts_with = "interval_s",
        required_unless_present = "interval_s"
    )]
    time_column: Option<String>,
    /// Rows are this many seconds apart (instead of a time column).
    #[arg(long)]
    interval_s: Option<f64>,
    /// The time of 0 s (RFC 3339).
    #[arg(long, default_value = "1970-01-01T00:00:00Z")]
    start: String,
    /// Column of the spindle speed, min^-1.
    #[arg(long)]
    spindle_column: Option<String>,
    /// Columns of temperatures, deg C (comma-separated or repeated); the column name is the
    /// sensor name.
    #[arg(long, num_args = 1..)]
    temperature_columns: Vec<String>,
    /// Columns of displacements, um (comma-separated or repeated).
    #[arg(long, num_args = 1..)]
    displacement_columns: Vec<String>,
    /// Machine id written to /machine/info (default: the file name).
    #[arg(long)]
    machine_id: Option<String>,
}

pub fn cmd_import_csv(a: ImportCsvArgs) -> Result<ExitCode> {
    let text = std::fs::read_to_string(&a.input)
        .with_context(|| format!("reading {}", a.input.display()))?;
    let start_ns = chrono::DateTime::parse_from_rfc3339(&a.start)
        .ok()
        .and_then(|d| d.timestamp_nanos_opt())
        .with_context(|| format!("--start '{}' is not an RFC 3339 time", a.start))?;
    let time = match (a.time_column, a.interval_s) {
        (Some(c), _) => RowTime::Column(c),
        (None, Some(s)) => RowTime::Interval(s),
        (None, None) => anyhow::bail!("give --time-column or --interval-s"),
    };
    let machine_id = a.machine_id.unwrap_or_else(|| {
        a.input
            .file_stem()
            .map_or("imported".into(), |s| s.to_string_lossy().into_owned())
    });
    let opts = CsvOptions {
        time,
        start_ns,
        spindle: a.spindle_column,
        temperatures: split_columns(&a.temperature_columns),
        displacements: split_columns(&a.displacement_columns),
        machine_id,
    };
    let im =
        import_csv(&text, &opts).with_context(|| format!("importing {}", a.input.display()))?;
    write_recording_file(&a.out, &im.recording)
        .with_context(|| format!("writing {}", a.out.display()))?;
    let r = &im.recording;
    println!(
        "{} rows -> {}: {} /spindle, {} /temperature, {} /displacement messages",
        im.rows,
        a.out.display(),
        r.spindle.len(),
        r.temperatures.len(),
        r.displacements.len()
    );
    for (col, n) in &im.skipped {
        println!("  column {col}: {n} cells empty or not a number, skipped");
    }
    Ok(ExitCode::SUCCESS)
}

/// A time given as a duration after `t0_ns` (`40h`, `90m`, `3600`) or as RFC 3339.
fn parse_time(text: &str, t0_ns: i64) -> Result<i64> {
    if let Ok(d) = chrono::DateTime::parse_from_rfc3339(text)
        && let Some(t) = d.timestamp_nanos_opt()
    {
        return Ok(t);
    }
    let d = driftwatch::series::parse_every(text).map_err(|_| {
        anyhow::anyhow!(
            "'{text}' is neither a duration after the start (40h, 90m, 3600) nor an RFC 3339 time"
        )
    })?;
    Ok(t0_ns + d)
}

fn read_recordings(paths: &[PathBuf]) -> Result<Vec<Recording>> {
    paths
        .iter()
        .map(|p| {
            read_file(p, &ReadOptions::default())
                .with_context(|| format!("reading {}", p.display()))
        })
        .collect()
}

#[derive(clap::Args)]
pub struct FitArgs {
    /// Machine TOML, or a built-in name (table_bc).
    #[arg(long)]
    machine: String,
    /// Recordings (spindle, temperatures, displacements, cycle results), in any order.
    #[arg(long, num_args = 1.., required = true)]
    recording: Vec<PathBuf>,
    /// Where the model goes (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Fit only data up to this time: a duration after the first event (40h) or RFC 3339.
    #[arg(long)]
    until: Option<String>,
    /// Model configuration TOML (default: the built-in `config/thermal.toml`).
    #[arg(long)]
    model_config: Option<PathBuf>,
    /// Reference speed of the heat input, min^-1 (overrides the configuration).
    #[arg(long)]
    n_ref_rpm: Option<f64>,
    /// Temperature sensors to use as inputs, with the default lags (comma-separated).
    #[arg(long, num_args = 1..)]
    temperature_inputs: Vec<String>,
    /// Spindle pole basis, min (comma-separated; overrides the configuration).
    #[arg(long, value_delimiter = ',')]
    taus_min: Vec<f64>,
    /// Fit only these channels (comma-separated; default: every observed channel).
    #[arg(long, num_args = 1..)]
    channels: Vec<String>,
}

pub fn model_config(
    file: Option<&PathBuf>,
    n_ref_rpm: Option<f64>,
    temperature_inputs: &[String],
    taus_min: &[f64],
) -> Result<ModelConfig> {
    let text = match file {
        Some(p) => {
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?
        }
        None => DEFAULT_MODEL_CONFIG.to_string(),
    };
    let mut cfg = ModelConfig::from_toml(&text).context("model configuration")?;
    if let Some(n) = n_ref_rpm {
        cfg.n_ref_rpm = n;
    }
    if !taus_min.is_empty() {
        cfg.taus_min = taus_min.to_vec();
    }
    for s in split_columns(temperature_inputs) {
        cfg.temperatures.push(TemperatureInput {
            sensor: s,
            taus_min: driftwatch::thermal_model::default_temperature_taus(),
        });
    }
    cfg.validate()?;
    Ok(cfg)
}

pub fn filter_channels(events: Vec<Event>, channels: &[String]) -> Vec<Event> {
    let keep = split_columns(channels);
    if keep.is_empty() {
        return events;
    }
    events
        .into_iter()
        .filter(|e| match e {
            Event::Observation { channel, .. } => keep.contains(channel),
            _ => true,
        })
        .collect()
}

pub fn cmd_fit(a: FitArgs) -> Result<ExitCode> {
    Kinematics::load(&a.machine).with_context(|| format!("machine '{}'", a.machine))?;
    let cfg = model_config(
        a.model_config.as_ref(),
        a.n_ref_rpm,
        &a.temperature_inputs,
        &a.taus_min,
    )?;
    let events = filter_channels(events_from(&read_recordings(&a.recording)?), &a.channels);
    let t0 = events.first().map_or(0, Event::t_ns);
    let until = a.until.as_deref().map(|u| parse_time(u, t0)).transpose()?;
    let model = fit(&cfg, &events, until)?;
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&a.out, serde_json::to_string_pretty(&model)?)
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "model of {} channel(s) fitted on {:.2} h of data -> {}",
        model.channels.len(),
        (model.to_ns - model.from_ns) as f64 / 3.6e12,
        a.out.display()
    );
    println!(
        "channel          n   rms um  chi2/dof  discrepancy um  ridge  held-out rmse um  temperatures"
    );
    for c in &model.channels {
        println!(
            "{:<12} {:>5} {:>8.3} {:>9.2} {:>15.3} {:>6} {:>17.3}  {}",
            c.name,
            c.n_obs,
            c.rms_um,
            c.chi2_dof,
            c.discrepancy_um,
            c.ridge,
            c.cv_rmse_um,
            match (
                model.config.temperatures.is_empty(),
                c.held_to_range.is_empty()
            ) {
                (true, _) => "-",
                (false, true) => "extrapolated (gains significant)",
                (false, false) => "held to the fit's range (gains not significant)",
            }
        );
    }
    // What each channel will serve, from the held-out tail of the fit data.
    let p = driftwatch::thermal_model::Predictor::new(&model, model.to_ns);
    println!(
        "what each channel serves, from the held-out tail ({:.0} % of its observations):",
        100.0 * model.config.holdout_share
    );
    for g in p.guards() {
        println!("{g}");
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args)]
pub struct PredictArgs {
    /// A model written by `driftwatch fit`.
    #[arg(long)]
    model: PathBuf,
    /// The recording to replay.
    #[arg(long)]
    recording: PathBuf,
    /// Output step, s.
    #[arg(long, default_value_t = 60.0)]
    step_s: f64,
    /// One JSON object per step (else a table).
    #[arg(long)]
    json: bool,
    /// Correct the model with the recording's observations only up to this time (a duration
    /// after the first event, or RFC 3339); later ones are compared, not used. Default: all.
    #[arg(long)]
    update_until: Option<String>,
    /// Print steps from this time on (same forms); observations from then on are scored
    /// before they are used (default: those after --update-until).
    #[arg(long)]
    from: Option<String>,
}

/// The truth of a simulated recording (`/sim/truth`, the minute samples, not the cycles'):
/// time and apparent errors.
fn truth_of(path: &std::path::Path) -> Result<Vec<(i64, std::collections::BTreeMap<String, f64>)>> {
    let r = read_file(
        path,
        &ReadOptions {
            keep_raw: true,
            ..Default::default()
        },
    )
    .with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for m in r
        .raw
        .iter()
        .filter(|m| m.topic == driftwatch::recording::TOPIC_TRUTH)
    {
        let Ok(v) = serde_json::from_slice::<serde_json::Value>(&m.data) else {
            continue;
        };
        if v.get("cycle").is_some_and(|c| !c.is_null()) {
            continue;
        }
        if let Some(a) = v.get("apparent").and_then(|a| a.as_object()) {
            let values = a
                .iter()
                .filter_map(|(k, x)| x.as_f64().map(|x| (k.clone(), x)))
                .collect();
            out.push((m.t_ns, values));
        }
    }
    out.sort_by_key(|x| x.0);
    Ok(out)
}

pub fn cmd_predict(a: PredictArgs) -> Result<ExitCode> {
    anyhow::ensure!(
        a.step_s > 0.0 && a.step_s.is_finite(),
        "--step-s must be > 0"
    );
    let text = std::fs::read_to_string(&a.model)
        .with_context(|| format!("reading {}", a.model.display()))?;
    let model = ThermalModel::from_json(&text).with_context(|| a.model.display().to_string())?;
    let events = events_from(&read_recordings(std::slice::from_ref(&a.recording))?);
    let Some(first) = events.first() else {
        anyhow::bail!("{}: no events to replay", a.recording.display());
    };
    let t0 = first.t_ns();
    let update_until = a
        .update_until
        .as_deref()
        .map(|u| parse_time(u, t0))
        .transpose()?
        .unwrap_or(i64::MAX);
    let from = a
        .from
        .as_deref()
        .map(|u| parse_time(u, t0))
        .transpose()?
        .unwrap_or(t0);
    let score_from = if a.from.is_some() {
        from
    } else {
        update_until.saturating_add(1)
    };
    let step_ns = (a.step_s * 1e9).round() as i64;
    let (steps, scores, served) = replay(&model, &events, step_ns, update_until, score_from);
    let mut out = std::io::stdout().lock();
    if !a.json {
        writeln!(
            out,
            "{:>10} {:<12} {:>10} {:>8} source",
            "t h", "channel", "value", "sigma"
        )?;
    }
    for s in steps.iter().filter(|s| s.t_ns >= from) {
        let source = |ch: &str| {
            if s.measured.contains_key(ch) {
                "measured"
            } else {
                "predicted"
            }
        };
        if a.json {
            let values: serde_json::Map<String, serde_json::Value> = s
                .predictions
                .iter()
                .map(|x| {
                    (
                        x.channel.clone(),
                        serde_json::json!({
                            "value": x.value,
                            "sigma": x.sigma,
                            "source": source(&x.channel),
                            "served_from": x.source.as_str(),
                            "model_value": x.model_value,
                            "fallback_reason": x.reason,
                            "measured": s.measured.get(&x.channel),
                        }),
                    )
                })
                .collect();
            let line = serde_json::json!({
                "t_ns": s.t_ns,
                "time": chrono::DateTime::from_timestamp_nanos(s.t_ns).to_rfc3339(),
                "values": values,
            });
            writeln!(out, "{line}")?;
        } else {
            for x in &s.predictions {
                writeln!(
                    out,
                    "{:>10.3} {:<12} {:>10.3} {:>8.3} {}",
                    (s.t_ns - t0) as f64 / 3.6e12,
                    x.channel,
                    x.value,
                    x.sigma,
                    source(&x.channel)
                )?;
            }
        }
    }
    drop(out);
    let what = if a.from.is_some() {
        "readings from --from on, each scored before it is used"
    } else {
        "readings after the last update"
    };
    for s in &scores {
        eprintln!(
            "{}: {} {what}: RMSE {:.3} {u} (persistence {:.3}, no change {:.3}, served {:.3}); band: z rms {:.2}, within 1 sigma {:.0} %, within 2 sigma {:.0} %",
            s.channel,
            s.n,
            s.rmse_um,
            s.persistence_rmse_um,
            s.no_change_rmse_um,
            s.served_rmse_um,
            s.z_rms,
            100.0 * s.within_1_sigma,
            100.0 * s.within_2_sigma,
            u = driftwatch::compensation::unit(&s.channel)
        );
    }
    for g in &served {
        eprintln!("at the end: {g}\n  {}", g.reason);
    }
    let truth = truth_of(&a.recording)?;
    if let Some((_, reference)) = truth.first() {
        let t = driftwatch::thermal_model::truth_scores(&steps, &events, &truth, reference, from);
        eprintln!(
            "against the recording's truth (/sim/truth) from --from on, RMS: no compensation (the first sample's truth) / last measured / served (share of the thermal error removed) / model"
        );
        for s in &t {
            let unit = driftwatch::compensation::unit(&s.channel);
            eprintln!(
                "{:<6} {:>5} min  none {:>7.3}  last measured {:>7.3}  served {:>7.3} ({:>5.1} %)  model {:>7.3} {unit}{}",
                s.channel,
                s.samples,
                s.none_rms,
                s.last_measured_rms,
                s.served_rms,
                100.0 * s.removed(),
                s.model_rms,
                if s.served_rms > s.none_rms {
                    "  WORSE THAN NONE"
                } else {
                    ""
                }
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
