//! `driftwatch import csv`: a table of a thermal test (one row per sample time; columns of
//! spindle speed, temperatures and displacements) turned into a contract recording: `/spindle`
//! (min^-1) at every change and at every row while the spindle turns, `/temperature` (deg C) and
//! `/displacement` (um) at every row. Pure: text in, recording out; a bad cell is skipped and
//! counted, a bad time refuses the file with its row.

use std::collections::BTreeMap;

use thiserror::Error;

use driftwatch_core::recording::{
    DisplacementMsg, MachineInfo, Recording, SpindleMsg, TemperatureMsg, Timed,
};

#[derive(Debug, Error, PartialEq)]
pub enum ImportError {
    #[error("CSV: {0}")]
    Csv(String),
    #[error("column '{0}' is not in the header (columns: {1})")]
    NoColumn(String, String),
    #[error("row {row}: time '{text}' is not a number of seconds or an RFC 3339 time")]
    BadTime { row: usize, text: String },
    #[error("row {row}: time {t_s} s goes back (previous {prev_s} s)")]
    TimeBack { row: usize, t_s: f64, prev_s: f64 },
    #[error("{0}")]
    Options(String),
}

/// Where each row's time comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum RowTime {
    /// Seconds after `start_ns` in this column (or RFC 3339 times).
    Column(String),
    /// Row `i` is at `start_ns + i * interval`.
    Interval(f64),
}

#[derive(Debug, Clone, PartialEq)]
pub struct CsvOptions {
    pub time: RowTime,
    /// The time of 0 s, ns since the Unix epoch.
    pub start_ns: i64,
    pub spindle: Option<String>,
    pub temperatures: Vec<String>,
    pub displacements: Vec<String>,
    pub machine_id: String,
}

/// The recording and what was skipped (cells that are empty or not numbers, per column).
#[derive(Debug)]
pub struct Imported {
    pub recording: Recording,
    pub rows: usize,
    pub skipped: BTreeMap<String, usize>,
}

/// How the file is written: the field delimiter and the decimal mark.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CsvFormat {
    pub delimiter: u8,
    /// Numbers are written with a decimal comma (`20,5`); the delimiter is then not a comma.
    pub decimal_comma: bool,
}

impl Default for CsvFormat {
    fn default() -> Self {
        CsvFormat {
            delimiter: b',',
            decimal_comma: false,
        }
    }
}

/// [`import_csv_with`] a comma-delimited file with decimal points.
pub fn import_csv(text: &str, o: &CsvOptions) -> Result<Imported, ImportError> {
    import_csv_with(text, o, CsvFormat::default())
}

/// Import `text` written in `fmt`. A column is named by its header, or by its position as
/// `#N` (1-based; the sensor then takes the header's name).
pub fn import_csv_with(
    text: &str,
    o: &CsvOptions,
    fmt: CsvFormat,
) -> Result<Imported, ImportError> {
    check_options(o, fmt)?;
    let mut rd = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .delimiter(fmt.delimiter)
        .from_reader(text.as_bytes());
    let header: Vec<String> = rd
        .headers()
        .map_err(|e| ImportError::Csv(e.to_string()))?
        .iter()
        .map(str::to_string)
        .collect();
    let cols = Columns::of(&header, o)?;

    let mut rec = Recording {
        info: Some(MachineInfo {
            machine_id: o.machine_id.clone(),
            kinematics: String::new(),
            software: format!("driftwatch {} import csv", env!("CARGO_PKG_VERSION")),
        }),
        ..Default::default()
    };
    let mut skipped: BTreeMap<String, usize> = BTreeMap::new();
    let mut prev_t: Option<i64> = None;
    let mut last_rpm: Option<f64> = None;
    let mut rows = 0;
    for (i, r) in rd.records().enumerate() {
        let row = i + 2; // 1-based, after the header
        let r = r.map_err(|e| ImportError::Csv(e.to_string()))?;
        let t_ns = match (&o.time, cols.time) {
            (RowTime::Interval(s), _) => o.start_ns + (i as f64 * s * 1e9).round() as i64,
            (_, Some(c)) => column_time(&r, c, row, o.start_ns, fmt, prev_t)?,
            _ => unreachable!("a time column is resolved above"),
        };
        prev_t = Some(t_ns);
        rows += 1;
        let mut num = |name: &str, c: usize| -> Option<f64> {
            let cell = r.get(c).map(|v| {
                if fmt.decimal_comma {
                    v.replace(',', ".")
                } else {
                    v.to_string()
                }
            });
            match cell.as_deref().map(str::parse::<f64>) {
                Some(Ok(v)) if v.is_finite() => Some(v),
                _ => {
                    *skipped.entry(name.to_string()).or_default() += 1;
                    None
                }
            }
        };
        if let Some((name, c)) = &cols.spindle
            && let Some(rpm) = num(name, *c)
            && (last_rpm != Some(rpm) || rpm != 0.0)
        {
            rec.spindle.push(Timed {
                t_ns,
                msg: SpindleMsg { rpm },
            });
            last_rpm = Some(rpm);
        }
        for (name, c) in &cols.temperatures {
            if let Some(celsius) = num(name, *c) {
                rec.temperatures.push(Timed {
                    t_ns,
                    msg: TemperatureMsg {
                        sensor: name.clone(),
                        celsius,
                    },
                });
            }
        }
        for (name, c) in &cols.displacements {
            if let Some(um) = num(name, *c) {
                rec.displacements.push(Timed {
                    t_ns,
                    msg: DisplacementMsg {
                        sensor: name.clone(),
                        um,
                    },
                });
            }
        }
    }
    Ok(Imported {
        recording: rec,
        rows,
        skipped,
    })
}

/// Options that cannot import anything, refused before the file is read.
fn check_options(o: &CsvOptions, fmt: CsvFormat) -> Result<(), ImportError> {
    if fmt.decimal_comma && fmt.delimiter == b',' {
        return Err(ImportError::Options(
            "a decimal comma needs another delimiter (--delimiter ';' or tab)".into(),
        ));
    }
    if o.spindle.is_none() && o.temperatures.is_empty() && o.displacements.is_empty() {
        return Err(ImportError::Options(
            "nothing to import: name a spindle, temperature or displacement column".into(),
        ));
    }
    if let RowTime::Interval(s) = o.time
        && !driftwatch_core::units::positive(s)
    {
        return Err(ImportError::Options(format!(
            "--interval-s must be > 0, not {s}"
        )));
    }
    Ok(())
}

/// The columns of the options, found in the header: the time's (if any), and each sensor's
/// name (its header's) and index.
struct Columns {
    time: Option<usize>,
    spindle: Option<(String, usize)>,
    temperatures: Vec<(String, usize)>,
    displacements: Vec<(String, usize)>,
}

impl Columns {
    fn of(header: &[String], o: &CsvOptions) -> Result<Columns, ImportError> {
        let col = |name: &str| -> Result<usize, ImportError> {
            let by_index = name
                .strip_prefix('#')
                .and_then(|n| n.parse::<usize>().ok())
                .filter(|&n| n >= 1 && n <= header.len())
                .map(|n| n - 1);
            by_index
                .or_else(|| header.iter().position(|h| h == name))
                .ok_or_else(|| ImportError::NoColumn(name.to_string(), header.join(", ")))
        };
        let time = match &o.time {
            RowTime::Column(c) => Some(col(c)?),
            RowTime::Interval(_) => None,
        };
        let spindle = o.spindle.as_deref().map(col).transpose()?;
        // A column named by position takes its header's name.
        let named = |c: &String| -> Result<(String, usize), ImportError> {
            let i = col(c)?;
            Ok((header[i].clone(), i))
        };
        let temperatures: Vec<(String, usize)> = o
            .temperatures
            .iter()
            .map(named)
            .collect::<Result<_, ImportError>>()?;
        let displacements: Vec<(String, usize)> = o
            .displacements
            .iter()
            .map(named)
            .collect::<Result<_, ImportError>>()?;
        Ok(Columns {
            time,
            spindle: spindle.map(|i| (header[i].clone(), i)),
            temperatures,
            displacements,
        })
    }
}

/// The time of row `row` from its column `c`: seconds after `start_ns` or an RFC 3339 time,
/// never before the previous row's.
fn column_time(
    r: &csv::StringRecord,
    c: usize,
    row: usize,
    start_ns: i64,
    fmt: CsvFormat,
    prev_t: Option<i64>,
) -> Result<i64, ImportError> {
    let text = r.get(c).unwrap_or("");
    let seconds = if fmt.decimal_comma {
        text.replace(',', ".").parse::<f64>()
    } else {
        text.parse::<f64>()
    };
    let t_ns = match seconds {
        Ok(s) if s.is_finite() => start_ns + (s * 1e9).round() as i64,
        _ => chrono::DateTime::parse_from_rfc3339(text)
            .ok()
            .and_then(|d| d.timestamp_nanos_opt())
            .ok_or_else(|| ImportError::BadTime {
                row,
                text: text.to_string(),
            })?,
    };
    if let Some(p) = prev_t
        && t_ns < p
    {
        return Err(ImportError::TimeBack {
            row,
            t_s: (t_ns - start_ns) as f64 / 1e9,
            prev_s: (p - start_ns) as f64 / 1e9,
        });
    }
    Ok(t_ns)
}

/// The rows of `text` grouped by the value of column `col` (a thermal test of several runs
/// in one table), each part a table of its own with the header, in the order the runs first
/// appear.
pub fn split_runs(
    text: &str,
    col: &str,
    fmt: CsvFormat,
) -> Result<Vec<(String, String)>, ImportError> {
    let err = |e: csv::Error| ImportError::Csv(e.to_string());
    let mut rd = csv::ReaderBuilder::new()
        .delimiter(fmt.delimiter)
        .trim(csv::Trim::All)
        .from_reader(text.as_bytes());
    let header = rd.headers().map_err(err)?.clone();
    let at = header.iter().position(|h| h == col).ok_or_else(|| {
        ImportError::NoColumn(col.into(), header.iter().collect::<Vec<_>>().join(", "))
    })?;
    let mut parts: Vec<(String, csv::Writer<Vec<u8>>)> = Vec::new();
    for r in rd.records() {
        let r = r.map_err(err)?;
        let run = r.get(at).unwrap_or("").to_string();
        let i = match parts.iter().position(|(n, _)| *n == run) {
            Some(i) => i,
            None => {
                let mut w = csv::WriterBuilder::new()
                    .delimiter(fmt.delimiter)
                    .from_writer(Vec::new());
                w.write_record(&header).map_err(err)?;
                parts.push((run, w));
                parts.len() - 1
            }
        };
        parts[i].1.write_record(&r).map_err(err)?;
    }
    parts
        .into_iter()
        .map(|(n, w)| {
            let bytes = w
                .into_inner()
                .map_err(|e| ImportError::Csv(e.to_string()))?;
            String::from_utf8(bytes)
                .map(|t| (n, t))
                .map_err(|e| ImportError::Csv(e.to_string()))
        })
        .collect()
}

/// Keep only the displacement readings that changed (and each sensor's first): for a sensor
/// that holds its value while the machine stands, a repeated value is not a reading.
pub fn keep_changed_displacements(rec: &mut Recording) {
    let mut last: BTreeMap<String, f64> = BTreeMap::new();
    rec.displacements
        .retain(|m| last.insert(m.msg.sensor.clone(), m.msg.um) != Some(m.msg.um));
}

/// Comma-separated column lists (`a,b` or repeated flags) as one list.
pub fn split_columns(args: &[String]) -> Vec<String> {
    args.iter()
        .flat_map(|a| a.split(','))
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(str::to_string)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::units;

    fn opts() -> CsvOptions {
        CsvOptions {
            time: RowTime::Column("time_s".into()),
            start_ns: 1_000_000_000,
            spindle: Some("rpm".into()),
            temperatures: vec!["t1".into()],
            displacements: vec!["ch1".into()],
            machine_id: "m".into(),
        }
    }

    const TEXT: &str = "time_s, rpm, ch1, t1\n0,0,0.1,20\n15,0,0.2,20.1\n30,1000,0.3,\n45,1000,x,20.3\n60,0,0.5,20.4\n";

    #[test]
    fn a_table_of_runs_splits_by_its_run_column_and_a_held_value_is_no_reading() {
        let text = "run,t,x\nb,0,1\na,0,5\nb,1,1\nb,2,2\n";
        let parts = split_runs(text, "run", CsvFormat::default()).unwrap();
        assert_eq!(parts.len(), 2);
        assert_eq!(parts[0].0, "b");
        assert_eq!(parts[0].1, "run,t,x\nb,0,1\nb,1,1\nb,2,2\n");
        assert!(split_runs(text, "day", CsvFormat::default()).is_err());
        let o = CsvOptions {
            time: RowTime::Column("t".into()),
            start_ns: 0,
            spindle: None,
            temperatures: Vec::new(),
            displacements: vec!["x".into()],
            machine_id: "m".into(),
        };
        let mut im = import_csv(&parts[0].1, &o).unwrap();
        keep_changed_displacements(&mut im.recording);
        let v: Vec<f64> = im
            .recording
            .displacements
            .iter()
            .map(|m| m.msg.um)
            .collect();
        assert_eq!(v, [1.0, 2.0]);
    }

    #[test]
    fn rows_become_contract_messages() {
        let im = import_csv(TEXT, &opts()).unwrap();
        assert_eq!(im.rows, 5);
        let rpm: Vec<(i64, f64)> = im
            .recording
            .spindle
            .iter()
            .map(|m| ((m.t_ns - 1_000_000_000) / 1_000_000_000, m.msg.rpm))
            .collect();
        // At every change, and at every row while turning.
        assert_eq!(rpm, [(0, 0.0), (30, 1000.0), (45, 1000.0), (60, 0.0)]);
        assert_eq!(im.recording.temperatures.len(), 4);
        assert_eq!(im.recording.displacements.len(), 4);
        assert_eq!(im.skipped.get("t1"), Some(&1));
        assert_eq!(im.skipped.get("ch1"), Some(&1));
        assert_eq!(im.recording.displacements[3].msg.um, 0.5);
        let by_interval = CsvOptions {
            time: RowTime::Interval(10.0),
            ..opts()
        };
        let im = import_csv(TEXT, &by_interval).unwrap();
        assert_eq!(im.recording.displacements[1].t_ns, 11_000_000_000);
    }

    #[test]
    fn bad_input_is_named() {
        let e = import_csv(
            TEXT,
            &CsvOptions {
                spindle: Some("speed".into()),
                ..opts()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("'speed'"), "{e}");
        let e = import_csv(
            "time_s,rpm\n0,1\nsoon,2\n",
            &CsvOptions {
                temperatures: vec![],
                displacements: vec![],
                ..opts()
            },
        )
        .unwrap_err();
        assert_eq!(
            e,
            ImportError::BadTime {
                row: 3,
                text: "soon".into()
            }
        );
        let e = import_csv(
            "time_s,rpm\n10,1\n5,2\n",
            &CsvOptions {
                temperatures: vec![],
                displacements: vec![],
                ..opts()
            },
        )
        .unwrap_err();
        assert!(matches!(e, ImportError::TimeBack { row: 3, .. }), "{e}");
        let e = import_csv(
            TEXT,
            &CsvOptions {
                time: RowTime::Interval(0.0),
                ..opts()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("interval"), "{e}");
        assert_eq!(
            split_columns(&["a,b".into(), " c ".into()]),
            ["a", "b", "c"]
        );
    }

    /// A file from a spreadsheet set to a decimal comma: semicolons, `20,5`, columns named
    /// by position taking their header's name.
    #[test]
    fn semicolons_decimal_commas_and_columns_by_position() {
        let text = "t;rpm;Motor temp;Z um\n0;0;20,5;1,25\n60;8000;21,0;2,5\n";
        let o = CsvOptions {
            time: RowTime::Column("#1".into()),
            start_ns: 0,
            spindle: Some("#2".into()),
            temperatures: vec!["#3".into()],
            displacements: vec!["Z um".into()],
            machine_id: "m".into(),
        };
        let fmt = CsvFormat {
            delimiter: b';',
            decimal_comma: true,
        };
        let im = import_csv_with(text, &o, fmt).unwrap();
        assert!(im.skipped.is_empty(), "{:?}", im.skipped);
        let r = &im.recording;
        assert_eq!(r.temperatures[1].msg.sensor, "Motor temp");
        assert_eq!(r.temperatures[0].msg.celsius, 20.5);
        assert_eq!(r.displacements[1].msg.um, 2.5);
        assert_eq!(r.spindle.last().unwrap().msg.rpm, 8000.0);
        assert_eq!(r.temperatures[1].t_ns, units::NS_PER_MIN);
        // Read as the default (comma, decimal point) the cells are not numbers.
        assert!(import_csv(text, &o).is_err());
        // A decimal comma with a comma delimiter is ambiguous, and refused.
        let e = import_csv_with(
            text,
            &o,
            CsvFormat {
                delimiter: b',',
                decimal_comma: true,
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("decimal comma"), "{e}");
        let mut past = o.clone();
        past.temperatures = vec!["#9".into()];
        assert!(import_csv_with(text, &past, fmt).is_err());
    }
}
