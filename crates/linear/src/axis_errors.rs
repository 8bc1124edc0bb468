//! The three linear axes' errors as functions of the commanded position (ISO 230-1 terms),
//! in the convention of `kinematics::LinearErrors`: X is the reference, Y may lean towards X
//! (`sxy`), Z towards X and Y (`sxz`, `syz`); `actual - commanded` is
//!
//! ```text
//! x: kx x + sxy y + sxz z + Sxy(y) + Sxz(z) + Px(x)
//! y: ky y + syz z + Syx(x) + Syz(z) + Py(y)
//! z: kz z + Szx(x) + Szy(y) + Pz(z)
//! ```
//!
//! with `S<dir><axis>` the straightness of an axis in a transverse direction (zero at both
//! ends of the range: the end-point reference line, so that it carries no slope) and `P` a
//! periodic positioning error (scale pitch). Angular errors (and the Abbe offsets they act
//! through) are not modelled: the step diagonal's mirror sits at the tool point.

use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::LinearErrors;
use rand::Rng;
use serde::{Deserialize, Serialize};

/// A straightness profile over `[0, range]`: `sum a_k sin(k pi u / range)`, um (zero at both
/// ends).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub amplitudes_um: Vec<f64>,
}

impl Profile {
    pub fn at(&self, u_mm: f64, range_mm: f64) -> f64 {
        self.amplitudes_um
            .iter()
            .enumerate()
            .map(|(k, a)| a * ((k + 1) as f64 * std::f64::consts::PI * u_mm / range_mm).sin())
            .sum()
    }
}

/// What an instrument on the linear axes sees: `actual - commanded` of the tool point, um, at
/// a commanded position (mm) from the measured volume's start corner.
pub trait ErrorField {
    fn error_um(&self, p: &Vec3) -> Vec3;
}

impl ErrorField for AxisErrors {
    fn error_um(&self, p: &Vec3) -> Vec3 {
        AxisErrors::error_um(self, p)
    }
}

/// The kinematics' own model of the linear axes (scale, squareness, ISO 230-1 components with
/// their Abbe levers) with the measured volume's start corner at `origin_mm` in machine
/// coordinates: a step diagonal on the virtual machine's truth. The tool point is where the
/// components are referred to (`abbe_mm` of the errors).
#[derive(Debug, Clone, Copy)]
pub struct Placed<'a> {
    pub errors: &'a LinearErrors,
    pub origin_mm: Vec3,
}

impl ErrorField for Placed<'_> {
    fn error_um(&self, p: &Vec3) -> Vec3 {
        let tip = |q: &Vec3| self.errors.tip(&(self.origin_mm + q), &Vec3::zeros());
        (tip(p) - tip(&Vec3::zeros()) - p) * 1e3
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AxisErrors {
    /// Measured range of each axis from its start, mm (the profiles' span).
    pub range_mm: f64,
    /// Scale errors kx, ky, kz, ppm.
    pub scale_ppm: [f64; 3],
    /// Squareness sxy, sxz, syz, urad.
    pub squareness_urad: [f64; 3],
    /// Straightness: Syx, Szx (X's, in y and z), Sxy, Szy (Y's), Sxz, Syz (Z's).
    pub straightness: [Profile; 6],
    /// Periodic positioning error per axis: amplitude um, period mm.
    pub periodic: [(f64, f64); 3],
}

impl AxisErrors {
    /// The errors a machine state's `LinearErrors` describe (scale and squareness, nothing
    /// else) over a range: what a step diagonal on the virtual machine sees.
    pub fn from_linear(l: &LinearErrors, range_mm: f64) -> Self {
        AxisErrors {
            range_mm,
            scale_ppm: l.k.map(|v| v * 1e6),
            squareness_urad: [l.sxy * 1e6, l.sxz * 1e6, l.syz * 1e6],
            ..AxisErrors::default()
        }
    }

    /// `actual - commanded`, um, at a commanded position (mm, from the range's start).
    pub fn error_um(&self, p: &Vec3) -> Vec3 {
        let r = self.range_mm;
        let s = |i: usize, u: f64| self.straightness[i].at(u, r);
        let per = |i: usize, u: f64| {
            let (a, period) = self.periodic[i];
            if period > 0.0 {
                a * (2.0 * std::f64::consts::PI * u / period).sin()
            } else {
                0.0
            }
        };
        let [kx, ky, kz] = self.scale_ppm.map(|v| v * 1e-3);
        let [sxy, sxz, syz] = self.squareness_urad.map(|v| v * 1e-3);
        Vec3::new(
            kx * p.x + sxy * p.y + sxz * p.z + s(2, p.y) + s(4, p.z) + per(0, p.x),
            ky * p.y + syz * p.z + s(0, p.x) + s(5, p.z) + per(1, p.y),
            kz * p.z + s(1, p.x) + s(3, p.y) + per(2, p.z),
        )
    }

    /// A machine's errors of a plausible size for a machining centre over `range_mm`: scales
    /// within +-10 ppm, squareness within +-20 urad, straightness of 1-3 um, a 0.2 um pitch
    /// error of 20 mm.
    pub fn random(range_mm: f64, rng: &mut impl Rng) -> AxisErrors {
        let mut u = |a: f64| a * (2.0 * rng.random::<f64>() - 1.0);
        AxisErrors {
            range_mm,
            scale_ppm: [u(10.0), u(10.0), u(10.0)],
            squareness_urad: [u(20.0), u(20.0), u(20.0)],
            straightness: std::array::from_fn(|_| Profile {
                amplitudes_um: vec![u(2.0), u(1.0), u(0.5)],
            }),
            periodic: [(u(0.2), 20.0), (u(0.2), 20.0), (u(0.2), 20.0)],
        }
    }
}
