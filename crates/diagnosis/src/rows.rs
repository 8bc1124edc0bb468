//! Detections as rows: each reading's deviation from its nominal value, its sensitivity to the
//! location errors and the nuisances the plan supports (the linear design of `identify`), the
//! signatures of the quantities outside that design (from the exact trip model), and the
//! event-level fields an effect's signature depends on (pose, approach, feed, speed, time within
//! the cycle, the sense each rotary axis last moved in). Every step of the cycle diagnosis and
//! the effect library work on these rows.

use std::collections::BTreeMap;

use serde::Serialize;
use thiserror::Error;

use driftwatch_core::identify::{Identifier, SolveError, SolveOptions};
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY};
use driftwatch_core::measurement::Axis;
use driftwatch_core::recording::{DetectionMsg, Timed};

#[derive(Debug, Error)]
pub enum DiagnosisError {
    #[error("no usable detections")]
    NoDetections,
    #[error("cycle {cycle}: {source}")]
    Cycle { cycle: i64, source: SolveError },
    #[error(
        "sigma_um must be between {lo} and {hi} um (one reading's noise), not {sigma:e}",
        lo = SIGMA_UM_RANGE.0,
        hi = SIGMA_UM_RANGE.1
    )]
    BadSigma { sigma: f64 },
}

/// The reading noise a diagnosis accepts, um: below a nanometre no setter reads, and the
/// whitened design would be numerically empty (an SVD of nothing); above 100 um a reading
/// says nothing about micrometre errors.
pub const SIGMA_UM_RANGE: (f64, f64) = (1e-3, 100.0);

/// One detection as the diagnosis sees it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectionRow {
    pub t_ns: i64,
    pub cycle: i64,
    /// What was measured (pose, approach, feed; see `cycle::MeasurementKey`), not the free label.
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
    /// Reading change per unit of each physical quantity outside the design
    /// ([`Rows::signatures`]), um, from the exact measurement model.
    pub signature: Vec<f64>,
}

/// The rows of a recording and the names of their sensitivity columns.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Rows {
    pub params: Vec<String>,
    /// The design parameters that are location errors (the rest are nuisances).
    pub locations: Vec<String>,
    /// Names of the signature columns: see [`SIGNATURES`].
    pub signatures: Vec<String>,
    pub rows: Vec<DetectionRow>,
}

impl Rows {
    pub fn param(&self, name: &str) -> Option<usize> {
        self.params.iter().position(|p| p == name)
    }
    pub fn signature(&self, name: &str) -> Option<usize> {
        self.signatures.iter().position(|p| p == name)
    }
}

/// Physical quantities outside the six location errors whose footprint on every reading the
/// rows carry, with their units. The names are the simulator's truth channels; `angle_<axis>`
/// is the angular positioning error of a rotary axis at its pose.
pub const SIGNATURES: &[(&str, &str)] = &[
    ("sx", "um"),
    ("sy", "um"),
    ("sz", "um"),
    ("setter_x", "um"),
    ("setter_y", "um"),
    ("setter_z", "um"),
    ("radius", "um"),
    ("latency", "ms"),
    ("kx", "ppm"),
    ("ky", "ppm"),
    ("kz", "ppm"),
    ("sxy", "urad"),
    ("sxz", "urad"),
    ("syz", "urad"),
];

/// Apply one unit (um, ms, ppm, urad) of signature `i` (in [`SIGNATURES`], then one angle per
/// rotary axis), times `x`, to a state.
fn perturb(s: &mut driftwatch_core::kinematics::MachineState, i: usize, x: f64) {
    match i {
        0..=2 => s.tool_tip[i] += x * 1e-3,
        3..=5 => s.beam_point[i - 3] += x * 1e-3,
        6 => s.radius += x * 1e-3,
        7 => s.latency_s += x * 1e-3,
        8..=10 => s.linear.k[i - 8] += x * 1e-6,
        11 => s.linear.sxy += x * 1e-6,
        12 => s.linear.sxz += x * 1e-6,
        13 => s.linear.syz += x * 1e-6,
        _ => s.angle_error[i - SIGNATURES.len()] += x * 1e-6,
    }
}

/// The signatures of one observation: central differences of the exact trip, um per unit.
fn signatures_of(k: &Kinematics, o: &driftwatch_core::identify::Observation, n: usize) -> Vec<f64> {
    let s0 = k.nominal_state();
    (0..n)
        .map(|i| {
            let at = |x: f64| {
                let mut s = s0;
                perturb(&mut s, i, x);
                driftwatch_core::measurement::latched(
                    k,
                    &s,
                    &o.angles,
                    &o.approach,
                    &o.position,
                    None,
                )
            };
            match (at(1.0), at(-1.0)) {
                (Ok(p), Ok(m)) => (p - m) / 2.0 * 1e3,
                _ => 0.0,
            }
        })
        .collect()
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
    for d in detections
        .iter()
        .filter(|d| d.msg.status() == driftwatch_core::recording::DetectionStatus::Ok)
    {
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
    let obs = |v: &[&Timed<DetectionMsg>]| -> Vec<driftwatch_core::identify::Observation> {
        v.iter()
            .map(|d| driftwatch_core::cycle::observation(k, d.t_ns, &d.msg))
            .collect()
    };
    let template = obs(first);
    // Each row has its own time, so drift within a cycle is the time model's to carry, not a
    // per-cycle rate's.
    let opts = SolveOptions {
        drift_rates: driftwatch_core::identify::DriftRates::Never,
        ..opts.clone()
    };
    let id = Identifier::new(k, &template, &opts).map_err(|source| DiagnosisError::Cycle {
        cycle: *first_cycle,
        source,
    })?;
    let mut signatures: Vec<String> = SIGNATURES.iter().map(|(n, _)| n.to_string()).collect();
    for ax in &k.rotary {
        signatures.push(format!("angle_{}", ax.name));
    }
    let mut params = Vec::new();
    let mut rows = Vec::new();
    let mut sense = driftwatch_core::kinematics::RotarySense::default();
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
                // Labels are free: the channel is what was measured.
                step: driftwatch_core::cycle::MeasurementKey::of_detection(&d.msg).to_string(),
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
                signature: signatures_of(k, ob, signatures.len()),
            });
        }
    }
    let names = k.identify_names();
    Ok(Rows {
        locations: params
            .iter()
            .filter(|p| names.contains(p))
            .cloned()
            .collect(),
        params,
        signatures,
        rows,
    })
}
