//! Diagnosis of where a model and a recording differ (issue 5), pure code. This first part
//! turns detections into the rows every later step works on: each reading's deviation from
//! its nominal value, its sensitivity to the location errors and the nuisances the plan
//! supports (the linear design of `identify`), and the event-level fields an effect's
//! signature depends on (pose, approach, feed, speed, time within the cycle, the sense each
//! rotary axis last moved in).

use std::collections::BTreeMap;

use serde::Serialize;
use thiserror::Error;

use crate::identify::{Identifier, SolveError, SolveOptions};
use crate::kinematics::{Kinematics, MAX_ROTARY};
use crate::measurement::Axis;
use crate::recording::{DetectionMsg, Timed};

#[derive(Debug, Error)]
pub enum DiagnosisError {
    #[error("no usable detections")]
    NoDetections,
    #[error("cycle {cycle}: {source}")]
    Cycle { cycle: i64, source: SolveError },
}

/// One detection as the diagnosis sees it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectionRow {
    pub t_ns: i64,
    pub cycle: i64,
    pub step: String,
    pub b_deg: f64,
    pub c_deg: f64,
    pub axis: Axis,
    pub direction: i8,
    pub feed_mm_min: f64,
    pub spindle_rpm: f64,
    /// Seconds since the first detection of its cycle.
    pub t_in_cycle_s: f64,
    /// The sense each rotary axis last moved in before this approach (-1, 0 before any
    /// move, +1), from the order of the detections.
    pub rotary_sense: [i8; MAX_ROTARY],
    /// The reading minus its nominal value, um.
    pub deviation_um: f64,
    /// Reading change per unit of each design parameter, um.
    pub sensitivity: Vec<f64>,
}

/// The rows of a recording and the names of their sensitivity columns.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Rows {
    pub params: Vec<String>,
    pub rows: Vec<DetectionRow>,
}

/// Rows of every tripped detection, cycle by cycle in time order. The design's parameters
/// are chosen once, on the first cycle's geometry, so that every row has the same columns;
/// no drift rates (every row has its own time).
pub fn detection_rows(
    k: &Kinematics,
    detections: &[Timed<DetectionMsg>],
    opts: &SolveOptions,
) -> Result<Rows, DiagnosisError> {
    let mut cycles: BTreeMap<i64, Vec<&Timed<DetectionMsg>>> = BTreeMap::new();
    for d in detections.iter().filter(|d| d.msg.status.is_none()) {
        cycles.entry(d.msg.cycle).or_default().push(d);
    }
    for v in cycles.values_mut() {
        v.sort_by_key(|d| d.t_ns);
    }
    let mut ordered: Vec<(i64, Vec<&Timed<DetectionMsg>>)> = cycles.into_iter().collect();
    ordered.sort_by_key(|(_, v)| v.first().map_or(i64::MAX, |d| d.t_ns));
    let Some((first_cycle, first)) = ordered.first() else {
        return Err(DiagnosisError::NoDetections);
    };
    let obs = |v: &[&Timed<DetectionMsg>]| -> Vec<crate::identify::Observation> {
        v.iter()
            .map(|d| crate::cycle::observation(k, d.t_ns, &d.msg))
            .collect()
    };
    let template = obs(first);
    // Each row has its own time, so drift within a cycle is the time model's to carry, not a
    // per-cycle rate's.
    let opts = SolveOptions {
        drift_rates: crate::identify::DriftRates::Never,
        ..opts.clone()
    };
    let id = Identifier::new(k, &template, &opts).map_err(|source| DiagnosisError::Cycle {
        cycle: *first_cycle,
        source,
    })?;
    let mut params = Vec::new();
    let mut rows = Vec::new();
    let mut sense = crate::kinematics::RotarySense::default();
    for (cycle, dets) in &ordered {
        let o = obs(dets);
        let design = id
            .nominal_design(&o)
            .map_err(|source| DiagnosisError::Cycle {
                cycle: *cycle,
                source,
            })?;
        params.clone_from(&design.params);
        let t0 = dets.first().map_or(0, |d| d.t_ns);
        for (i, (d, ob)) in dets.iter().zip(&o).enumerate() {
            let rotary_sense = sense.go_to(&ob.angles);
            rows.push(DetectionRow {
                t_ns: d.t_ns,
                cycle: *cycle,
                step: d.msg.step.clone(),
                b_deg: d.msg.b_deg,
                c_deg: d.msg.c_deg,
                axis: d.msg.axis,
                direction: d.msg.direction,
                feed_mm_min: d.msg.feed_mm_min,
                spindle_rpm: d.msg.spindle_rpm,
                t_in_cycle_s: (d.t_ns - t0) as f64 / 1e9,
                rotary_sense,
                deviation_um: (ob.reading() - design.nominal_mm[i]) * 1e3,
                sensitivity: design.sensitivity_um.row(i).iter().copied().collect(),
            });
        }
    }
    Ok(Rows { params, rows })
}

/// The baseline of physics.md 4.6: every design parameter (the location errors and the
/// nuisances) as an offset plus gains on the spindle pole basis, fitted jointly to every
/// detection at its own time. Clean data must fit it to the noise before any search.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Baseline {
    /// `<parameter>` (offset) and `<parameter>*spindle_lag_<tau>min`, in column order.
    pub columns: Vec<String>,
    pub coef: Vec<f64>,
    /// Residual of every row, um.
    pub residual_um: Vec<f64>,
    pub chi2: f64,
    pub dof: usize,
    pub chi2_dof: f64,
}

/// Fit the baseline to `rows` with the spindle log `spindle` (every speed change, the
/// cycles' own spins included) and one-reading uncertainty `sigma_um`.
pub fn fit_baseline(
    rows: &Rows,
    spindle: &[crate::thermal_model::Event],
    cfg: &crate::thermal_model::ModelConfig,
    sigma_um: f64,
) -> Result<Baseline, DiagnosisError> {
    use crate::thermal_model::{Event, Features};
    use nalgebra::{DMatrix, DVector};
    if rows.rows.is_empty() {
        return Err(DiagnosisError::NoDetections);
    }
    let spindle_only = crate::thermal_model::ModelConfig {
        temperatures: Vec::new(),
        instant_speed: false,
        ..cfg.clone()
    };
    let t0 = spindle
        .first()
        .map_or(rows.rows[0].t_ns, Event::t_ns)
        .min(rows.rows[0].t_ns);
    let mut f = Features::new(&spindle_only, &BTreeMap::new(), t0);
    let mut order: Vec<usize> = (0..rows.rows.len()).collect();
    order.sort_by_key(|i| rows.rows[*i].t_ns);
    let basis = 1 + spindle_only.taus_min.len();
    let p = rows.params.len() * basis;
    let n = rows.rows.len();
    let mut a = DMatrix::zeros(n, p);
    let mut k_ev = 0;
    for &i in &order {
        let r = &rows.rows[i];
        while k_ev < spindle.len() && spindle[k_ev].t_ns() <= r.t_ns {
            f.apply(&spindle[k_ev]);
            k_ev += 1;
        }
        f.advance_to(r.t_ns);
        let x = f.row();
        for (j, s) in r.sensitivity.iter().enumerate() {
            for (b, xb) in x.iter().enumerate() {
                a[(i, j * basis + b)] = s * xb / sigma_um;
            }
        }
    }
    let y = DVector::from_iterator(n, rows.rows.iter().map(|r| r.deviation_um / sigma_um));
    let svd = a.clone().svd(true, true);
    let tol = svd.singular_values.max() * 1e-10;
    let rank = svd.singular_values.iter().filter(|s| **s > tol).count();
    let beta = svd
        .solve(&y, tol)
        .map_err(|_| DiagnosisError::NoDetections)?;
    let resid = &y - &a * &beta;
    let chi2 = resid.dot(&resid);
    let dof = n.saturating_sub(rank).max(1);
    let mut columns = Vec::with_capacity(p);
    for name in &rows.params {
        columns.push(name.clone());
        for t in &spindle_only.taus_min {
            columns.push(format!("{name}*spindle_lag_{t}min"));
        }
    }
    Ok(Baseline {
        columns,
        coef: beta.iter().copied().collect(),
        residual_um: resid.iter().map(|r| r * sigma_um).collect(),
        chi2,
        dof,
        chi2_dof: chi2 / dof as f64,
    })
}

/// A group of readings whose residuals do not average to zero.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Mismatch {
    /// What the readings are grouped by (`approach`, `pose`, `B sense`, ...).
    pub by: String,
    pub group: String,
    pub n: usize,
    pub mean_um: f64,
    /// The mean in units of its standard error, `sigma / sqrt(n)`.
    pub t: f64,
}

/// Where the residuals are systematic: the mean residual of the readings grouped by approach
/// (axis and direction), pose, the sense each rotary axis last moved in and the time within
/// the cycle (15-s bins), every group with `|t| >= t_min`, largest first.
pub fn locate(rows: &Rows, residual_um: &[f64], sigma_um: f64, t_min: f64) -> Vec<Mismatch> {
    type Key = fn(&DetectionRow) -> String;
    let groupings: [(&str, Key); 5] = [
        ("approach", |r| {
            format!(
                "{}{}",
                r.axis.name(),
                if r.direction > 0 { "+" } else { "-" }
            )
        }),
        ("pose", |r| format!("B{} C{}", r.b_deg, r.c_deg)),
        ("B sense", |r| format!("{:+}", r.rotary_sense[0])),
        ("C sense", |r| format!("{:+}", r.rotary_sense[1])),
        ("time in cycle", |r| {
            let bin = (r.t_in_cycle_s / 15.0).floor() * 15.0;
            format!("{bin}-{} s", bin + 15.0)
        }),
    ];
    let mut out = Vec::new();
    for (by, key) in groupings {
        let mut groups: BTreeMap<String, (usize, f64)> = BTreeMap::new();
        for (r, e) in rows.rows.iter().zip(residual_um) {
            let g = groups.entry(key(r)).or_default();
            g.0 += 1;
            g.1 += e;
        }
        for (group, (n, sum)) in groups {
            let mean = sum / n as f64;
            let t = mean / (sigma_um / (n as f64).sqrt());
            if t.abs() >= t_min {
                out.push(Mismatch {
                    by: by.to_string(),
                    group,
                    n,
                    mean_um: mean,
                    t,
                });
            }
        }
    }
    out.sort_by(|a, b| b.t.abs().total_cmp(&a.t.abs()));
    out
}
