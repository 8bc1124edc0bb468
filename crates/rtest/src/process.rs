//! From readings to deviations: sensor readings -> ball-centre displacement in the nest frame
//! (`G^-1 r`) -> the deviation of the spindle-side object from the table-side one in table
//! coordinates (E, J: the nest frame is the table frame; Es: the nest turns with the head, so
//! the displacement is negated and turned by the nominal head and table rotations, the seed's
//! equation (2) on a C table) -> machine coordinates -> radial, axial and tangential
//! components against the turning axis (ISO 10791-6: radial from the axis to the ball,
//! axial along the axis, tangential their cross product in the turning sense) -> the test's
//! figures.

use driftwatch_core::geometry::{Mat3, Vec3};
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::instrument::{Calibration, Setting};
use crate::kinematic_test::{Run, axis_line, nominal_rotations};

/// One processed reading.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Deviation {
    pub index: usize,
    pub angles_deg: [f64; MAX_ROTARY],
    /// The turning axis' commanded angle, deg.
    pub angle_deg: f64,
    pub t_ns: i64,
    /// Ball centre from the nest centre, nest frame, um.
    pub nest_um: Vec3,
    /// Spindle-side object from the table-side object, table frame, um.
    pub table_um: Vec3,
    /// The same in the machine frame at the pose, um.
    pub machine_um: Vec3,
    pub radial_um: f64,
    pub axial_um: f64,
    pub tangential_um: f64,
    /// Covariance of `table_um` from this reading alone, um^2.
    #[serde(skip)]
    pub cov_table: Mat3,
    /// The turn from the nest frame to the table frame.
    #[serde(skip)]
    pub nest_to_table: Mat3,
    /// Where each sensor touches the ball (outward normal, the ball's own frame), now and
    /// at the device's zero: the ball's form error is the difference of the two.
    #[serde(skip)]
    pub contacts: [(Vec3, Vec3); 3],
}

/// The figures of one direction over a test.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Figures {
    /// Largest minus smallest, um.
    pub range_um: f64,
    /// Largest magnitude, um.
    pub max_abs_um: f64,
    pub mean_um: f64,
    /// Once-per-revolution component fitted over the turning angle: amplitude (um) and the
    /// angle of its maximum (deg). Only over sweeps of at least 180 deg.
    pub first_harmonic_um: Option<f64>,
    pub first_harmonic_peak_deg: Option<f64>,
    /// Largest difference between the out and back readings at one angle, um.
    pub reversal_um: Option<f64>,
}

/// A processed test.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Processed {
    pub test: &'static str,
    pub setting: Setting,
    pub axis: String,
    pub calibration: String,
    /// The programmed centre of the table-side object, table frame, mm.
    pub ball_mm: Vec3,
    /// The inverse sensitivity matrix used and the covariance of each of its rows: the
    /// calibration's systematic part, for the identification.
    #[serde(skip)]
    pub g_inv: Mat3,
    #[serde(skip)]
    pub g_row_cov: Mat3,
    /// The ball's sphericity, um (its form is propagated as a systematic).
    pub sphericity_um: f64,
    pub points: Vec<Deviation>,
    pub radial: Figures,
    pub axial: Figures,
    pub tangential: Figures,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProcessError {
    #[error("the calibration is for the {cal} setting but the test ran in {run}")]
    Setting {
        cal: &'static str,
        run: &'static str,
    },
    #[error("the sensitivity matrix cannot be inverted: the three sensors do not span space")]
    Singular,
    #[error("the test has no readings")]
    Empty,
    #[error("reading {index}: {what} is not finite")]
    NotFinite { index: usize, what: &'static str },
}

/// Processes one test run with a calibration.
pub fn process(k: &Kinematics, run: &Run, cal: &Calibration) -> Result<Processed, ProcessError> {
    if cal.setting != run.setting {
        return Err(ProcessError::Setting {
            cal: cal.setting.name(),
            run: run.setting.name(),
        });
    }
    if run.points.is_empty() {
        return Err(ProcessError::Empty);
    }
    let cov_nest = cal.displacement_cov().ok_or(ProcessError::Singular)?;
    let g_inv = cal.g.try_inverse().ok_or(ProcessError::Singular)?;
    let nominal = k.nominal_state();
    let mut points = Vec::with_capacity(run.points.len());
    for p in &run.points {
        if p.readings_um.iter().any(|v| !v.is_finite()) {
            return Err(ProcessError::NotFinite {
                index: p.index,
                what: "a reading",
            });
        }
        if p.angles_deg.iter().any(|v| !v.is_finite()) {
            return Err(ProcessError::NotFinite {
                index: p.index,
                what: "an angle",
            });
        }
        let nest = cal
            .displacement(&p.readings_um)
            .ok_or(ProcessError::Singular)?;
        let (rt, rh) = nominal_rotations(k, &p.angles_deg);
        // Nest frame -> table frame.
        let q = if run.setting.nest_on_table() {
            Mat3::identity()
        } else {
            -(rt.transpose() * rh)
        };
        let table = q * nest;
        let machine = rt * table;
        let (u, c) = axis_line(k, &nominal, run.spec.axis, &p.angles_deg);
        let ball = k
            .pose_transform(&nominal, &p.angles_deg)
            .point(&run.spec.ball_mm);
        let r = (ball - c) - u * (ball - c).dot(&u);
        let radial = r.normalize();
        let tangential = u.cross(&radial);
        points.push(Deviation {
            index: p.index,
            angles_deg: p.angles_deg,
            angle_deg: p.angles_deg[run.spec.axis],
            t_ns: p.t_ns,
            nest_um: nest,
            table_um: table,
            machine_um: machine,
            radial_um: machine.dot(&radial),
            axial_um: machine.dot(&u),
            tangential_um: machine.dot(&tangential),
            cov_table: q * cov_nest * q.transpose(),
            nest_to_table: q,
            contacts: {
                let ball_to_nest = if run.setting.nest_on_table() {
                    rt.transpose() * rh
                } else {
                    rh.transpose() * rt
                };
                let design = run.setting.design();
                [0, 1, 2].map(|i| {
                    let face: Vec3 = design.column(i).into();
                    (ball_to_nest.transpose() * face, face)
                })
            },
        });
    }
    let fig = |f: fn(&Deviation) -> f64| figures(&points, f);
    Ok(Processed {
        test: run.spec.kind.name(),
        setting: run.setting,
        axis: k.rotary[run.spec.axis].name.clone(),
        calibration: cal.source.clone(),
        ball_mm: run.spec.ball_mm,
        g_inv,
        g_row_cov: cal.row_cov,
        sphericity_um: cal.sphericity_um,
        radial: fig(|d| d.radial_um),
        axial: fig(|d| d.axial_um),
        tangential: fig(|d| d.tangential_um),
        points,
    })
}

fn figures(points: &[Deviation], f: fn(&Deviation) -> f64) -> Figures {
    let v: Vec<f64> = points.iter().map(f).collect();
    let (lo, hi) = v
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), x| (l.min(*x), h.max(*x)));
    let angles: Vec<f64> = points.iter().map(|d| d.angle_deg).collect();
    let span = angles.iter().cloned().fold(f64::MIN, f64::max)
        - angles.iter().cloned().fold(f64::MAX, f64::min);
    let harmonic = (span >= 180.0)
        .then(|| first_harmonic(&angles, &v))
        .flatten();
    // Out and back: the same angle read twice.
    let mut reversal: Option<f64> = None;
    for (i, a) in points.iter().enumerate() {
        for b in &points[i + 1..] {
            if (a.angle_deg - b.angle_deg).abs() < 1e-9 {
                let d = (f(a) - f(b)).abs();
                reversal = Some(reversal.map_or(d, |r: f64| r.max(d)));
            }
        }
    }
    Figures {
        range_um: hi - lo,
        max_abs_um: lo.abs().max(hi.abs()),
        mean_um: v.iter().sum::<f64>() / v.len() as f64,
        first_harmonic_um: harmonic.map(|h| h.0),
        first_harmonic_peak_deg: harmonic.map(|h| h.1),
        reversal_um: reversal,
    }
}

/// Least squares `v = a0 + a cos(angle) + b sin(angle)`: (amplitude, angle of the maximum).
pub fn first_harmonic(angles_deg: &[f64], v: &[f64]) -> Option<(f64, f64)> {
    let n = v.len();
    if n < 4 {
        return None;
    }
    let a = DMatrix::from_fn(n, 3, |i, j| {
        let t = angles_deg[i].to_radians();
        match j {
            0 => 1.0,
            1 => t.cos(),
            _ => t.sin(),
        }
    });
    let sol = driftwatch_core::least_squares::lsq(&a, &DVector::from_column_slice(v)).beta;
    Some((sol[1].hypot(sol[2]), sol[2].atan2(sol[1]).to_degrees()))
}
