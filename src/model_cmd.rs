//! `driftwatch import csv`, `fit` and `predict`: the thermal model on recordings.

use driftwatch_core::units;
use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};

use crate::prediction_plot::Panel;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::recording::Recording;
use driftwatch_recording::csv_import::{
    CsvFormat, CsvOptions, RowTime, import_csv_with, keep_changed_displacements, split_columns,
    split_runs,
};
use driftwatch_recording::mcap_io::{ReadOptions, read_file, write_recording_file};
use driftwatch_thermal::families::{ChannelChoice, Family};
use driftwatch_thermal::model::{
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
    /// Columns of displacements, um (comma-separated or repeated). Any column may be given
    /// by its position as #N (1-based); the sensor takes the header's name.
    #[arg(long, num_args = 1..)]
    displacement_columns: Vec<String>,
    /// Machine id written to /machine/info (default: the file name).
    #[arg(long)]
    machine_id: Option<String>,
    /// Field delimiter: one character, or `tab`.
    #[arg(long, default_value = ",")]
    delimiter: String,
    /// Numbers have a decimal comma (20,5); give another --delimiter.
    #[arg(long)]
    decimal_comma: bool,
    /// Replace --out if it exists (else the import is refused).
    #[arg(long)]
    force: bool,
    /// Column naming each row's run (a thermal test of several runs, each zeroed at its
    /// start, in one table): --out is then a directory, one recording per run
    /// (`<run>.mcap`), for `fit --runs`.
    #[arg(long)]
    run_column: Option<String>,
    /// The displacement sensors hold their value between real updates (while the machine
    /// stands): a row whose value did not change is not a reading and is left out.
    #[arg(long)]
    only_changed: bool,
}

pub fn cmd_import_csv(a: ImportCsvArgs) -> Result<ExitCode> {
    let delimiter = match a.delimiter.as_str() {
        "tab" | "\\t" | "\t" => b'\t',
        d if d.len() == 1 && d.is_ascii() => d.as_bytes()[0],
        d => anyhow::bail!("--delimiter '{d}': give one ASCII character or tab"),
    };
    anyhow::ensure!(
        a.force || !a.out.exists(),
        "{} exists: give --force to replace it",
        a.out.display()
    );
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
    let fmt = CsvFormat {
        delimiter,
        decimal_comma: a.decimal_comma,
    };
    let parts = match &a.run_column {
        Some(col) => {
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("creating {}", a.out.display()))?;
            split_runs(&text, col, fmt)
                .with_context(|| format!("{}: --run-column {col}", a.input.display()))?
                .into_iter()
                .map(|(run, t)| {
                    let safe: String = run
                        .chars()
                        .map(|c| {
                            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                                c
                            } else {
                                '_'
                            }
                        })
                        .collect();
                    (Some(run), a.out.join(format!("{safe}.mcap")), t)
                })
                .collect()
        }
        None => vec![(None, a.out.clone(), text)],
    };
    for (run, out, text) in parts {
        anyhow::ensure!(
            a.force || a.run_column.is_none() || !out.exists(),
            "{} exists: give --force to replace it",
            out.display()
        );
        let mut im = import_csv_with(&text, &opts, fmt).with_context(|| {
            format!(
                "importing {}{}",
                a.input.display(),
                run.as_ref()
                    .map_or(String::new(), |r| format!(" (run {r})"))
            )
        })?;
        if a.only_changed {
            keep_changed_displacements(&mut im.recording);
        }
        write_recording_file(&out, &im.recording)
            .with_context(|| format!("writing {}", out.display()))?;
        let r = &im.recording;
        println!(
            "{} rows -> {}: {} /spindle, {} /temperature, {} /displacement messages",
            im.rows,
            out.display(),
            r.spindle.len(),
            r.temperatures.len(),
            r.displacements.len()
        );
        for (col, n) in &im.skipped {
            println!("  column {col}: {n} cells empty or not a number, skipped");
        }
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
    let d = driftwatch_service::series::parse_every(text).map_err(|_| {
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
    /// Machine TOML, or a built-in name (table_bc, head_b_table_c, table_d45_c, head_d45_table_c, trunnion_ac): checked when given; a displacement
    /// recording needs none.
    #[arg(long)]
    machine: Option<String>,
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
    /// Temperature sensors to use as inputs, with the default lags (comma-separated). A
    /// displacement recording's grey box takes every temperature that varies unless some are
    /// named here; `none`: no temperature (the spindle basis alone).
    #[arg(long, num_args = 1..)]
    temperature_inputs: Vec<String>,
    /// Spindle pole basis, min (comma-separated; overrides the configuration).
    #[arg(long, value_delimiter = ',')]
    taus_min: Vec<f64>,
    /// Fit only these channels (comma-separated; default: every observed channel).
    #[arg(long, num_args = 1..)]
    channels: Vec<String>,
    /// The model family of each displacement channel: `auto` (the lowest rolling-origin CV
    /// error on the fit data among grey_box, persistence, regression, key_regression and
    /// arx), or one of them. Cycle-result channels always take the grey box.
    #[arg(long, default_value = "auto")]
    family: String,
    /// Use only these temperature sensors as inputs, in every family (comma-separated;
    /// default: every sensor the recordings have).
    #[arg(long, num_args = 1..)]
    sensors: Vec<String>,
    /// Grid step of the families, min (displacement channels; default: the temperatures'
    /// median sample spacing, at least a 400th of the data's span, or of the shortest run).
    #[arg(long)]
    step_min: Option<f64>,
    /// How far ahead of its last reading the model will be used (a duration, 8h): the
    /// families are judged by CV at this horizon. Default: the span of the recordings after
    /// --until (what is left to predict), else as far as the CV folds reach.
    #[arg(long)]
    horizon: Option<String>,
    /// Each recording is one run of a thermal test (a day, zeroed at its start): learn
    /// across them and write a model that predicts a new run whole from its first reading
    /// (`predict --new-run`). Runs are taken in the order of their first event, then of
    /// the arguments.
    #[arg(long)]
    runs: bool,
}

/// What `fit --runs` writes: per displacement channel the family chosen across runs.
#[derive(serde::Serialize, serde::Deserialize)]
struct RunsModelFile {
    across_runs: Vec<driftwatch_thermal::across_runs::RunsChoice>,
}

/// What `fit` writes: the grey-box model (read by the service as it is) and, for
/// displacement channels, the family competition and the chosen family.
#[derive(serde::Serialize, serde::Deserialize)]
struct ModelFile {
    #[serde(flatten)]
    model: ThermalModel,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    families: Vec<ChannelChoice>,
}

/// Keep only the named temperature sensors (all when none are named).
fn only_sensors(events: Vec<Event>, sensors: &[String]) -> Vec<Event> {
    if sensors.is_empty() {
        return events;
    }
    events
        .into_iter()
        .filter(|e| match e {
            Event::Temperature { sensor, .. } => sensors.contains(sensor),
            _ => true,
        })
        .collect()
}

/// Whether a temperature sensor's readings vary in the events.
fn varies(events: &[Event], sensor: &str) -> bool {
    let mut range: Option<(f64, f64)> = None;
    for e in events {
        if let Event::Temperature {
            sensor: s, celsius, ..
        } = e
            && s == sensor
        {
            let (lo, hi) = range.get_or_insert((*celsius, *celsius));
            *lo = lo.min(*celsius);
            *hi = hi.max(*celsius);
        }
    }
    range.is_some_and(|(lo, hi)| hi > lo)
}

/// Whether the spindle turned in the events (a log of zeros is no spindle log).
fn spins(events: &[Event]) -> bool {
    events
        .iter()
        .any(|e| matches!(e, Event::Spindle { rpm, .. } if *rpm != 0.0))
}

/// The displacement channels (observations without an uncertainty, as CSV imports and
/// `/displacement` messages give them) of the events.
fn displacement_channels(events: &[Event]) -> Vec<String> {
    let mut v: Vec<String> = events
        .iter()
        .filter_map(|e| match e {
            Event::Observation {
                channel,
                sigma: None,
                ..
            } => Some(channel.clone()),
            _ => None,
        })
        .collect();
    v.sort();
    v.dedup();
    v
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
    for s in split_columns(temperature_inputs)
        .into_iter()
        .filter(|s| s != "none")
    {
        cfg.temperatures.push(TemperatureInput {
            sensor: s,
            taus_min: driftwatch_thermal::model::default_temperature_taus(),
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
    if a.runs {
        return fit_runs(&a);
    }
    if let Some(m) = &a.machine {
        Kinematics::load(m).with_context(|| format!("machine '{m}'"))?;
    }
    let force = forced_family(&a.family)?;
    check_step(a.step_min)?;
    let (events, cfg) = fit_inputs(&a)?;
    let t0 = events.first().map_or(0, Event::t_ns);
    let until = a.until.as_deref().map(|u| parse_time(u, t0)).transpose()?;
    let model = fit(&cfg, &events, until)?;
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let last_t = events.last().map_or(t0, Event::t_ns);
    let horizon_ns = match (&a.horizon, until) {
        (Some(h), _) => Some(parse_time(h, 0)?),
        (None, Some(u)) if last_t > u => Some(last_t - u),
        _ => None,
    };
    let step_ns = a.step_min.map_or_else(
        || driftwatch_thermal::families::default_step_ns(&[&events]),
        units::min_to_ns,
    );
    let families = choose_families(&events, &cfg, step_ns, until, force, horizon_ns);
    let file = ModelFile { model, families };
    let model = &file.model;
    std::fs::write(&a.out, serde_json::to_string_pretty(&file)?)
        .with_context(|| format!("writing {}", a.out.display()))?;
    print_fit(model, &a.out);
    print_family_scores(&file.families, force.is_some());
    // What each channel will serve, from the held-out tail of the fit data.
    let p = driftwatch_thermal::model::Predictor::new(model, model.to_ns);
    println!(
        "what each channel serves, from the held-out tail ({:.0} % of its observations):",
        100.0 * model.config.holdout_share
    );
    for g in p.guards() {
        println!("{g}");
    }
    Ok(ExitCode::SUCCESS)
}

/// `--step-min`, when given, must be a positive number of minutes.
fn check_step(step_min: Option<f64>) -> Result<()> {
    anyhow::ensure!(
        step_min.is_none_or(|m| m > 0.0 && m.is_finite()),
        "--step-min must be > 0"
    );
    Ok(())
}

/// `fit --runs`: each recording a run; per displacement channel the family that predicts a
/// new run from its start, chosen by forward chaining over the runs.
fn fit_runs(a: &FitArgs) -> Result<ExitCode> {
    check_step(a.step_min)?;
    anyhow::ensure!(
        a.until.is_none() && a.family == "auto",
        "--runs learns from whole runs: --until and --family do not apply"
    );
    let sensors = split_columns(&a.sensors);
    let mut runs: Vec<(i64, usize, Vec<Event>)> = Vec::new();
    for (i, rec) in read_recordings(&a.recording)?.into_iter().enumerate() {
        let ev = only_sensors(filter_channels(events_from(&[rec]), &a.channels), &sensors);
        runs.push((ev.first().map_or(i64::MAX, Event::t_ns), i, ev));
    }
    runs.sort_by_key(|r| (r.0, r.1));
    let step_ns = a.step_min.map_or_else(
        || {
            let r: Vec<&[Event]> = runs.iter().map(|r| r.2.as_slice()).collect();
            driftwatch_thermal::families::default_step_ns(&r)
        },
        units::min_to_ns,
    );
    let mut channels: Vec<String> = runs
        .iter()
        .flat_map(|r| displacement_channels(&r.2))
        .collect();
    channels.sort();
    channels.dedup();
    let mut out = Vec::new();
    for ch in &channels {
        let grids: Vec<driftwatch_thermal::families::Grid> = runs
            .iter()
            .filter_map(|r| driftwatch_thermal::families::grid(&r.2, ch, step_ns))
            .collect();
        anyhow::ensure!(
            grids.iter().all(|g| g.names == grids[0].names),
            "{ch}: the runs do not all have the same inputs"
        );
        let refs: Vec<&driftwatch_thermal::families::Grid> = grids.iter().collect();
        match driftwatch_thermal::across_runs::choose(&refs) {
            Some(c) => {
                println!(
                    "{ch}: {} runs; chained CV RMSE (each run from the second on predicted whole from the runs before): {}",
                    refs.len(),
                    c.cv.iter()
                        .map(|(f, e)| match e {
                            Some(e) => format!("{} {e:.3}", f.as_str()),
                            None => format!("{} could not be run", f.as_str()),
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                );
                println!("{ch}: served: {}", c.why);
                out.push(c);
            }
            None => eprintln!("{ch}: no family could be fitted across the runs"),
        }
    }
    anyhow::ensure!(
        !out.is_empty(),
        "no displacement channel could be fitted across the runs"
    );
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(
        &a.out,
        serde_json::to_string_pretty(&RunsModelFile { across_runs: out })?,
    )
    .with_context(|| format!("writing {}", a.out.display()))?;
    println!("-> {}", a.out.display());
    Ok(ExitCode::SUCCESS)
}

/// `predict --new-run`: the recording as a new run, each channel predicted whole from its
/// first reading by the family `fit --runs` chose; scored on the updated readings against
/// holding the first reading.
fn predict_new_run(a: &PredictArgs, text: &str) -> Result<ExitCode> {
    let file: RunsModelFile = serde_json::from_str(text)
        .with_context(|| format!("{}: not a model written by fit --runs", a.model.display()))?;
    let events = events_from(&read_recordings(std::slice::from_ref(&a.recording))?);
    let t0 = events.first().map_or(0, Event::t_ns);
    let mut out = std::io::stdout().lock();
    for c in &file.across_runs {
        let g = driftwatch_thermal::families::grid(&events, &c.channel, c.step_ns)
            .with_context(|| format!("{}: no readings with every input", c.channel))?;
        anyhow::ensure!(
            g.names == c.names,
            "{}: the model's inputs are {}, the recording has {}",
            c.channel,
            c.names.join(", "),
            g.names.join(", ")
        );
        let p = driftwatch_thermal::across_runs::predict(&c.fitted, &g);
        let (mut e, mut held) = (Vec::new(), Vec::new());
        for (k, v) in p.iter().enumerate() {
            if a.json {
                let line = serde_json::json!({
                    "t_ns": g.t_ns[k],
                    "values": {c.channel.clone(): {"value": v, "source": "predicted",
                        "family": c.family.as_str(), "measured": g.y[k]}},
                });
                writeln!(out, "{line}")?;
            } else {
                writeln!(
                    out,
                    "{:>10.3} {:<12} {:>10.3} predicted ({}; measured {:.3})",
                    units::ns_to_h(g.t_ns[k] - t0),
                    c.channel,
                    v,
                    c.family.as_str(),
                    g.y[k]
                )?;
            }
            if k > 0 && g.fresh[k] {
                e.push(v - g.y[k]);
                held.push(g.y[0] - g.y[k]);
            }
        }
        let rms = driftwatch_thermal::families::rms;
        eprintln!(
            "{}: {} from the run's first reading, {} updated readings: RMSE {:.3} (first reading held {:.3}); {}",
            c.channel,
            c.family.as_str(),
            e.len(),
            rms(&e),
            rms(&held),
            c.why
        );
        if let Some((k, j, d)) = driftwatch_thermal::across_runs::leaves_changes(c, &g) {
            eprintln!(
                "{}: warning: from {:.2} h {} has changed by {d:.2} since the run's start, beyond what the fit runs taught ({:.2} to {:.2}): the prediction is an extrapolation there",
                c.channel,
                units::ns_to_h(g.t_ns[k] - t0),
                g.names[j],
                c.change_ranges[j][0],
                c.change_ranges[j][1]
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `--family`: `auto` (None) or the family every displacement channel takes.
fn forced_family(family: &str) -> Result<Option<Family>> {
    Ok(match family {
        "auto" => None,
        f => Some(Family::parse(f).with_context(|| {
            format!(
                "--family {f}: use auto, {}",
                Family::ALL.map(Family::as_str).join(", ")
            )
        })?),
    })
}

/// The recordings' events (only the named channels and sensors) and the model configuration
/// the data allow; prints the inputs.
fn fit_inputs(a: &FitArgs) -> Result<(Vec<Event>, ModelConfig)> {
    let sensors = split_columns(&a.sensors);
    let events = only_sensors(
        filter_channels(events_from(&read_recordings(&a.recording)?), &a.channels),
        &sensors,
    );
    let mut cfg = model_config(
        a.model_config.as_ref(),
        a.n_ref_rpm,
        &a.temperature_inputs,
        &a.taus_min,
    )?;
    let all_sensors = driftwatch_thermal::model::sensors_of(&events);
    for s in &sensors {
        anyhow::ensure!(
            all_sensors.contains(s),
            "--sensors {s}: the recordings have no such sensor (they have: {})",
            all_sensors.join(", ")
        );
    }
    inputs_the_data_allow(&mut cfg, &events, &all_sensors, &a.temperature_inputs);
    println!(
        "inputs: {}{}",
        if spins(&events) {
            "spindle speed, "
        } else {
            ""
        },
        if all_sensors.is_empty() {
            "no temperatures".to_string()
        } else {
            format!("temperatures {}", all_sensors.join(", "))
        }
    );
    Ok((events, cfg))
}

/// The temperature inputs and the spindle basis as the data allow them, with a warning when
/// there is no spindle log.
fn inputs_the_data_allow(
    cfg: &mut ModelConfig,
    events: &[Event],
    all_sensors: &[String],
    temperature_inputs: &[String],
) {
    let every_sensor = || {
        all_sensors
            .iter()
            .map(|s| TemperatureInput {
                sensor: s.clone(),
                taus_min: driftwatch_thermal::model::default_temperature_taus(),
            })
            .collect()
    };
    // A displacement recording's grey box takes every temperature that varies unless some
    // are named: it competes with regressions that take them all, and `bench thermal` judges
    // it so. (A constant one is the offset again.)
    let none_named = split_columns(temperature_inputs) == ["none"];
    if cfg.temperatures.is_empty() && !none_named && !displacement_channels(events).is_empty() {
        cfg.temperatures = every_sensor();
        cfg.temperatures.retain(|t| varies(events, &t.sensor));
    }
    if !spins(events) {
        // No spindle log: the spindle basis would be a column of zeros. The temperatures
        // are the inputs, every one unless some are named.
        cfg.taus_min.clear();
        cfg.instant_speed = false;
        if cfg.temperatures.is_empty() && !none_named {
            cfg.temperatures = every_sensor();
        }
        eprintln!(
            "warning: the recordings have no spindle speed (no /spindle message, or only 0): the models use the temperatures alone{}",
            if cfg.temperatures.is_empty() {
                " (there are none: an offset only)"
            } else {
                ""
            }
        );
    }
}

/// The families compete on each displacement channel, on the fit data only.
fn choose_families(
    events: &[Event],
    cfg: &ModelConfig,
    step_ns: i64,
    until: Option<i64>,
    force: Option<Family>,
    horizon_ns: Option<i64>,
) -> Vec<ChannelChoice> {
    // In grid steps; none given: as far as the folds reach.
    let horizon = horizon_ns.map_or(usize::MAX, |h| {
        (h.max(1) as f64 / step_ns as f64).ceil() as usize
    });
    let train_end = until.unwrap_or(i64::MAX);
    let mut families = Vec::new();
    for ch in displacement_channels(events) {
        let Some(g) = driftwatch_thermal::families::grid(events, &ch, step_ns) else {
            continue;
        };
        match driftwatch_thermal::families::choose(
            events,
            &g,
            train_end,
            &Family::ALL,
            cfg,
            force,
            horizon,
        ) {
            Some(c) => families.push(c),
            None => eprintln!(
                "{ch}: no family could be fitted (too few readings for the rolling origins)"
            ),
        }
    }
    families
}

/// The grey box's fit of each channel, as a table.
fn print_fit(model: &ThermalModel, out: &std::path::Path) {
    println!(
        "model of {} channel(s) fitted on {:.2} h of data -> {}",
        model.channels.len(),
        units::ns_to_h(model.to_ns - model.from_ns),
        out.display()
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
}

/// The families' cross-validation scores on each displacement channel, the chosen (or
/// `forced`) one marked.
fn print_family_scores(families: &[ChannelChoice], forced: bool) {
    if families.is_empty() {
        return;
    }
    println!(
        "model families, rolling-origin cross-validation on the fit data (eight origins, each fitted on what came before it and predicting freely up to the horizon of use): CV RMSE; the 68/95 % band of the CV errors at horizons under 1 h and over 8 h; and its CV coverage (each fold against the other folds' bands; 68 and 95 % when calibrated). These are CV figures on the fit data, not a hold-out."
    );
    println!(
        "{:<12} {:<15} {:>9} {:>13} {:>13} {:>11}  chosen / inputs",
        "channel", "family", "CV rmse", "band <1 h", "band >8 h", "CV cov"
    );
    for c in families {
        for s in &c.scores {
            let (early, late) = s
                .bands
                .as_ref()
                .map_or(((s.band68, s.band95), (s.band68, s.band95)), |b| {
                    (b.at(0), b.at(usize::MAX))
                });
            println!(
                "{:<12} {:<15} {:>9.3} {:>6.2}/{:<6.2} {:>6.2}/{:<6.2} {:>4.0}%/{:>3.0}%  {}{}",
                c.channel,
                s.family,
                s.cv_rmse,
                early.0,
                early.1,
                late.0,
                late.1,
                100.0 * s.cv_cover68.unwrap_or(f64::NAN),
                100.0 * s.cv_cover95.unwrap_or(f64::NAN),
                if s.family == c.family {
                    if forced { "<- forced; " } else { "<- chosen; " }
                } else {
                    ""
                },
                s.detail
            );
        }
        if let Some(ch) = &c.choice {
            println!("{:<12} served: {}", c.channel, ch.why);
        }
    }
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
    /// after the first event, or RFC 3339); later ones are compared, not used. `none`: no
    /// correction after the fit's data. Default: all.
    #[arg(long)]
    update_until: Option<String>,
    /// Print steps from this time on (same forms); observations from then on are scored
    /// before they are used (default: those after --update-until).
    #[arg(long)]
    from: Option<String>,
    /// Also draw each channel (measured, predicted, band, where the updates stop) to this SVG.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// The recording is a new run: predict it whole from its first reading with a model
    /// written by `fit --runs`.
    #[arg(long)]
    new_run: bool,
}

/// The grey box's rows from `from` on: a table, or one JSON object per step.
fn print_steps(
    steps: &[driftwatch_thermal::model::ReplayStep],
    from: i64,
    t0: i64,
    json: bool,
) -> Result<()> {
    let mut out = std::io::stdout().lock();
    if !json {
        writeln!(
            out,
            "{:>10} {:<12} {:>10} {:>8} source",
            "t h", "channel", "value", "sigma"
        )?;
    }
    for s in steps
        .iter()
        .filter(|s| s.t_ns >= from && !s.predictions.is_empty())
    {
        let source = |ch: &str| {
            if s.measured.contains_key(ch) {
                "measured"
            } else {
                "predicted"
            }
        };
        if json {
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
                    units::ns_to_h(s.t_ns - t0),
                    x.channel,
                    x.value,
                    x.sigma,
                    source(&x.channel)
                )?;
            }
        }
    }
    Ok(())
}

/// Draw the panels, with the readings from `from` on, to `path`. `boundary_h`: where the
/// grey box's updates stop (a family's panel has its own).
fn write_plot(
    path: &std::path::Path,
    mut panels: std::collections::BTreeMap<String, Panel>,
    events: &[Event],
    from: i64,
    t0: i64,
    boundary_h: Option<f64>,
) -> Result<()> {
    let h = |t: i64| units::ns_to_h(t - t0);
    for e in events.iter().filter(|e| e.t_ns() >= from) {
        if let Event::Observation {
            channel,
            value,
            t_ns,
            ..
        } = e
            && let Some(p) = panels.get_mut(channel)
        {
            p.measured.push((h(*t_ns), *value));
        }
    }
    let list: Vec<Panel> = panels
        .into_iter()
        .map(|(ch, mut p)| {
            p.unit = driftwatch_core::error_name::channel_unit(&ch).to_string();
            p.boundary_h = p.boundary_h.or(boundary_h);
            p.channel = ch;
            p
        })
        .collect();
    let svg = crate::prediction_plot::svg(&list)
        .map_err(|e| anyhow::anyhow!("drawing {}: {e}", path.display()))?;
    std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))?;
    eprintln!("plot of {} channel(s) -> {}", list.len(), path.display());
    Ok(())
}

/// A family channel ready to run: its choice, its grid on the recording, the first grid point
/// it predicts.
type Run = (ChannelChoice, driftwatch_thermal::families::Grid, usize);

/// Grid each chosen family on the recording, from the last reading at or before `origin_t`.
fn family_runs(chosen: Vec<ChannelChoice>, events: &[Event], origin_t: i64) -> Result<Vec<Run>> {
    let mut runs = Vec::new();
    for c in chosen {
        let g = driftwatch_thermal::families::grid(events, &c.channel, c.step_ns)
            .with_context(|| format!("{}: no readings with every input", c.channel))?;
        anyhow::ensure!(
            g.names == c.inputs,
            "{}: the model's {} inputs are {}, the recording has {}",
            c.channel,
            c.family,
            c.inputs.join(", "),
            g.names.join(", ")
        );
        let origin = g.index_at(origin_t.saturating_add(1)).max(1);
        runs.push((c, g, origin));
    }
    Ok(runs)
}

#[derive(serde::Deserialize)]
struct FamiliesOnly {
    #[serde(default)]
    families: Vec<ChannelChoice>,
}

/// A channel served by its family choice: it runs freely from the last reading before grid
/// point `origin` (the fit's end, or --update-until), without updates. Rows from `from` on at
/// `step_ns`, then RMSE, largest error and band coverage against the readings after the
/// origin, next to persistence.
struct FamilyRun<'a> {
    c: &'a ChannelChoice,
    g: &'a driftwatch_thermal::families::Grid,
    origin: usize,
    /// The grey box's served values of the channel, by time.
    grey: &'a [(i64, f64)],
}

/// Runs the family, prints its rows and figures, and gives its predicted series (h, value,
/// 68 % band) for a plot.
fn predict_family(
    r: &FamilyRun,
    t0: i64,
    from: i64,
    step_ns: i64,
    json: bool,
) -> Result<Vec<(f64, f64, f64)>> {
    let (c, g, origin) = (r.c, r.g, r.origin);
    // The grey box's served value at each grid time from the last reading on (a
    // combination holds it; it may serve beyond the fit range).
    let grey_at = |t: &i64| {
        let at = r.grey.partition_point(|(tg, _)| tg <= t);
        at.checked_sub(1).map_or(f64::NAN, |i| r.grey[i].1)
    };
    let grey: Vec<f64> = g.t_ns[origin.min(g.len())..].iter().map(grey_at).collect();
    let grey_prev = grey_at(&g.t_ns[origin - 1]);
    let served = c.serve(g, origin, g.len(), &grey, grey_prev);
    eprintln!(
        "{}: served {}",
        c.channel,
        driftwatch_thermal::families::describe_served(&served, g, origin)
    );
    warn_untested_excursion(c, g, origin, t0);
    let p: Vec<(f64, String)> = served.iter().map(|(v, s)| (*v, s.to_string())).collect();
    let mut next_row = from;
    let mut series = Vec::new();
    let mut out = std::io::stdout().lock();
    for (i, (v, by)) in p.iter().enumerate() {
        let k = origin + i;
        let y = g.y[k];
        // The band widens with the time since the last reading used.
        let (b68, b95) = c.band_at(i);
        if g.t_ns[k] >= from {
            series.push((units::ns_to_h(g.t_ns[k] - t0), *v, b68));
        }
        // Rows at the requested step (the family runs on its own grid).
        if g.t_ns[k] < next_row {
            continue;
        }
        next_row = g.t_ns[k].saturating_add(step_ns);
        if json {
            let line = serde_json::json!({
                "t_ns": g.t_ns[k],
                "time": chrono::DateTime::from_timestamp_nanos(g.t_ns[k]).to_rfc3339(),
                "values": {c.channel.clone(): {
                    "value": v,
                    "sigma": b68,
                    "band95": b95,
                    "source": "predicted",
                    "family": by,
                    "measured": y,
                }},
            });
            writeln!(out, "{line}")?;
        } else {
            writeln!(
                out,
                "{:>10.3} {:<12} {:>10.3} {:>8.3} predicted ({by}; measured {:.3})",
                units::ns_to_h(g.t_ns[k] - t0),
                c.channel,
                v,
                b68,
                y
            )?;
        }
    }
    drop(out);
    let values: Vec<f64> = p.iter().map(|(v, _)| *v).collect();
    let score =
        driftwatch_thermal::families::score_free_run(g, origin, &values, &c.bands_or_pooled());
    eprintln!(
        "{}: {} ({}), free run from {:.2} h, {} updated readings on the {:.0}-min grid: RMSE {:.3} (persistence {:.3}), max {:.3}; band by horizon: within the CV's 68 % band {:.0} %, 95 % band {:.0} %",
        c.channel,
        c.family,
        c.fitted.describe(g),
        units::ns_to_h(g.t_ns[origin.min(g.len() - 1)] - t0),
        score.errors.len(),
        units::ns_to_min(c.step_ns),
        score.rmse,
        score.persistence_rmse,
        score.max_abs,
        100.0 * score.within68,
        100.0 * score.within95,
    );
    Ok(series)
}

/// Say where an input first goes further beyond its fit data's range than any CV fold went
/// (as a warming hall or a faulty sensor does): what is served from there is an
/// extrapolation no fold tested.
fn warn_untested_excursion(
    c: &ChannelChoice,
    g: &driftwatch_thermal::families::Grid,
    origin: usize,
    t0: i64,
) {
    let Some(tested) = c.choice.as_ref().map(|ch| ch.tested_excursion) else {
        return;
    };
    let bar = tested.max(driftwatch_thermal::families::RANGE_SLACK);
    let first = (origin..g.len())
        .map(|k| {
            (
                k,
                driftwatch_thermal::families::excursion_by_input(g, &c.ranges, k),
            )
        })
        .find(|(_, (x, _))| x.is_finite() && *x > bar);
    if let Some((k, (x, j))) = first {
        eprintln!(
            "{}: warning: from {:.2} h {} is beyond its fit range by {x:.2} of it (fitted on {:.3} to {:.3}), further than any CV fold went ({tested:.2}): what is served from there is an untested extrapolation (a regime the fit data did not hold, or a faulty sensor)",
            c.channel,
            units::ns_to_h(g.t_ns[k] - t0),
            g.names[j],
            c.ranges[j][0],
            c.ranges[j][1]
        );
    }
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
        .filter(|m| m.topic == driftwatch_core::recording::TOPIC_TRUTH)
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
    if a.new_run {
        let text = std::fs::read_to_string(&a.model)
            .with_context(|| format!("reading {}", a.model.display()))?;
        return predict_new_run(&a, &text);
    }
    let (model, mut grey_chosen, mut chosen) = read_model_file(&a.model)?;
    // A free run from a cut (--update-until): a channel whose choice hands over to another
    // family beyond the fit range is served by its choice, as `fit` made it; the grey box's
    // filter serves the channels that chose it throughout (corrected by every reading up to
    // the cut).
    if a.update_until.is_some() {
        let (with, without): (Vec<_>, Vec<_>) = grey_chosen.into_iter().partition(|c| {
            c.choice.as_ref().is_some_and(|ch| {
                ch.beyond
                    .as_ref()
                    .is_some_and(|b| b.family != Family::GreyBox)
            })
        });
        chosen.extend(with);
        grey_chosen = without;
    }
    let events = events_from(&read_recordings(std::slice::from_ref(&a.recording))?);
    let Some(first) = events.first() else {
        anyhow::bail!("{}: no events to replay", a.recording.display());
    };
    let t0 = first.t_ns();
    // `none`: nothing after the fit's data corrects the model (its posterior holds the rest).
    let update_until = match a.update_until.as_deref() {
        Some("none") => model.to_ns,
        Some(u) => parse_time(u, t0)?,
        None => i64::MAX,
    };
    let origin_t = if a.update_until.is_some() {
        update_until
    } else {
        model.to_ns
    };
    let runs = family_runs(chosen, &events, origin_t)?;
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
    let (mut steps, mut scores, served) =
        replay(&model, &events, step_ns, update_until, score_from);
    // Channels another family serves are not the grey box's; it takes over where the
    // family leaves its fit data.
    let other = |ch: &str| runs.iter().any(|(c, ..)| c.channel == ch);
    let greys: Vec<Vec<(i64, f64)>> = runs
        .iter()
        .map(|(c, ..)| served_values(&steps, &c.channel))
        .collect();
    for s in &mut steps {
        s.predictions.retain(|p| !other(&p.channel));
    }
    scores.retain(|s| !other(&s.channel));
    print_steps(&steps, from, t0, a.json)?;
    print_scores(&scores, a.from.is_some());
    // Where the families' CV chose the grey box and the updates stop, its CV band by
    // horizon (the filter's own band assumes the updates go on).
    if update_until < i64::MAX {
        print_grey_bands(&grey_chosen, &events, &steps, update_until);
    }
    for g in served.iter().filter(|g| !other(&g.channel)) {
        eprintln!("at the end: {g}\n  {}", g.reason);
    }
    // One panel per channel: the grey box's served values, or the family's.
    let h = |t: i64| units::ns_to_h(t - t0);
    let mut panels = grey_panels(&steps, from, t0);
    for ((c, g, origin), grey) in runs.iter().zip(&greys) {
        let run = FamilyRun {
            c,
            g,
            origin: *origin,
            grey,
        };
        let series = predict_family(&run, t0, from, step_ns, a.json)?;
        let panel = panels.entry(c.channel.clone()).or_default();
        panel.source = format!("{} (68 % band of its CV)", c.family);
        panel.predicted = series;
        panel.boundary_h = g.t_ns.get(origin.saturating_sub(1)).map(|t| h(*t));
    }
    if let Some(path) = &a.plot {
        let boundary = a.update_until.is_some().then(|| h(update_until));
        write_plot(path, panels, &events, from, t0, boundary)?;
    }
    print_truth(&a.recording, &steps, &events, from)?;
    Ok(ExitCode::SUCCESS)
}

/// A model file written by `driftwatch fit`: the grey box, the channels whose families' CV
/// chose the grey box, and the channels another family serves.
fn read_model_file(
    path: &std::path::Path,
) -> Result<(ThermalModel, Vec<ChannelChoice>, Vec<ChannelChoice>)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let model = ThermalModel::from_json(&text).with_context(|| path.display().to_string())?;
    let (grey_chosen, chosen): (Vec<ChannelChoice>, Vec<ChannelChoice>) =
        serde_json::from_str::<FamiliesOnly>(&text)
            .with_context(|| path.display().to_string())?
            .families
            .into_iter()
            .partition(|c| c.family == Family::GreyBox.as_str());
    Ok((model, grey_chosen, chosen))
}

/// The grey box's served values of channel `ch`, by time.
fn served_values(steps: &[driftwatch_thermal::model::ReplayStep], ch: &str) -> Vec<(i64, f64)> {
    steps
        .iter()
        .filter_map(|s| {
            s.predictions
                .iter()
                .find(|p| p.channel == ch)
                .map(|p| (s.t_ns, p.value))
        })
        .collect()
}

/// The grey box's scores on the readings it predicted before using them.
fn print_scores(scores: &[driftwatch_thermal::model::HoldoutScore], from_given: bool) {
    let what = if from_given {
        "readings from --from on, each scored before it is used"
    } else {
        "readings after the last update"
    };
    for s in scores {
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
            u = driftwatch_core::error_name::channel_unit(&s.channel)
        );
    }
}

/// The coverage of the families' CV band by horizon, for each channel where the CV chose the
/// grey box, over the readings after the last update.
fn print_grey_bands(
    grey_chosen: &[ChannelChoice],
    events: &[Event],
    steps: &[driftwatch_thermal::model::ReplayStep],
    update_until: i64,
) {
    for c in grey_chosen {
        // Each reading after the last update against the step at or before it.
        let e: Vec<(usize, f64)> = events
            .iter()
            .filter_map(|ev| match ev {
                Event::Observation {
                    t_ns,
                    channel,
                    value,
                    ..
                } if *channel == c.channel && *t_ns > update_until => Some((*t_ns, *value)),
                _ => None,
            })
            .filter_map(|(t, m)| {
                let k = steps.partition_point(|s| s.t_ns <= t).checked_sub(1)?;
                let p = steps[k]
                    .predictions
                    .iter()
                    .find(|p| p.channel == c.channel)?;
                let h = ((t - update_until) / c.step_ns.max(1)) as usize;
                Some((h, p.value - m))
            })
            .collect();
        if let (false, Some(b)) = (e.is_empty(), &c.bands) {
            let (c68, c95) = b.coverage(&e);
            eprintln!(
                "{}: the grey box's CV band by horizon since the last update (from the families' CV): within the 68 % band {:.0} %, the 95 % band {:.0} % of {} readings",
                c.channel,
                100.0 * c68,
                100.0 * c95,
                e.len()
            );
        }
    }
}

/// One panel per channel the grey box serves, with its served values from `from` on.
fn grey_panels(
    steps: &[driftwatch_thermal::model::ReplayStep],
    from: i64,
    t0: i64,
) -> std::collections::BTreeMap<String, Panel> {
    let h = |t: i64| units::ns_to_h(t - t0);
    let mut panels: std::collections::BTreeMap<String, Panel> = Default::default();
    for s in steps.iter().filter(|s| s.t_ns >= from) {
        for p in &s.predictions {
            let panel = panels.entry(p.channel.clone()).or_default();
            panel.source = "grey box (one sigma)".into();
            panel.predicted.push((h(s.t_ns), p.value, p.sigma));
        }
    }
    panels
}

/// The replay against the recording's truth (`/sim/truth`), when it has one.
fn print_truth(
    recording: &std::path::Path,
    steps: &[driftwatch_thermal::model::ReplayStep],
    events: &[Event],
    from: i64,
) -> Result<()> {
    let truth = truth_of(recording)?;
    let Some((_, reference)) = truth.first() else {
        return Ok(());
    };
    let t = driftwatch_thermal::model::truth_scores(steps, events, &truth, reference, from);
    eprintln!(
        "against the recording's truth (/sim/truth) from --from on, RMS: no compensation (the first sample's truth) / last measured / served (share of the thermal error removed) / model"
    );
    for s in &t {
        let unit = driftwatch_core::error_name::channel_unit(&s.channel);
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
    Ok(())
}
