//! The linear axes' geometric errors (ISO 230-1): each axis' positioning, two straightness and
//! three angular errors as functions of its position, and the three squareness errors.
//!
//! The tool side's linear axes carry the tool: the tip commanded at linear-axis positions `p`
//! is at `A p + e(p)`, where `A = I + [[kx, Sxy, Sxz], [0, ky, Syz], [0, 0, kz]]` holds the
//! scales and squareness (the rigid part every instrument sees first) and `e(p)` the component
//! errors beyond them:
//!
//! `e(p) = sum_j [ t_j(p_j) + r_j(p_j) x l_j(p) ]`,
//!
//! with `t_j` the translation of axis j's carriage (positioning along j, straightness across;
//! ISO names EXJ, EYJ, EZJ), `r_j` its small rotation (EAJ, EBJ, ECJ, rad) and `l_j` the lever
//! from the carriage's reference point to the tip: the tip's offset from the point where the
//! component errors were measured (`abbe_mm`, plus the head chain's displacement of the tip)
//! and the positions of the axes that axis j carries (`stack`, from the bed up to the spindle).
//! Each component is a polynomial with no constant term in `u = p / 100 mm`:
//! `c1 u + c2 u^2 + c3 u^3` (um or urad), so the errors are zero at the axes' origin, where
//! the NC's reference is. A linear term of a straightness is a squareness and a linear term of
//! a positioning error is a scale: a geometry keeps those in `k` and `s` and the curvature
//! here (nothing stops both; they add).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::geometry::{Mat3, Vec3};

/// The length that normalises positions in the component polynomials, mm.
pub const COMPONENT_UNIT_MM: f64 = 100.0;

/// One axis' component errors: translation along X, Y, Z (um) and rotation about X, Y, Z
/// (urad), each `[c1, c2, c3]` of `u = p / 100 mm`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AxisComponents {
    pub translation_um: [[f64; 3]; 3],
    pub rotation_urad: [[f64; 3]; 3],
}

impl AxisComponents {
    fn is_zero(&self) -> bool {
        self.translation_um
            .iter()
            .chain(&self.rotation_urad)
            .flatten()
            .all(|c| *c == 0.0)
    }
}

fn poly(c: &[f64; 3], u: f64) -> f64 {
    u * (c[0] + u * (c[1] + u * c[2]))
}

/// Linear-axis errors of the tool side: scales, squareness and the component errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearErrors {
    /// Scale errors of X, Y, Z (dimensionless).
    pub k: [f64; 3],
    /// Squareness (rad): X moves with Y by `Sxy`, X with Z by `Sxz`, Y with Z by `Syz`.
    pub sxy: f64,
    pub sxz: f64,
    pub syz: f64,
    /// Component errors of X, Y, Z beyond scale and squareness.
    pub axes: [AxisComponents; 3],
    /// The axes from the bed up to the spindle (0 = X): axis `stack[i]` carries the ones after.
    pub stack: [usize; 3],
    /// The tool tip at the zero pose relative to where the component errors were measured, mm.
    pub abbe_mm: Vec3,
}

impl Default for LinearErrors {
    fn default() -> Self {
        LinearErrors {
            k: [0.0; 3],
            sxy: 0.0,
            sxz: 0.0,
            syz: 0.0,
            axes: [AxisComponents::default(); 3],
            stack: [0, 1, 2],
            abbe_mm: Vec3::zeros(),
        }
    }
}

impl LinearErrors {
    /// `A`: the scales and squareness as a matrix on the commanded displacement.
    pub fn matrix(&self) -> Mat3 {
        Mat3::new(
            1.0 + self.k[0],
            self.sxy,
            self.sxz,
            0.0,
            1.0 + self.k[1],
            self.syz,
            0.0,
            0.0,
            1.0 + self.k[2],
        )
    }

    /// Whether any component error is non-zero (when none is, the tip is `A p` exactly).
    pub fn has_components(&self) -> bool {
        self.axes.iter().any(|a| !a.is_zero())
    }

    /// `e(p)`, mm: the component errors' displacement of the tip at linear-axis positions `p`
    /// (mm), the tip displaced by `tip_offset` (mm, e.g. by a head chain) from where it is at
    /// the zero pose.
    pub fn component_error(&self, p: &Vec3, tip_offset: &Vec3) -> Vec3 {
        if !self.has_components() {
            return Vec3::zeros();
        }
        let mut e = Vec3::zeros();
        for (level, &j) in self.stack.iter().enumerate() {
            let a = &self.axes[j];
            if a.is_zero() {
                continue;
            }
            let u = p[j] / COMPONENT_UNIT_MM;
            let t = Vec3::from_fn(|i, _| poly(&a.translation_um[i], u)) * 1e-3;
            let r = Vec3::from_fn(|i, _| poly(&a.rotation_urad[i], u)) * 1e-6;
            let mut lever = self.abbe_mm + tip_offset;
            for &carried in &self.stack[level + 1..] {
                lever[carried] += p[carried];
            }
            e += t + r.cross(&lever);
        }
        e
    }

    /// The actual tip displacement for commanded linear-axis positions `p` (mm).
    pub fn tip(&self, p: &Vec3, tip_offset: &Vec3) -> Vec3 {
        self.matrix() * p + self.component_error(p, tip_offset)
    }
}

const AXES: [char; 3] = ['X', 'Y', 'Z'];
const ROTATIONS: [char; 3] = ['A', 'B', 'C'];

/// A geometry in the units people write: what a machine file's `[linear]` section, the
/// service's geometry versions and `driftwatch diagonal solve --geometry-out` hold.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields, default)]
pub struct LinearGeometry {
    /// Scale errors of X, Y, Z, ppm.
    #[cfg_attr(feature = "openapi", schema(min_items = 3, max_items = 3))]
    pub scale_ppm: [f64; 3],
    /// Squareness, urad, in the kinematics' convention: `xy` (X moves with Y), `xz`, `yz`.
    pub squareness_urad: Squareness,
    /// Component errors beyond scale and squareness by ISO 230-1 name (`EZX`: X's
    /// straightness along Z; `EBX`: X's rotation about Y; `EXX`: X's positioning), each
    /// `[c1, c2, c3]` of `u = p / 100 mm`, um or urad (three numbers: checked with the
    /// names, so that a wrong count is named like a wrong name).
    pub components: BTreeMap<String, Vec<f64>>,
    /// The axes from the bed up to the spindle, e.g. "XYZ" (X carries Y, which carries Z).
    #[cfg_attr(feature = "openapi", schema(pattern = "^[XYZxyz]{3}$"))]
    pub stack: Option<String>,
    /// The tool tip at the zero pose relative to where the components were measured, mm.
    #[cfg_attr(feature = "openapi", schema(min_items = 3, max_items = 3))]
    pub abbe_mm: [f64; 3],
}

#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields, default)]
pub struct Squareness {
    pub xy: f64,
    pub xz: f64,
    pub yz: f64,
}

#[derive(Debug, Error, PartialEq)]
pub enum GeometryError {
    #[error(
        "unknown component '{0}': ISO 230-1 names E<direction><axis>, direction X|Y|Z (translation) or A|B|C (rotation), axis X|Y|Z"
    )]
    UnknownComponent(String),
    #[error("component '{0}' has {1} coefficients: it takes three, [c1, c2, c3]")]
    Coefficients(String, usize),
    #[error("stack '{0}' must name X, Y and Z once each, from the bed up")]
    Stack(String),
    #[error(
        "{what} = {value} is not finite or beyond {limit} {unit}: no machine is that far out; a unit slip?"
    )]
    OutOfRange {
        what: String,
        value: f64,
        limit: f64,
        unit: &'static str,
    },
}

/// The largest scale (ppm), squareness (urad), component coefficient (um or urad) and Abbe
/// offset (mm) a geometry may hold: far beyond any machine, near any unit slip.
pub const LIMITS: [f64; 4] = [1000.0, 2000.0, 1000.0, 2000.0];

fn check(what: &str, value: f64, limit: f64, unit: &'static str) -> Result<(), GeometryError> {
    if value.is_finite() && value.abs() <= limit {
        Ok(())
    } else {
        Err(GeometryError::OutOfRange {
            what: what.to_string(),
            value,
            limit,
            unit,
        })
    }
}

impl LinearGeometry {
    /// The kinematics' errors, checked.
    pub fn errors(&self) -> Result<LinearErrors, GeometryError> {
        let mut e = LinearErrors::default();
        for (j, v) in self.scale_ppm.iter().enumerate() {
            check(&format!("scale_ppm[{}]", AXES[j]), *v, LIMITS[0], "ppm")?;
            e.k[j] = v * 1e-6;
        }
        let s = &self.squareness_urad;
        for (name, v) in [("xy", s.xy), ("xz", s.xz), ("yz", s.yz)] {
            check(&format!("squareness_urad.{name}"), v, LIMITS[1], "urad")?;
        }
        (e.sxy, e.sxz, e.syz) = (s.xy * 1e-6, s.xz * 1e-6, s.yz * 1e-6);
        for (name, c) in &self.components {
            let (j, rotation, i) = parse_component(name)
                .ok_or_else(|| GeometryError::UnknownComponent(name.clone()))?;
            let c: [f64; 3] = c
                .as_slice()
                .try_into()
                .map_err(|_| GeometryError::Coefficients(name.clone(), c.len()))?;
            for v in c {
                check(name, v, LIMITS[2], if rotation { "urad" } else { "um" })?;
            }
            let a = &mut e.axes[j];
            match rotation {
                true => a.rotation_urad[i] = c,
                false => a.translation_um[i] = c,
            }
        }
        if let Some(st) = &self.stack {
            let idx: Vec<usize> = st
                .chars()
                .filter_map(|ch| AXES.iter().position(|a| a.eq_ignore_ascii_case(&ch)))
                .collect();
            let mut sorted = idx.clone();
            sorted.sort_unstable();
            if st.chars().count() != 3 || sorted != [0, 1, 2] {
                return Err(GeometryError::Stack(st.clone()));
            }
            e.stack = [idx[0], idx[1], idx[2]];
        }
        for (j, v) in self.abbe_mm.iter().enumerate() {
            check(&format!("abbe_mm[{}]", AXES[j]), *v, LIMITS[3], "mm")?;
        }
        e.abbe_mm = Vec3::from(self.abbe_mm);
        Ok(e)
    }

    /// The document of `e` (the inverse of [`LinearGeometry::errors`]; zero components left out).
    pub fn of(e: &LinearErrors) -> LinearGeometry {
        let mut components = BTreeMap::new();
        for (j, a) in e.axes.iter().enumerate() {
            for i in 0..3 {
                if a.translation_um[i] != [0.0; 3] {
                    components.insert(
                        format!("E{}{}", AXES[i], AXES[j]),
                        a.translation_um[i].to_vec(),
                    );
                }
                if a.rotation_urad[i] != [0.0; 3] {
                    components.insert(
                        format!("E{}{}", ROTATIONS[i], AXES[j]),
                        a.rotation_urad[i].to_vec(),
                    );
                }
            }
        }
        LinearGeometry {
            scale_ppm: e.k.map(|k| k * 1e6),
            squareness_urad: Squareness {
                xy: e.sxy * 1e6,
                xz: e.sxz * 1e6,
                yz: e.syz * 1e6,
            },
            components,
            stack: Some(e.stack.iter().map(|&j| AXES[j]).collect()),
            abbe_mm: e.abbe_mm.into(),
        }
    }

    /// Whether the geometry is all zero (the NC's own assumption).
    pub fn is_zero(&self) -> bool {
        self.errors().is_ok_and(|e| {
            e == LinearErrors {
                stack: e.stack,
                abbe_mm: e.abbe_mm,
                ..LinearErrors::default()
            }
        })
    }
}

/// `(axis, is_rotation, direction)` of an ISO 230-1 component name such as `EZX` or `EBY`.
pub fn parse_component(name: &str) -> Option<(usize, bool, usize)> {
    let c: Vec<char> = name.chars().collect();
    if c.len() != 3 || c[0] != 'E' {
        return None;
    }
    let axis = AXES.iter().position(|a| *a == c[2])?;
    if let Some(i) = AXES.iter().position(|a| *a == c[1]) {
        return Some((axis, false, i));
    }
    ROTATIONS
        .iter()
        .position(|a| *a == c[1])
        .map(|i| (axis, true, i))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_straightness_moves_the_tip_across_the_axis_by_its_polynomial() {
        let mut e = LinearErrors::default();
        // EZX = 2 um u^2: X at 200 mm puts the tip 8 um up.
        e.axes[0].translation_um[2] = [0.0, 2.0, 0.0];
        let d = e.component_error(&Vec3::new(200.0, 50.0, -30.0), &Vec3::zeros());
        assert!((d - Vec3::new(0.0, 0.0, 8e-3)).norm() < 1e-15, "{d}");
    }

    #[test]
    fn an_angular_error_acts_through_the_carried_axes_and_the_abbe_offset() {
        // EBX (X pitching about Y) of 10 urad per 100 mm; X carries Y and Z.
        let mut e = LinearErrors::default();
        e.axes[0].rotation_urad[1] = [10.0, 0.0, 0.0];
        e.abbe_mm = Vec3::new(0.0, 0.0, -150.0);
        let p = Vec3::new(100.0, 20.0, 50.0);
        let d = e.component_error(&p, &Vec3::zeros());
        // Rotation 10 urad about Y of the lever (0, 20, 50 - 150): dx = 1e-5 * (-100).
        let want = Vec3::new(0.0, 1e-5, 0.0).cross(&Vec3::new(0.0, 20.0, -100.0));
        assert!((d - want).norm() < 1e-15, "{d} vs {want}");
        // Z on top carries nothing: its own pitch sees only the Abbe offset.
        let mut top = LinearErrors::default();
        top.axes[2].rotation_urad[1] = [10.0, 0.0, 0.0];
        let d = top.component_error(&Vec3::new(100.0, 20.0, 100.0), &Vec3::new(5.0, 0.0, 0.0));
        let want = Vec3::new(0.0, 1e-5, 0.0).cross(&Vec3::new(5.0, 0.0, 0.0));
        assert!((d - want).norm() < 1e-15);
    }

    #[test]
    fn the_document_round_trips_and_refuses_unit_slips() {
        let text = r#"
            scale_ppm = [3.0, -2.0, 0.0]
            squareness_urad = { xy = 12.0, yz = -5.0 }
            components = { EZX = [0.0, 1.5, -0.3], EBY = [4.0, 0.0, 0.0] }
            stack = "YXZ"
            abbe_mm = [0.0, 0.0, -120.0]
        "#;
        let g: LinearGeometry = toml::from_str(text).unwrap();
        let e = g.errors().unwrap();
        assert_eq!(e.stack, [1, 0, 2]);
        assert_eq!(e.axes[0].translation_um[2], [0.0, 1.5, -0.3]);
        assert_eq!(e.axes[1].rotation_urad[1], [4.0, 0.0, 0.0]);
        assert!((e.sxy - 12e-6).abs() < 1e-18);
        let back = LinearGeometry::of(&e);
        assert_eq!(back.errors().unwrap(), e);
        let bad = |t: &str| {
            toml::from_str::<LinearGeometry>(t)
                .unwrap()
                .errors()
                .unwrap_err()
        };
        assert!(matches!(
            bad("scale_ppm = [3e6, 0, 0]"),
            GeometryError::OutOfRange { .. }
        ));
        assert!(matches!(
            bad("components = { EQX = [1, 0, 0] }"),
            GeometryError::UnknownComponent(_)
        ));
        assert!(matches!(bad("stack = \"XXZ\""), GeometryError::Stack(_)));
        assert!(matches!(
            bad("components = { EZX = [1, 0] }"),
            GeometryError::Coefficients(_, 2)
        ));
        assert!(g.errors().is_ok() && !g.is_zero() && LinearGeometry::default().is_zero());
    }
}
