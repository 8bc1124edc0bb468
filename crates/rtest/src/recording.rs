//! R-test runs as recording messages (`docs/recording-format.md`, topics `/rtest/setup` and
//! `/rtest/reading`) and back: the shell writes and reads the MCAP file, this module only
//! turns runs into messages and messages into runs, checking every field.

use std::collections::BTreeMap;

use driftwatch_core::geometry::{Mat3, Vec3};
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY};
use serde::{Deserialize, Serialize};

use crate::instrument::{Calibration, Setting};
use crate::kinematic_test::{Point, Run, TestKind, TestSpec};

pub use driftwatch_core::recording::TOPIC_RTEST_READING as TOPIC_READING;
pub use driftwatch_core::recording::TOPIC_RTEST_SETUP as TOPIC_SETUP;

/// `/rtest/setup`: one per run, before its readings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SetupMsg {
    pub run: i64,
    /// "BK1", "BK2", "XYC" (or another name: processed the same way).
    pub test: String,
    /// "E", "J" or "Es".
    pub setting: String,
    /// The turning rotary axis, by the machine's name for it.
    pub axis: String,
    /// Programmed centre of the table-side object, table frame, mm.
    pub ball_mm: [f64; 3],
    /// Sensitivity matrix, readings (um) = G * displacement (um, nest frame), rows per sensor.
    pub sensitivity: [[f64; 3]; 3],
    pub sensitivity_source: String,
    /// Covariance of each row of G (dimensionless); absent: zero.
    #[serde(default)]
    pub sensitivity_row_cov: Option<[[f64; 3]; 3]>,
    pub reading_sigma_um: f64,
    #[serde(default)]
    pub sphericity_um: f64,
}

/// `/rtest/reading`: one reading of the three sensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReadingMsg {
    pub run: i64,
    pub index: usize,
    /// Commanded angles, as in `/probe/detection` (`b_deg` carries the tilting axis).
    pub b_deg: f64,
    pub c_deg: f64,
    /// Commanded linear-axis position, mm.
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    /// Sensor readings, um.
    pub u_um: f64,
    pub v_um: f64,
    pub w_um: f64,
}

fn rows(m: &Mat3) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)]])
}

fn mat(r: &[[f64; 3]; 3]) -> Mat3 {
    Mat3::from_fn(|i, j| r[i][j])
}

/// A run and the calibration it is processed with, as messages with their log times.
pub fn to_messages(
    k: &Kinematics,
    run: &Run,
    cal: &Calibration,
    number: i64,
) -> (SetupMsg, Vec<(i64, ReadingMsg)>) {
    let setup = SetupMsg {
        run: number,
        test: run.spec.kind.name().to_string(),
        setting: run.setting.name().to_string(),
        axis: k.rotary[run.spec.axis].name.clone(),
        ball_mm: [run.spec.ball_mm.x, run.spec.ball_mm.y, run.spec.ball_mm.z],
        sensitivity: rows(&cal.g),
        sensitivity_source: cal.source.clone(),
        sensitivity_row_cov: Some(rows(&cal.row_cov)),
        reading_sigma_um: cal.reading_sigma_um,
        sphericity_um: cal.sphericity_um,
    };
    let readings = run
        .points
        .iter()
        .map(|p| {
            let (b, c) = k.fields_from_angles(&p.angles_deg);
            (
                p.t_ns,
                ReadingMsg {
                    run: number,
                    index: p.index,
                    b_deg: b,
                    c_deg: c,
                    x_mm: p.commanded_mm.x,
                    y_mm: p.commanded_mm.y,
                    z_mm: p.commanded_mm.z,
                    u_um: p.readings_um[0],
                    v_um: p.readings_um[1],
                    w_um: p.readings_um[2],
                },
            )
        })
        .collect();
    (setup, readings)
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecordingError {
    #[error("{topic} message {n}: {detail}")]
    Message {
        topic: &'static str,
        n: usize,
        detail: String,
    },
    #[error("run {run}: {detail}")]
    Run { run: i64, detail: String },
    #[error("the recording has no {TOPIC_SETUP} messages (no R-test runs)")]
    NoRuns,
}

/// Runs from the messages of a recording: `(topic, log time, JSON bytes)` in file order.
pub fn from_messages(
    k: &Kinematics,
    messages: &[(String, i64, Vec<u8>)],
) -> Result<Vec<(Run, Calibration)>, RecordingError> {
    let mut setups: BTreeMap<i64, SetupMsg> = BTreeMap::new();
    let mut readings: BTreeMap<i64, Vec<(i64, ReadingMsg)>> = BTreeMap::new();
    for (n, (topic, t_ns, data)) in messages.iter().enumerate() {
        match topic.as_str() {
            TOPIC_SETUP => {
                let m: SetupMsg =
                    serde_json::from_slice(data).map_err(|e| RecordingError::Message {
                        topic: TOPIC_SETUP,
                        n,
                        detail: e.to_string(),
                    })?;
                setups.insert(m.run, m);
            }
            TOPIC_READING => {
                let m: ReadingMsg =
                    serde_json::from_slice(data).map_err(|e| RecordingError::Message {
                        topic: TOPIC_READING,
                        n,
                        detail: e.to_string(),
                    })?;
                readings.entry(m.run).or_default().push((*t_ns, m));
            }
            _ => {}
        }
    }
    if setups.is_empty() {
        return Err(RecordingError::NoRuns);
    }
    let mut out = Vec::new();
    for (run, s) in setups {
        let bad = |detail: String| RecordingError::Run { run, detail };
        let setting = Setting::parse(&s.setting)
            .ok_or_else(|| bad(format!("setting '{}' is not E, J or Es", s.setting)))?;
        let axis = k
            .rotary
            .iter()
            .position(|a| a.name == s.axis)
            .ok_or_else(|| bad(format!("{} has no axis '{}'", k.name, s.axis)))?;
        let numbers = s
            .sensitivity
            .iter()
            .flatten()
            .chain(&s.ball_mm)
            .chain(std::iter::once(&s.reading_sigma_um));
        if numbers.clone().any(|v| !v.is_finite()) {
            return Err(bad("a set-up number is not finite".into()));
        }
        if s.reading_sigma_um <= 0.0 {
            return Err(bad("reading_sigma_um must be positive".into()));
        }
        let g = mat(&s.sensitivity);
        if g.try_inverse().is_none() {
            return Err(bad("the sensitivity matrix is singular".into()));
        }
        let mut rs = readings.remove(&run).unwrap_or_default();
        if rs.is_empty() {
            return Err(bad("no readings".into()));
        }
        rs.sort_by_key(|(t, m)| (m.index, *t));
        let mut points = Vec::with_capacity(rs.len());
        for (t_ns, m) in &rs {
            let values = [
                m.b_deg, m.c_deg, m.x_mm, m.y_mm, m.z_mm, m.u_um, m.v_um, m.w_um,
            ];
            if values.iter().any(|v| !v.is_finite()) {
                return Err(bad(format!(
                    "reading {} has a value that is not finite",
                    m.index
                )));
            }
            let angles_deg: [f64; MAX_ROTARY] = k.angles_from_fields(m.b_deg, m.c_deg);
            points.push(Point {
                index: m.index,
                angles_deg,
                commanded_mm: Vec3::new(m.x_mm, m.y_mm, m.z_mm),
                readings_um: [m.u_um, m.v_um, m.w_um],
                t_ns: *t_ns,
            });
        }
        let sweep: Vec<f64> = points.iter().map(|p| p.angles_deg[axis]).collect();
        let from = sweep.iter().cloned().fold(f64::MAX, f64::min);
        let to = sweep.iter().cloned().fold(f64::MIN, f64::max);
        let spec = TestSpec {
            kind: TestKind::parse(&s.test).unwrap_or(TestKind::Xyc),
            axis,
            fixed_deg: points[0].angles_deg,
            from_deg: from,
            to_deg: to,
            step_deg: 0.0,
            bidirectional: false,
            ball_mm: Vec3::new(s.ball_mm[0], s.ball_mm[1], s.ball_mm[2]),
            feed_mm_min: 0.0,
            dwell_s: 0.0,
        };
        if TestKind::parse(&s.test).is_none() {
            return Err(bad(format!("test '{}' is not BK1, BK2 or XYC", s.test)));
        }
        let cal = Calibration {
            setting,
            g,
            source: s.sensitivity_source.clone(),
            reading_sigma_um: s.reading_sigma_um,
            residual_rms_um: 0.0,
            row_cov: s.sensitivity_row_cov.map(|r| mat(&r)).unwrap_or_default(),
            sphericity_um: s.sphericity_um.max(0.0),
        };
        out.push((
            Run {
                spec,
                setting,
                points,
            },
            cal,
        ));
    }
    if let Some((run, _)) = readings.into_iter().next() {
        return Err(RecordingError::Run {
            run,
            detail: format!("readings without a {TOPIC_SETUP} message"),
        });
    }
    Ok(out)
}

/// Runs from a device's CSV export: a header row, then one row per reading with the columns
/// `angle_deg,u_um,v_um,w_um` and optionally `x_mm,y_mm,z_mm` (commanded position) and
/// `t_s` (time from the start). `spec` says which test, axis, fixed angles and ball centre;
/// the calibration comes with the device.
pub fn from_csv(
    text: &str,
    spec: &TestSpec,
    setting: Setting,
    start_ns: i64,
) -> Result<Run, RecordingError> {
    let bad = |n: usize, detail: String| RecordingError::Message {
        topic: "csv",
        n,
        detail,
    };
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let header: Vec<String> = lines
        .next()
        .ok_or_else(|| bad(0, "empty file".into()))?
        .split(',')
        .map(|h| h.trim().to_ascii_lowercase())
        .collect();
    let col = |name: &str| header.iter().position(|h| h == name);
    let need = |name: &str| {
        col(name).ok_or_else(|| {
            bad(
                1,
                format!("no column '{name}' (header: {})", header.join(",")),
            )
        })
    };
    let (ca, cu, cv, cw) = (
        need("angle_deg")?,
        need("u_um")?,
        need("v_um")?,
        need("w_um")?,
    );
    let (cx, cy, cz, ct) = (col("x_mm"), col("y_mm"), col("z_mm"), col("t_s"));
    let mut points = Vec::new();
    for (i, line) in lines.enumerate() {
        let row = i + 2;
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        let get = |c: usize| -> Result<f64, RecordingError> {
            let s = cells
                .get(c)
                .ok_or_else(|| bad(row, format!("line {row}: only {} cells", cells.len())))?;
            let v: f64 = s
                .parse()
                .map_err(|_| bad(row, format!("line {row}: '{s}' is not a number")))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(bad(row, format!("line {row}: '{s}' is not finite")))
            }
        };
        let mut angles = spec.fixed_deg;
        angles[spec.axis] = get(ca)?;
        let commanded = match (cx, cy, cz) {
            (Some(x), Some(y), Some(z)) => Vec3::new(get(x)?, get(y)?, get(z)?),
            _ => Vec3::zeros(),
        };
        let t_ns = match ct {
            Some(c) => start_ns + (get(c)? * 1e9).round() as i64,
            None => start_ns + i as i64 * 1_000_000_000,
        };
        points.push(Point {
            index: i,
            angles_deg: angles,
            commanded_mm: commanded,
            readings_um: [get(cu)?, get(cv)?, get(cw)?],
            t_ns,
        });
    }
    if points.is_empty() {
        return Err(bad(2, "no readings".into()));
    }
    Ok(Run {
        spec: spec.clone(),
        setting,
        points,
    })
}
