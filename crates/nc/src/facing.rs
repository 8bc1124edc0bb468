//! A lathe facing pass through given points, as a program for one control: what a control
//! without a built-in correction table (seed 003's Okuma has one) loads to cut a corrected
//! face. The points are plain `(radius, Z)` pairs in mm, edge first; where they come from
//! (a correction table) is the caller's.
//!
//! The pass only: rapid to the edge at a clearance above the face, feed to the first point,
//! feed through every point to the centre, retract in Z. The tool, the spindle and the work
//! offset (Z zero on the face) are active when it starts; the header says so.
//!
//! X is written as each control's lathes conventionally read it (`x_is_diameter`):
//! - **FANUC** lathe (G-code system A): X is the diameter; `G98` is feed per minute there
//!   (`G90` is a turning cycle, absolute is the X/Z addresses themselves).
//! - **Siemens** 840D: `DIAMON` (diameter programming, the turning convention) is commanded.
//! - **HEIDENHAIN** TNC 640: `FUNCTION MODE TURN`, where X values are diameters.
//! - **ISO** (LinuxCNC): `G8`, radius mode (its default), is commanded.

use thiserror::Error;

use crate::blocks::{Blocks, fmt_plain};
use crate::dialect::Dialect;

#[derive(Debug, Error, PartialEq)]
pub enum FacingError {
    #[error("decimals must be 1..={max} for {dialect}, not {decimals}")]
    Decimals {
        dialect: Dialect,
        decimals: usize,
        max: usize,
    },
    #[error("a facing pass needs at least two points")]
    TooFewPoints,
    #[error("point {0}: radius and Z must be finite and the radius not negative")]
    BadPoint(usize),
    #[error("feed and clearance must be positive")]
    NotPositive,
}

/// What to cut and how to name it.
#[derive(Debug, Clone, PartialEq)]
pub struct FacingPass {
    /// Program number (FANUC `O`), the program name elsewhere (`DW<number>`).
    pub number: u32,
    /// Header comment lines after the title (what the points are: the table, the resolution).
    pub comments: Vec<String>,
    /// `(radius, Z)`, mm, edge first.
    pub points: Vec<(f64, f64)>,
    pub feed_mm_min: f64,
    /// The approach and the retract: this far above the highest point's Z, mm.
    pub clearance_mm: f64,
    /// Decimals of X and Z: the control's least input increment (4: 0.0001 mm).
    pub decimals: usize,
}

/// Whether the dialect's program carries X as the diameter (else as the radius).
pub fn x_is_diameter(d: Dialect) -> bool {
    match d {
        Dialect::Fanuc | Dialect::Siemens | Dialect::Heidenhain => true,
        Dialect::Iso => false,
    }
}

/// The most decimals the dialect's controls take for a position.
fn max_decimals(d: Dialect) -> usize {
    match d {
        // TNC: positions to 4 places after the point.
        Dialect::Heidenhain => 4,
        _ => 5,
    }
}

/// A free text as a comment's: upper case, without the characters that end a comment on
/// some control.
fn comment_text(s: &str) -> String {
    let s: String = s
        .to_uppercase()
        .chars()
        .map(|c| if matches!(c, '(' | ')' | ';') { ' ' } else { c })
        .collect();
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// The program text of the facing pass in dialect `d`.
pub fn facing_program(d: Dialect, pass: &FacingPass) -> Result<String, FacingError> {
    let max = max_decimals(d);
    if !(1..=max).contains(&pass.decimals) {
        return Err(FacingError::Decimals {
            dialect: d,
            decimals: pass.decimals,
            max,
        });
    }
    if pass.points.len() < 2 {
        return Err(FacingError::TooFewPoints);
    }
    if let Some(i) = pass
        .points
        .iter()
        .position(|(r, z)| !(r.is_finite() && z.is_finite() && *r >= 0.0))
    {
        return Err(FacingError::BadPoint(i + 1));
    }
    if !(pass.feed_mm_min > 0.0 && pass.clearance_mm > 0.0) {
        return Err(FacingError::NotPositive);
    }
    let mut o = Blocks::new(d, pass.decimals);
    let title = "DRIFTWATCH LATHE FACING PASS - GENERATED, DO NOT EDIT";
    let name = format!("DW{}", pass.number);
    match d {
        Dialect::Fanuc => {
            o.emit("%");
            o.emit(&format!("O{:04} ({title})", pass.number));
        }
        Dialect::Heidenhain => {
            o.emit(&format!("BEGIN PGM {name} MM"));
            o.comment(title);
        }
        Dialect::Siemens => o.comment(&format!("{name} {title}")),
        Dialect::Iso => {
            o.emit("%");
            o.comment(&format!("{name} {title}"));
        }
    }
    for c in &pass.comments {
        o.comment(&comment_text(c));
    }
    let mode = match d {
        Dialect::Fanuc => "X IS THE DIAMETER - FANUC LATHE, G-CODE SYSTEM A",
        Dialect::Siemens => "X IS THE DIAMETER - DIAMON",
        Dialect::Heidenhain => "X IS THE DIAMETER - TURNING MODE",
        Dialect::Iso => "X IS THE RADIUS - G8",
    };
    o.comment(mode);
    o.comment("THE PASS ONLY: TOOL, SPINDLE AND WORK OFFSET WITH Z0 ON THE FACE ARE ACTIVE");
    let x_of = |r: f64| if x_is_diameter(d) { 2.0 * r } else { r };
    let top = pass
        .points
        .iter()
        .map(|p| p.1)
        .fold(f64::NEG_INFINITY, f64::max);
    let clear = top + pass.clearance_mm;
    let f = fmt_plain(pass.feed_mm_min);
    let (r0, z0) = pass.points[0];
    let (x, zc, zf) = (o.word('X', x_of(r0)), o.word('Z', clear), o.word('Z', z0));
    match d {
        Dialect::Fanuc => {
            o.emit("G21 G18 G40 G98");
            o.emit(&format!("G00 {x} {zc}"));
            o.emit(&format!("G01 {zf} F{f}"));
        }
        Dialect::Siemens => {
            o.emit("G18 G71 G90 G40 G94 DIAMON");
            o.emit(&format!("G0 {x} {zc}"));
            o.emit(&format!("G1 {zf} F{f}"));
        }
        Dialect::Heidenhain => {
            o.emit("FUNCTION MODE TURN");
            o.emit(&format!("L {x} {zc} R0 FMAX"));
            o.emit(&format!("L {zf} R0 F{f}"));
        }
        Dialect::Iso => {
            o.emit("G18 G21 G90 G40 G94 G8");
            o.emit(&format!("G0 {x} {zc}"));
            o.emit(&format!("G1 {zf} F{f}"));
        }
    }
    for (r, z) in &pass.points[1..] {
        let (x, z) = (o.word('X', x_of(*r)), o.word('Z', *z));
        match d {
            Dialect::Fanuc => o.emit(&format!("G01 {x} {z}")),
            Dialect::Siemens | Dialect::Iso => o.emit(&format!("G1 {x} {z}")),
            Dialect::Heidenhain => o.emit(&format!("L {x} {z}")),
        }
    }
    match d {
        Dialect::Fanuc => {
            o.emit(&format!("G00 {zc}"));
            o.emit("M30");
            o.emit("%");
        }
        Dialect::Siemens => {
            o.emit(&format!("G0 {zc}"));
            o.emit("M30");
        }
        Dialect::Heidenhain => {
            o.emit(&format!("L {zc} R0 FMAX"));
            o.emit("FUNCTION MODE MILL");
            o.emit(&format!("END PGM {name} MM"));
        }
        Dialect::Iso => {
            o.emit(&format!("G0 {zc}"));
            o.emit("M2");
            o.emit("%");
        }
    }
    Ok(o.text)
}
