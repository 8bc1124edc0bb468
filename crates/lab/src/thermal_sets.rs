//! Thermal-test data sets on disk, for `bench thermal --data DIR`: a folder holds a
//! `manifest.toml` (or several `manifest*.toml`, one set each) beside its CSV files. The
//! manifest names the columns, their units' roles, the runs (one file per run, or a run
//! column), which readings are real, and where a run's fit ends. Every key is documented in
//! `docs/thermal-sets.md`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use driftwatch_recording::csv_import::{
    CsvFormat, CsvOptions, RowTime, import_csv_with, keep_changed_displacements, split_runs,
};
use driftwatch_thermal::model::{Event, events_from};

#[derive(Debug, serde::Deserialize)]
#[serde(untagged)]
enum OneOrMany {
    One(String),
    Many(Vec<String>),
}

/// `manifest.toml`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    name: String,
    #[serde(default)]
    source: String,
    #[serde(default)]
    licence: String,
    #[serde(default)]
    description: String,
    /// One CSV per run, or one CSV (with `run` naming the run column when it holds several).
    csv: OneOrMany,
    run: Option<String>,
    /// The time column (seconds, or RFC 3339), or `interval_s` between rows.
    time: Option<String>,
    interval_s: Option<f64>,
    spindle: Option<String>,
    #[serde(default)]
    temperatures: Vec<String>,
    displacements: Vec<String>,
    /// `changed`: the displacement sensor holds its value between real updates, so a row
    /// whose value did not change is not a reading.
    valid: Option<String>,
    #[serde(default = "comma")]
    delimiter: String,
    #[serde(default)]
    decimal_comma: bool,
    /// Within a run: fit on this share of it (default 0.55), or on its first `fit_h` hours.
    fit_share: Option<f64>,
    fit_h: Option<f64>,
    /// Grid step of the families, min (default: the rows' median spacing, at least a
    /// 400th of the shortest run).
    step_min: Option<f64>,
}

fn comma() -> String {
    ",".into()
}

/// One run of a set: its name and events (time from 0 at the run's first row).
pub struct Run {
    pub name: String,
    pub events: Vec<Event>,
}

/// A data set ready for the bench.
pub struct ThermalData {
    pub name: String,
    pub source: String,
    pub licence: String,
    pub description: String,
    pub runs: Vec<Run>,
    pub channels: Vec<String>,
    pub inputs: String,
    pub fit_share: f64,
    pub fit_h: Option<f64>,
    pub step_min: Option<f64>,
}

/// Every set under `dir`: its own manifests and those of its subfolders, sorted by path.
pub fn load_all(dir: &Path) -> Result<Vec<ThermalData>> {
    let mut manifests: Vec<PathBuf> = Vec::new();
    let mut look = |d: &Path| -> Result<()> {
        for e in std::fs::read_dir(d).with_context(|| format!("reading {}", d.display()))? {
            let p = e?.path();
            let is_manifest = p
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("manifest") && n.ends_with(".toml"));
            if is_manifest {
                manifests.push(p);
            }
        }
        Ok(())
    };
    look(dir)?;
    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let p = e?.path();
        if p.is_dir() {
            look(&p)?;
        }
    }
    manifests.sort();
    manifests.iter().map(|m| load(m)).collect()
}

/// One set from its manifest.
pub fn load(manifest: &Path) -> Result<ThermalData> {
    let text = std::fs::read_to_string(manifest)
        .with_context(|| format!("reading {}", manifest.display()))?;
    let m: Manifest =
        toml::from_str(&text).with_context(|| format!("parsing {}", manifest.display()))?;
    let dir = manifest.parent().unwrap_or(Path::new("."));
    let files = match &m.csv {
        OneOrMany::One(f) => vec![f.clone()],
        OneOrMany::Many(v) => v.clone(),
    };
    anyhow::ensure!(
        m.valid.as_deref().is_none_or(|v| v == "changed"),
        "{}: valid = {:?}: the only rule is \"changed\"",
        manifest.display(),
        m.valid
    );
    let fmt = CsvFormat {
        delimiter: *m.delimiter.as_bytes().first().unwrap_or(&b','),
        decimal_comma: m.decimal_comma,
    };
    let opts = CsvOptions {
        time: match (&m.time, m.interval_s) {
            (Some(c), _) => RowTime::Column(c.clone()),
            (None, Some(s)) => RowTime::Interval(s),
            (None, None) => anyhow::bail!("{}: give time or interval_s", manifest.display()),
        },
        start_ns: 0,
        spindle: m.spindle.clone(),
        temperatures: m.temperatures.clone(),
        displacements: m.displacements.clone(),
        machine_id: m.name.clone(),
    };
    let mut runs = Vec::new();
    for f in &files {
        let path = dir.join(f);
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let parts = match &m.run {
            Some(col) => split_runs(&text, col, fmt)
                .with_context(|| format!("{}: run column {col}", path.display()))?,
            None => vec![(f.trim_end_matches(".csv").to_string(), text)],
        };
        for (name, text) in parts {
            let mut im = import_csv_with(&text, &opts, fmt)
                .with_context(|| format!("importing {} (run {name})", path.display()))?;
            if m.valid.is_some() {
                keep_changed_displacements(&mut im.recording);
            }
            runs.push(Run {
                name,
                events: events_from(&[im.recording]),
            });
        }
    }
    let inputs = format!(
        "{}{} temperatures",
        if m.spindle.is_some() {
            "spindle + "
        } else {
            ""
        },
        m.temperatures.len()
    );
    Ok(ThermalData {
        name: m.name,
        source: m.source,
        licence: m.licence,
        description: m.description,
        runs,
        channels: m.displacements,
        inputs,
        fit_share: m.fit_share.unwrap_or(0.55),
        fit_h: m.fit_h,
        step_min: m.step_min,
    })
}
