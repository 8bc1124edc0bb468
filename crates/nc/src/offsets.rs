//! A served compensation set in one control's own variables, with the program text that writes
//! them, the step from the previous served set per variable, and how far the part zero moves
//! when they are loaded (`docs/nc.md`, "Offsets in each control's form").
//!
//! Every number comes from the machine's kinematics, never from a family's name: the move of
//! each axis line and the change of its direction are `Kinematics::lines` of the set's errors,
//! and the datum shift is `Kinematics::pose_transform` and the head chain at each pose, before
//! and after. What differs between controls is only which vector a line's move adds to:
//!
//! - FANUC (tool center point for 5-axis machining, 30i): the rotary table position
//!   19700-19702, the table axes' intersection offset 19703-19705, the tool axis to tool
//!   rotation axis offset 19709-19711; absolute vectors, so the commissioned (nominal) value of
//!   each is an argument and the program writes nominal + offset, in the parameter's increment.
//! - Siemens 840D: the swivel data record's fine offsets of l1..l4 (`$TC_CARR41`..`60`, added to
//!   the basic vectors by the control), and the rotary axis vectors v1/v2 (`$TC_CARR7`..`12`).
//! - HEIDENHAIN: Q parameters holding the offsets in mm and deg for the OEM's cycle that loads
//!   the kinematics (the kinematics description itself is OEM-only).
//! - LinuxCNC (`xyzbc-trt-kins`, `xyzac-trt-kins`): the kinematics' HAL pins, the C line's
//!   rotation point and the tilting line's offset from it; absolute positions, so the
//!   commissioned value of each pin is an argument, as on FANUC; a halcmd script sets them.
//! - json: driftwatch's own offsets (`NcLayout`).
//!
//! A set is only turned into NC values when it still looks validated (exactly the machine's
//! errors, finite, believable) and its step from the previous served set lies within the
//! validation's step limit; otherwise the answer is a typed refusal, never a program.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use driftwatch_core::error_name::ErrorName;
use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY, MachineState, Side};
use driftwatch_core::units;
use driftwatch_machine::compensation::{CompensationSet, ValidationLimits, compensation_message};
use driftwatch_machine::nc_offsets::NcLayout;

/// The form the offsets are asked for in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OffsetFormat {
    Json,
    Fanuc,
    Siemens,
    Heidenhain,
    Linuxcnc,
}

impl OffsetFormat {
    pub const ALL: [OffsetFormat; 5] = [
        OffsetFormat::Json,
        OffsetFormat::Fanuc,
        OffsetFormat::Siemens,
        OffsetFormat::Heidenhain,
        OffsetFormat::Linuxcnc,
    ];

    pub fn name(self) -> &'static str {
        match self {
            OffsetFormat::Json => "json",
            OffsetFormat::Fanuc => "fanuc",
            OffsetFormat::Siemens => "siemens",
            OffsetFormat::Heidenhain => "heidenhain",
            OffsetFormat::Linuxcnc => "linuxcnc",
        }
    }

    pub fn parse(s: &str) -> Result<Self, OffsetsError> {
        Self::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| OffsetsError::UnknownFormat(s.to_string()))
    }
}

/// The geometry pins of LinuxCNC's trt kinematics (`xyzbc-trt-kins.x-rot-point`, ...), without
/// the module's prefix: the names a commissioned value is given by. `tool-offset` is not one:
/// motion sets it from the tool table.
pub const LINUXCNC_PINS: [&str; 6] = [
    "x-rot-point",
    "y-rot-point",
    "z-rot-point",
    "x-offset",
    "y-offset",
    "z-offset",
];

/// What a control's form needs that driftwatch cannot know: given by the caller (command-line
/// flags, query parameters), never a hidden constant.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NcOptions {
    /// FANUC: the increment of parameters 19700-19714 in mm, which `R` counts: 0.001 for
    /// increment system IS-B (default), 0.0001 for IS-C.
    pub fanuc_increment_mm: f64,
    /// FANUC: the commissioned value of each parameter written (number -> mm), the geometry
    /// driftwatch's machine file calls nominal. Required: the parameters are absolute.
    pub fanuc_nominal_mm: BTreeMap<u32, f64>,
    /// FANUC: the program number (`O`).
    pub fanuc_program: u32,
    /// Siemens: the swivel data record (toolholder) number `n` of `$TC_CARR..[n]`.
    pub siemens_carrier: u32,
    /// Siemens: +1 when the commissioned rotary axis vectors point along the machine file's
    /// axes, -1 when against them.
    pub siemens_axis_sign: f64,
    /// HEIDENHAIN: the first Q parameter of the block the offsets are written to.
    pub heidenhain_q_base: u32,
    /// LinuxCNC: the commissioned value of each kinematics pin written, by its name without
    /// the module's prefix (`x-rot-point` -> mm; one of [`LINUXCNC_PINS`]). Required: the pins
    /// are absolute.
    pub linuxcnc_nominal_mm: BTreeMap<String, f64>,
    /// The work origin whose move is reported, mm in the table frame.
    pub work_origin_mm: [f64; 3],
    /// The poses of the datum-shift report, deg per rotary axis; empty: the zero pose and each
    /// axis alone at -90 and +90 where its travel allows.
    pub poses_deg: Vec<Vec<f64>>,
}

impl Default for NcOptions {
    fn default() -> Self {
        NcOptions {
            fanuc_increment_mm: 0.001,
            fanuc_nominal_mm: BTreeMap::new(),
            fanuc_program: 8100,
            siemens_carrier: 1,
            siemens_axis_sign: 1.0,
            heidenhain_q_base: 1600,
            linuxcnc_nominal_mm: BTreeMap::new(),
            work_origin_mm: [0.0; 3],
            poses_deg: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Error)]
pub enum OffsetsError {
    #[error("unknown offsets format '{0}': one of json, fanuc, siemens, heidenhain, linuxcnc")]
    UnknownFormat(String),
    #[error("set {version} is not a validated {machine} set: {}", .reasons.join("; "))]
    NotValidated {
        machine: String,
        version: u64,
        reasons: Vec<String>,
    },
    #[error("the previous set {previous} is not older than set {version}")]
    PreviousNotOlder { version: u64, previous: u64 },
    #[error(
        "set {version} steps beyond the limit from the served set {previous}, refused rather than written: {}",
        .steps.join("; ")
    )]
    StepBeyondLimit {
        version: u64,
        previous: u64,
        steps: Vec<String>,
    },
    #[error(
        "FANUC parameters {} hold absolute vectors: give their commissioned values (nominal, mm)",
        .params.iter().map(u32::to_string).collect::<Vec<_>>().join(", ")
    )]
    MissingNominal { params: Vec<u32> },
    #[error(
        "{kins} pins {} hold absolute positions: give their commissioned values (nominal, mm)",
        .pins.join(", ")
    )]
    MissingPinNominal { kins: String, pins: Vec<String> },
    #[error("{machine}: {message}")]
    Unsupported { machine: String, message: String },
    #[error("bad option: {0}")]
    BadOption(String),
}

/// One value as the control takes it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NcVariable {
    /// The control's name: `19703`, `$TC_CARR44[1]`, `Q1600`, or driftwatch's offset name.
    pub name: String,
    pub meaning: String,
    /// The unit of `value` and `step` (`0.001 mm` for a FANUC increment count).
    pub unit: String,
    /// As written: rounded to the control's resolution.
    pub value: f64,
    /// `value` minus the exact value (rounding), same unit.
    pub rounding: f64,
    /// The change from the previous served set's value, same unit; none without one.
    pub step: Option<f64>,
    /// The text the program writes.
    pub text: String,
}

/// How far the part zero moves against the tool at one pose when the new values are loaded.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DatumShift {
    pub pose: String,
    pub pose_deg: Vec<f64>,
    /// Machine frame, um.
    pub shift_um: [f64; 3],
    pub norm_um: f64,
}

/// A set in one control's form.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NcOffsets {
    pub format: OffsetFormat,
    pub machine: String,
    pub version: u64,
    pub previous_version: Option<u64>,
    /// The control's name for the machine's kinematics (`19680 = 12`, `$TC_CARR23 = "P"`).
    pub kinematic_type: String,
    pub variables: Vec<NcVariable>,
    /// Identified errors no variable of this form carries (and the datum shift leaves out).
    pub not_written: Vec<String>,
    pub notes: Vec<String>,
    pub datum_shift: Vec<DatumShift>,
    /// The program that writes the variables (none for json).
    pub program: Option<String>,
}

/// A variable before rounding: its exact value in `unit`, rounded to `decimals`.
struct Raw {
    name: String,
    label: String,
    meaning: String,
    unit: String,
    exact: f64,
    decimals: usize,
}

/// What a control's form makes of a machine: its variables from a set's errors, the errors it
/// writes, the kinematic type and notes.
struct Form {
    raw: Vec<Raw>,
    writes: fn(ErrorName) -> bool,
    kinematic_type: String,
    notes: Vec<String>,
}

/// The set in `format`: variables, steps from `previous` (the set served before it), the
/// datum shift and the program. Refused when the set does not look validated, when its step
/// from `previous` lies beyond the limits' step (grown by their rates over the time between,
/// as the service ramps), or when the control's form needs an option that is missing.
pub fn nc_offsets(
    format: OffsetFormat,
    k: &Kinematics,
    set: &CompensationSet,
    previous: Option<&CompensationSet>,
    limits: &ValidationLimits,
    opts: &NcOptions,
) -> Result<NcOffsets, OffsetsError> {
    let layout = NcLayout::of(k);
    check_validated(set, &layout, limits)?;
    if let Some(prev) = previous {
        check_validated(prev, &layout, limits)?;
        check_step(set, prev, limits)?;
    }
    let form = form(format, k, &set.errors, opts)?;
    let before = previous
        .map(|p| form_values(format, k, &p.errors, opts))
        .transpose()?;
    let variables = form
        .raw
        .iter()
        .map(|r| {
            let value = round_to(r.exact, r.decimals);
            let step = before.as_ref().and_then(|b| {
                b.get(&r.name)
                    .map(|p| round_to(value - round_to(*p, r.decimals), r.decimals))
            });
            NcVariable {
                name: r.name.clone(),
                meaning: r.meaning.clone(),
                unit: r.unit.clone(),
                value,
                rounding: value - r.exact,
                step,
                text: number(value, r.decimals, format == OffsetFormat::Heidenhain),
            }
        })
        .collect::<Vec<_>>();
    let not_written: Vec<String> = layout
        .errors
        .iter()
        .filter(|n| !(form.writes)(**n))
        .map(|n| format!("{n} = {:.3} {}", set.errors[n], n.unit()))
        .collect();
    let mut notes = form.notes;
    if previous.is_none() {
        notes.push(
            "no previous served set: the step from the values the NC holds now is not known; \
             check them before the first load"
                .into(),
        );
    }
    let datum_shift = datum_shift(k, set, previous, form.writes, opts)?;
    let mut out = NcOffsets {
        format,
        machine: k.name.clone(),
        version: set.version,
        previous_version: previous.map(|p| p.version),
        kinematic_type: form.kinematic_type,
        variables,
        not_written,
        notes,
        datum_shift,
        program: None,
    };
    let labels: Vec<&str> = form.raw.iter().map(|r| r.label.as_str()).collect();
    out.program = program(&out, &labels, set, opts);
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Checks
// ---------------------------------------------------------------------------------------------

/// The checks a served set passed that need no history: exactly the machine's errors, finite
/// and believable, each with a positive finite uncertainty. A set read from a file or a
/// database is checked again here, so no hand-edited set becomes a program.
fn check_validated(
    set: &CompensationSet,
    layout: &NcLayout,
    limits: &ValidationLimits,
) -> Result<(), OffsetsError> {
    let mut reasons = Vec::new();
    for n in &layout.errors {
        let max = if n.is_angular() {
            limits.max_abs_urad
        } else {
            limits.max_abs_um
        };
        match set.errors.get(n) {
            None => reasons.push(format!("{n} missing")),
            // `within` is false for a NaN value or limit, so either refuses.
            Some(v) if !within(v.abs(), max) => reasons.push(format!(
                "{n} = {v} {} is not a finite value within the believable {max} {}",
                n.unit(),
                n.unit()
            )),
            Some(_) => {}
        }
        match set.sigma.get(n) {
            Some(s) if units::positive(*s) => {}
            _ => reasons.push(format!("{n} has no positive finite uncertainty")),
        }
    }
    for n in set.errors.keys() {
        if !layout.holds(n.as_str()) {
            reasons.push(format!(
                "{n} is not an error of {} ({})",
                layout.machine,
                layout.list()
            ));
        }
    }
    if reasons.is_empty() {
        Ok(())
    } else {
        Err(OffsetsError::NotValidated {
            machine: layout.machine.clone(),
            version: set.version,
            reasons,
        })
    }
}

/// Each error's step from the previous served set within the validation's step limit, grown by
/// its rate over the minutes between the two sets: the limit `compensation::ramp` holds served
/// sets to, so a served sequence always passes and anything else is refused. An error new in
/// `set` steps from 0, as the ramp has it.
fn check_step(
    set: &CompensationSet,
    prev: &CompensationSet,
    limits: &ValidationLimits,
) -> Result<(), OffsetsError> {
    if prev.version >= set.version {
        return Err(OffsetsError::PreviousNotOlder {
            version: set.version,
            previous: prev.version,
        });
    }
    let mut steps = Vec::new();
    for (n, v) in &set.errors {
        let from = prev.errors.get(n).copied().unwrap_or(0.0);
        let max = limits
            .step_limit(n.is_angular(), prev.valid_from_ns, set.valid_from_ns)
            .max();
        let step = v - from;
        // 1e-9: the ramp's own rounding; a NaN limit refuses.
        if !within(step.abs(), max + 1e-9) {
            steps.push(format!(
                "{n} {from:.3} -> {v:.3} {u} (step {step:+.3} {u} over the limit {max:.3} {u})",
                u = n.unit()
            ));
        }
    }
    if steps.is_empty() {
        Ok(())
    } else {
        Err(OffsetsError::StepBeyondLimit {
            version: set.version,
            previous: prev.version,
            steps,
        })
    }
}

/// `x` at most `max`; false when either is NaN, so that a NaN fails the check it is in.
fn within(x: f64, max: f64) -> bool {
    x <= max
}

// ---------------------------------------------------------------------------------------------
// Geometry
// ---------------------------------------------------------------------------------------------

/// The state of `errors` (those `keep` takes), on the held errors when `held`, else on none.
fn state_of(
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    keep: fn(ErrorName) -> bool,
    held: bool,
) -> MachineState {
    let mut s = k.nominal_state();
    if !held {
        s.loc = [[0.0; 5]; MAX_ROTARY];
    }
    for (n, v) in errors {
        if let Some(id) = k.error_id(n.as_str())
            && keep(*n)
        {
            s.loc[id.axis][id.slot] = v * id.scale();
        }
    }
    s
}

/// Each axis line's move (mm) and direction change at the zero pose, from the errors alone.
fn line_moves(k: &Kinematics, errors: &BTreeMap<ErrorName, f64>) -> (Vec<Vec3>, Vec<Vec3>) {
    let (offsets, dirs) = k.lines(&state_of(k, errors, |_| true, false));
    let n = k.rotary.len();
    let moves = offsets[..n].to_vec();
    let turns = (0..n).map(|i| dirs[i] - k.rotary[i].u0).collect();
    (moves, turns)
}

/// `v` without its part along the unit `u`: a line has no position along itself.
fn square_to(v: Vec3, u: Vec3) -> Vec3 {
    v - u * v.dot(&u)
}

/// Which components of a vector function of the errors any identified error can move: the
/// ones a control is given (a component no error moves keeps its commissioned value).
fn moved(k: &Kinematics, f: &dyn Fn(&BTreeMap<ErrorName, f64>) -> Vec<Vec3>) -> Vec<[bool; 3]> {
    let mut out: Vec<[bool; 3]> = Vec::new();
    for id in &k.identify {
        let e = BTreeMap::from([(k.rotary[id.axis].error_names[id.slot], 1.0)]);
        for (i, v) in f(&e).into_iter().enumerate() {
            if out.len() <= i {
                out.push([false; 3]);
            }
            for c in 0..3 {
                out[i][c] |= v[c].abs() > 1e-12;
            }
        }
    }
    out
}

/// The table and head axes, outermost first.
fn sides(k: &Kinematics) -> (Vec<usize>, Vec<usize>) {
    let of = |s: Side| {
        (0..k.rotary.len())
            .filter(|i| k.rotary[*i].side == s)
            .collect()
    };
    (of(Side::Table), of(Side::Head))
}

fn unsupported(k: &Kinematics, what: &str) -> OffsetsError {
    OffsetsError::Unsupported {
        machine: k.name.clone(),
        message: format!("{what}: no family with this chain ships, so no form is derived for it"),
    }
}

// ---------------------------------------------------------------------------------------------
// The controls' forms
// ---------------------------------------------------------------------------------------------

fn form(
    format: OffsetFormat,
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<Form, OffsetsError> {
    match format {
        OffsetFormat::Json => Ok(json_form(k, errors)),
        OffsetFormat::Fanuc => fanuc_form(k, errors, opts),
        OffsetFormat::Siemens => siemens_form(k, errors, opts),
        OffsetFormat::Heidenhain => heidenhain_form(k, errors, opts),
        OffsetFormat::Linuxcnc => linuxcnc_form(k, errors, opts),
    }
}

/// The exact values of a set's variables by name (for the step from the previous set).
fn form_values(
    format: OffsetFormat,
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<BTreeMap<String, f64>, OffsetsError> {
    Ok(form(format, k, errors, opts)?
        .raw
        .into_iter()
        .map(|r| (r.name, r.exact))
        .collect())
}

fn json_form(k: &Kinematics, errors: &BTreeMap<ErrorName, f64>) -> Form {
    let layout = NcLayout::of(k);
    let values = layout.offsets(errors);
    let raw = layout
        .offsets
        .iter()
        .filter_map(|o| {
            let meaning = o
                .terms
                .iter()
                .map(|(n, w)| format!("{w:+.4} {n}"))
                .collect::<Vec<_>>()
                .join(" ");
            values.get(&o.name).map(|v| Raw {
                name: o.name.clone(),
                label: o.name.clone(),
                meaning,
                unit: o.unit.to_string(),
                exact: *v,
                decimals: 3,
            })
        })
        .collect();
    Form {
        raw,
        writes: |_| true,
        kinematic_type: "driftwatch NC offsets (docs/nc.md)".into(),
        notes: Vec::new(),
    }
}

/// A control's vector from the line moves (mm) and the direction changes of the axes.
type VectorOf = Box<dyn Fn(&[Vec3], &[Vec3]) -> Vec3>;

/// One vector of a control: its name per component, a short label, its meaning and how it
/// follows from the line moves and direction changes.
struct NcVector {
    names: [String; 3],
    label: String,
    meaning: String,
    of: VectorOf,
}

/// The FANUC vectors of a machine's chain (A-79348E: 19700-19702 from the machine origin to
/// the first table axis, 19703-19705 from it to the second, 19709-19711 from the tool axis to
/// the tool rotation axis).
fn fanuc_vectors(k: &Kinematics) -> Result<(u32, Vec<NcVector>), OffsetsError> {
    let (table, head) = sides(k);
    let p = |first: u32| [0, 1, 2].map(|c| (first + c).to_string());
    let name = |i: usize| k.rotary[i].name.clone();
    let position = |t: usize| NcVector {
        names: p(19700),
        label: "ROTARY TABLE POSITION".into(),
        meaning: format!(
            "rotary table position: machine origin to a point on the {} axis (its line's move)",
            name(t)
        ),
        of: Box::new(move |m, _| m[t]),
    };
    match (table.as_slice(), head.as_slice()) {
        ([t0, t1], []) => {
            let (t0, t1) = (*t0, *t1);
            let u1 = k.rotary[t1].u0;
            Ok((
                12,
                vec![
                    position(t0),
                    NcVector {
                        names: p(19703),
                        label: "TABLE AXES INTERSECTION OFFSET".into(),
                        meaning: format!(
                            "intersection offset: the {} axis to the {} axis (the {} line's move \
                             less the {} line's, square to {})",
                            name(t0),
                            name(t1),
                            name(t1),
                            name(t0),
                            name(t1)
                        ),
                        of: Box::new(move |m, _| square_to(m[t1] - m[t0], u1)),
                    },
                ],
            ))
        }
        ([t], [h]) => {
            let h = *h;
            Ok((
                21,
                vec![
                    position(*t),
                    NcVector {
                        names: p(19709),
                        label: "TOOL AXIS TO TOOL ROTATION AXIS".into(),
                        meaning: format!(
                            "intersection offset: the tool axis to the {} axis (its line's move \
                             in the head frame at the zero pose)",
                            name(h)
                        ),
                        of: Box::new(move |m, _| m[h]),
                    },
                ],
            ))
        }
        _ => Err(unsupported(
            k,
            &format!(
                "{} table and {} head axes on FANUC",
                table.len(),
                head.len()
            ),
        )),
    }
}

fn fanuc_form(
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<Form, OffsetsError> {
    let inc = opts.fanuc_increment_mm;
    if !(units::positive(inc) && inc <= 0.01) {
        return Err(OffsetsError::BadOption(format!(
            "fanuc_increment_mm = {inc}: the increment of 19700-19714 in mm (0.001 IS-B, 0.0001 IS-C)"
        )));
    }
    let (kind, vectors) = fanuc_vectors(k)?;
    let written = moved(k, &|e| {
        let (m, t) = line_moves(k, e);
        vectors.iter().map(|v| (v.of)(&m, &t)).collect()
    });
    let (m, t) = line_moves(k, errors);
    let mut raw = Vec::new();
    let mut missing = Vec::new();
    for (v, w) in vectors.iter().zip(&written) {
        let d = (v.of)(&m, &t);
        for c in (0..3).filter(|c| w[*c]) {
            let number: u32 = v.names[c].parse().unwrap_or(0);
            let Some(nominal) = opts.fanuc_nominal_mm.get(&number) else {
                missing.push(number);
                continue;
            };
            raw.push(Raw {
                name: v.names[c].clone(),
                label: format!("{} {}", v.label, ["X", "Y", "Z"][c]),
                meaning: format!(
                    "{}, {}: nominal {nominal} mm + offset",
                    v.meaning,
                    &"xyz"[c..=c]
                ),
                unit: format!("{inc} mm"),
                exact: (nominal + d[c]) / inc,
                decimals: 0,
            });
        }
    }
    if !missing.is_empty() {
        return Err(OffsetsError::MissingNominal { params: missing });
    }
    Ok(Form {
        raw,
        // No parameter confirmed for a rotary axis' small tilt (19682-19690 set the direction
        // as a machine axis or one inclination angle): orientations are not written.
        writes: |n| !n.is_angular(),
        kinematic_type: format!("19680 = {kind}"),
        notes: vec![
            "the pivot is also held elsewhere: work offsets (G54..) taught at a tilted pose, the \
             tilted working plane (G68.2) and CAM posts with the pivot built in must be kept \
             consistent with these parameters"
                .into(),
            "orientation errors are not written: no FANUC parameter for a rotary axis' small \
             tilt was confirmed in the sources (docs/nc.md)"
                .into(),
        ],
    })
}

/// The Siemens vectors of the swivel data record (IM9 commissioning manual, "Swiveling"):
/// table-table (type P) l2 machine reference to the 1st axis, l3 1st to 2nd, l4 closing the
/// chain; mixed (type M) l2 tool adapter to the 1st (head) axis, l1 = -l2, l3 machine
/// reference to the 2nd (table) axis, l4 = -l3. Fine offsets are the basic number + 40.
fn siemens_vectors(
    k: &Kinematics,
    n: u32,
    sign: f64,
) -> Result<(char, Vec<NcVector>), OffsetsError> {
    let (table, head) = sides(k);
    let carr = |first: u32| [0, 1, 2].map(|c| format!("$TC_CARR{}[{n}]", first + c));
    let fine = |first: u32, label: &str, meaning: String, f: VectorOf| NcVector {
        names: carr(first),
        label: label.into(),
        meaning,
        of: f,
    };
    let axis = |first: u32, label: &str, i: usize| {
        let u0 = k.rotary[i].u0;
        NcVector {
            names: carr(first),
            label: label.into(),
            meaning: format!(
                "rotary axis vector of {} (absolute: its actual direction, sign {sign:+})",
                k.rotary[i].name
            ),
            of: Box::new(move |_, t| (u0 + t[i]).normalize() * sign),
        }
    };
    let name = |i: usize| k.rotary[i].name.clone();
    match (table.as_slice(), head.as_slice()) {
        ([a, b], []) => {
            let (a, b) = (*a, *b);
            let ub = k.rotary[b].u0;
            let l3 = move |m: &[Vec3]| square_to(m[b] - m[a], ub);
            Ok((
                'P',
                vec![
                    fine(
                        44,
                        "l2 fine",
                        format!(
                            "l2 fine offset: machine reference to the {} axis (its line's move)",
                            name(a)
                        ),
                        Box::new(move |m, _| m[a]),
                    ),
                    fine(
                        55,
                        "l3 fine",
                        format!(
                            "l3 fine offset: {} axis to {} axis (the {} line's move less the {} line's, square to {})",
                            name(a),
                            name(b),
                            name(b),
                            name(a),
                            name(b)
                        ),
                        Box::new(move |m, _| l3(m)),
                    ),
                    fine(
                        58,
                        "l4 fine",
                        "l4 fine offset: closes the chain, -(l2 + l3)".into(),
                        Box::new(move |m, _| -(m[a] + l3(m))),
                    ),
                    axis(7, "v1", a),
                    axis(10, "v2", b),
                ],
            ))
        }
        ([t], [h]) => {
            let (t, h) = (*t, *h);
            Ok((
                'M',
                vec![
                    fine(
                        41,
                        "l1 fine",
                        "l1 fine offset: closes the head chain, -l2".into(),
                        Box::new(move |m, _| -m[h]),
                    ),
                    fine(
                        44,
                        "l2 fine",
                        format!(
                            "l2 fine offset: tool adapter to the {} axis (its line's move in the head frame)",
                            name(h)
                        ),
                        Box::new(move |m, _| m[h]),
                    ),
                    fine(
                        55,
                        "l3 fine",
                        format!(
                            "l3 fine offset: machine reference to the {} axis (its line's move)",
                            name(t)
                        ),
                        Box::new(move |m, _| m[t]),
                    ),
                    fine(
                        58,
                        "l4 fine",
                        "l4 fine offset: closes the table chain, -l3".into(),
                        Box::new(move |m, _| -m[t]),
                    ),
                    axis(7, "v1", h),
                    axis(10, "v2", t),
                ],
            ))
        }
        _ => Err(unsupported(
            k,
            &format!(
                "{} table and {} head axes on Siemens",
                table.len(),
                head.len()
            ),
        )),
    }
}

fn siemens_form(
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<Form, OffsetsError> {
    let sign = opts.siemens_axis_sign;
    if sign != 1.0 && sign != -1.0 {
        return Err(OffsetsError::BadOption(format!(
            "siemens_axis_sign = {sign}: +1 or -1"
        )));
    }
    let (kind, vectors) = siemens_vectors(k, opts.siemens_carrier, sign)?;
    // A rotary axis vector is written whole when any error turns it; an offset component only
    // when an error moves it.
    let written = moved(k, &|e| {
        let (m, t) = line_moves(k, e);
        let zero = vec![Vec3::zeros(); t.len()];
        vectors
            .iter()
            .map(|v| (v.of)(&m, &t) - (v.of)(&vec![Vec3::zeros(); m.len()], &zero))
            .collect()
    });
    let (m, t) = line_moves(k, errors);
    let mut raw = Vec::new();
    for (v, w) in vectors.iter().zip(&written) {
        let is_axis = v.label.starts_with('v');
        let d = (v.of)(&m, &t);
        for c in (0..3).filter(|c| if is_axis { w.iter().any(|x| *x) } else { w[*c] }) {
            raw.push(Raw {
                name: v.names[c].clone(),
                label: format!("{} {}", v.label, &"xyz"[c..=c]),
                meaning: format!("{}, {}", v.meaning, &"xyz"[c..=c]),
                unit: if is_axis { "1".into() } else { "mm".into() },
                exact: d[c],
                decimals: if is_axis { 7 } else { 4 },
            });
        }
    }
    Ok(Form {
        raw,
        writes: |_| true,
        kinematic_type: format!("$TC_CARR23[{}] = \"{kind}\"", opts.siemens_carrier),
        notes: vec![
            "offsets go to the fine offsets ($TC_CARR41-60, added by the control to the basic \
             l1-l4): the basic vectors keep the commissioned geometry; the fine offsets act only \
             where the machine data enable them (see docs/nc.md)"
                .into(),
            "v1/v2 are absolute unit vectors: the actual direction of each axis that has an \
             identified tilt"
                .into(),
            "the record takes effect when it is next selected (TCARR / CYCLE800)".into(),
        ],
    })
}

fn heidenhain_form(
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<Form, OffsetsError> {
    let layout = NcLayout::of(k);
    let values = layout.offsets(errors);
    let mut raw = Vec::new();
    // The direction-vector form repeats the tilts: one of the two forms is enough here.
    for (i, o) in layout
        .offsets
        .iter()
        .filter(|o| !o.name.contains("_dir_"))
        .enumerate()
    {
        let Some(v) = values.get(&o.name) else {
            continue;
        };
        let angular = o.unit == "urad";
        let q = opts.heidenhain_q_base.saturating_add(i as u32);
        raw.push(Raw {
            name: format!("Q{q}"),
            label: format!("{} in {}", o.name, if angular { "deg" } else { "mm" }),
            meaning: format!(
                "{} in {} for the OEM cycle that loads the kinematics",
                o.name,
                if angular { "deg" } else { "mm" }
            ),
            unit: if angular { "deg".into() } else { "mm".into() },
            exact: if angular {
                (v * 1e-6).to_degrees()
            } else {
                v * 1e-3
            },
            decimals: if angular { 6 } else { 4 },
        });
    }
    Ok(Form {
        raw,
        writes: |_| true,
        kinematic_type: "kinematics description (OEM)".into(),
        notes: vec![
            "the kinematics description is written by the machine builder's tools or \
             KinematicsOpt (cycles 451/452) only; these Q parameters carry the offsets for an \
             OEM cycle that loads them: without one they change nothing"
                .into(),
            "a preset taught at a tilted pose moves with the kinematics: check or reset it after \
             the load"
                .into(),
        ],
    })
}

/// The LinuxCNC trt kinematics a chain is: its module and the tilting and the rotary table
/// axis. `xyzbc-trt-kins` and `xyzac-trt-kins` turn a table point `p` to the joints
/// `rp + D + R_T(t) (Rz(c) (p - rp) - D)` (LinuxCNC's `trtfuncs.c`): C about the vertical line
/// through the rotation point `rp`, the tilting axis T (B along +Y, A along +X) about the line
/// through `rp + D`, both turning the table positively for a positive command.
fn linuxcnc_chain(k: &Kinematics) -> Result<(&'static str, usize, usize), OffsetsError> {
    let refuse = |message: String| OffsetsError::Unsupported {
        machine: k.name.clone(),
        message,
    };
    let (table, head) = sides(k);
    let ([t, c], []) = (table.as_slice(), head.as_slice()) else {
        return Err(refuse(format!(
            "LinuxCNC's trt kinematics (xyzbc-trt-kins, xyzac-trt-kins) take two table axes and \
             no head axis; this chain has {} table and {} head axes",
            table.len(),
            head.len()
        )));
    };
    let (t, c) = (*t, *c);
    let along = |i: usize, v: Vec3| (k.rotary[i].u0 - v).norm() < 1e-9;
    if !along(c, Vec3::z()) {
        return Err(refuse(format!(
            "LinuxCNC's trt kinematics turn the inner table axis about +Z; {} lies along {}",
            k.rotary[c].name, k.rotary[c].u0
        )));
    }
    let kins = if along(t, Vec3::y()) {
        "xyzbc-trt-kins"
    } else if along(t, Vec3::x()) {
        "xyzac-trt-kins"
    } else {
        return Err(refuse(format!(
            "LinuxCNC's trt kinematics tilt the table about +Y (xyzbc-trt-kins) or +X \
             (xyzac-trt-kins); {} lies along {}",
            k.rotary[t].name, k.rotary[t].u0
        )));
    };
    let iso: Vec<&str> = [t, c]
        .into_iter()
        .filter(|i| k.rotary[*i].sign < 0.0)
        .map(|i| k.rotary[i].name.as_str())
        .collect();
    if !iso.is_empty() {
        return Err(refuse(format!(
            "{} in the ISO 841 table sense (sense = \"table\": the table turns negatively for a \
             positive command), but LinuxCNC's trt kinematics turn the table positively for a \
             positive command: describe the machine with sense = \"direct\" on both table \
             axes, as in deploy/linuxcnc/machines",
            iso.join(" and ")
        )));
    }
    Ok((kins, t, c))
}

/// LinuxCNC's trt kinematics: the C line is vertical through `(x-rot-point, y-rot-point)`, so
/// those grow by the C line's move square to C; the tilting line passes through the rotation
/// point plus `(x-offset, ., z-offset + tool-offset)` (B) or `(., y-offset, z-offset +
/// tool-offset)` (A), so the offset grows by the tilting line's move less the C line's, square
/// to the tilting axis. `z-rot-point` is never written (no position along C), nor
/// `tool-offset` (the loaded tool's, from motion).
fn linuxcnc_form(
    k: &Kinematics,
    errors: &BTreeMap<ErrorName, f64>,
    opts: &NcOptions,
) -> Result<Form, OffsetsError> {
    let (kins, t, c) = linuxcnc_chain(k)?;
    let unknown: Vec<&str> = opts
        .linuxcnc_nominal_mm
        .keys()
        .map(String::as_str)
        .filter(|p| !LINUXCNC_PINS.contains(p))
        .collect();
    if !unknown.is_empty() {
        return Err(OffsetsError::BadOption(format!(
            "linuxcnc_nominal_mm: no pin {} in the trt kinematics; the pins are {}",
            unknown.join(", "),
            LINUXCNC_PINS.join(", ")
        )));
    }
    let (ut, uc) = (k.rotary[t].u0, k.rotary[c].u0);
    let (tn, cn) = (k.rotary[t].name.clone(), k.rotary[c].name.clone());
    let rot = move |m: &[Vec3]| square_to(m[c], uc);
    let pins = |v: &str| ["x", "y", "z"].map(|a| format!("{a}-{v}"));
    let vectors = [
        NcVector {
            names: pins("rot-point"),
            label: "rotation point".into(),
            meaning: format!(
                "rotation point: the {cn} line (vertical through it) moved by its line's move"
            ),
            of: Box::new(move |m, _| rot(m)),
        },
        NcVector {
            names: pins("offset"),
            label: "offset".into(),
            meaning: format!(
                "offset: the {tn} line from the rotation point, grown by the {tn} line's move \
                 less the {cn} line's, square to {tn}"
            ),
            of: Box::new(move |m, _| square_to(m[t] - rot(m), ut)),
        },
    ];
    let written = moved(k, &|e| {
        let (m, tt) = line_moves(k, e);
        vectors.iter().map(|v| (v.of)(&m, &tt)).collect()
    });
    let (m, tt) = line_moves(k, errors);
    let mut raw = Vec::new();
    let mut missing = Vec::new();
    let mut written_pins = Vec::new();
    for (v, w) in vectors.iter().zip(&written) {
        let d = (v.of)(&m, &tt);
        for i in (0..3).filter(|i| w[*i]) {
            let pin = &v.names[i];
            written_pins.push(pin.as_str());
            let Some(nominal) = opts.linuxcnc_nominal_mm.get(pin) else {
                missing.push(pin.clone());
                continue;
            };
            raw.push(Raw {
                name: format!("{kins}.{pin}"),
                label: pin.clone(),
                meaning: format!(
                    "{}, {}: nominal {nominal} mm + offset",
                    v.meaning,
                    &"xyz"[i..=i]
                ),
                unit: "mm".into(),
                exact: nominal + d[i],
                decimals: 6,
            });
        }
    }
    if !missing.is_empty() {
        return Err(OffsetsError::MissingPinNominal {
            kins: kins.into(),
            pins: missing,
        });
    }
    let mut notes = vec![
        format!(
            "{kins} reads these pins whenever it runs: the joints move by the datum shift at \
             the current pose with the next move at the latest; load the script with the \
             machine at rest, not in a cut"
        ),
        "setp sets an unlinked pin only: the pins written here must be set with setp in the \
         HAL file, not driven by a signal"
            .into(),
        format!(
            "orientation and zero-angle errors are not written: {kins} holds the {cn} line \
             along Z and the {tn} line along {} exactly, and has no pin for a tilt",
            ["X", "Y", "Z"][ut.iamax()]
        ),
    ];
    let held: Vec<String> = k
        .held
        .iter()
        .filter(|(id, v)| !id.is_position() && *v != 0.0)
        .map(|(id, v)| format!("{} = {v} urad", k.error_name(*id)))
        .collect();
    if !held.is_empty() {
        notes.push(format!(
            "held in the machine file, and not held by {kins} either: {}",
            held.join(", ")
        ));
    }
    let ignored: Vec<&str> = opts
        .linuxcnc_nominal_mm
        .keys()
        .map(String::as_str)
        .filter(|p| !written_pins.contains(p))
        .collect();
    if !ignored.is_empty() {
        notes.push(format!(
            "commissioned values given for pins no identified error moves ({}): not written, \
             the pins keep their values",
            ignored.join(", ")
        ));
    }
    Ok(Form {
        raw,
        writes: |n| !n.is_angular(),
        kinematic_type: format!("KINEMATICS = {kins}"),
        notes,
    })
}

// ---------------------------------------------------------------------------------------------
// Datum shift
// ---------------------------------------------------------------------------------------------

/// The zero pose, then each axis alone at -90 and +90 deg where its travel allows.
fn default_poses(k: &Kinematics) -> Vec<Vec<f64>> {
    let n = k.rotary.len();
    let mut poses = vec![vec![0.0; n]];
    for (i, ax) in k.rotary.iter().enumerate() {
        for a in [-90.0, 90.0] {
            if ax.travel_deg[0] <= a && a <= ax.travel_deg[1] {
                let mut p = vec![0.0; n];
                p[i] = a;
                poses.push(p);
            }
        }
    }
    poses
}

/// Where the part zero lies relative to the tool tip at a pose in the NC's model of `state`, mm.
fn part_from_tool(k: &Kinematics, state: &MachineState, pose: &[f64], origin: &Vec3) -> Vec3 {
    let mut angles = [0.0; MAX_ROTARY];
    angles[..pose.len()].copy_from_slice(pose);
    let lines = k.lines(state);
    let part = k.pose_transform_on(&lines, state, &angles).point(origin);
    let tool = k.tool_pose_on(&lines, state, &angles);
    part - (tool.actual - tool.nominal)
}

/// How far the part zero moves against the tool at each pose when the NC's model goes from the
/// previous set (or no compensation) to `set`, through the kinematics on the machine's held
/// errors; only the errors the form writes move it.
fn datum_shift(
    k: &Kinematics,
    set: &CompensationSet,
    previous: Option<&CompensationSet>,
    writes: fn(ErrorName) -> bool,
    opts: &NcOptions,
) -> Result<Vec<DatumShift>, OffsetsError> {
    let poses = if opts.poses_deg.is_empty() {
        default_poses(k)
    } else {
        opts.poses_deg.clone()
    };
    let origin = Vec3::from(opts.work_origin_mm);
    if !origin.iter().all(|x| x.is_finite()) {
        return Err(OffsetsError::BadOption(
            "work_origin_mm is not finite".into(),
        ));
    }
    let after = state_of(k, &set.errors, writes, true);
    let none = BTreeMap::new();
    let before = state_of(k, previous.map_or(&none, |p| &p.errors), writes, true);
    poses
        .iter()
        .map(|pose| {
            if pose.len() != k.rotary.len() || !pose.iter().all(|a| a.is_finite()) {
                return Err(OffsetsError::BadOption(format!(
                    "pose {pose:?}: {} finite angles (deg), one per rotary axis of {}",
                    k.rotary.len(),
                    k.name
                )));
            }
            let d = (part_from_tool(k, &after, pose, &origin)
                - part_from_tool(k, &before, pose, &origin))
                * 1e3;
            Ok(DatumShift {
                pose: k.pose_label(pose),
                pose_deg: pose.clone(),
                shift_um: [d.x, d.y, d.z],
                norm_um: d.norm(),
            })
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Programs
// ---------------------------------------------------------------------------------------------

fn round_to(x: f64, decimals: usize) -> f64 {
    let f = 10f64.powi(decimals as i32);
    // + 0.0: no "-0" in a program.
    (x * f).round() / f + 0.0
}

fn number(x: f64, decimals: usize, signed: bool) -> String {
    if signed {
        format!("{x:+.decimals$}")
    } else {
        format!("{x:.decimals$}")
    }
}

fn step_text(v: &NcVariable) -> String {
    match v.step {
        Some(s) => format!("step {s:+} {}", v.unit),
        None => "no previous set".into(),
    }
}

fn header(o: &NcOffsets, set: &CompensationSet) -> Vec<String> {
    let mut h = vec![
        format!(
            "driftwatch offsets: {} set {} ({:?}{})",
            o.machine,
            o.version,
            set.source,
            set.cycle
                .map(|c| format!(", cycle {c}"))
                .unwrap_or_default()
        ),
        format!(
            "previous served set: {}",
            o.previous_version
                .map_or("none".to_string(), |v| v.to_string())
        ),
        format!("kinematics: {}", o.kinematic_type),
    ];
    h.extend(o.notes.iter().cloned());
    for n in &o.not_written {
        h.push(format!("not written: {n}"));
    }
    for d in &o.datum_shift {
        h.push(format!(
            "part zero moves at {}: x {:+.1} y {:+.1} z {:+.1} um",
            d.pose, d.shift_um[0], d.shift_um[1], d.shift_um[2]
        ));
    }
    h
}

fn program(
    o: &NcOffsets,
    labels: &[&str],
    set: &CompensationSet,
    opts: &NcOptions,
) -> Option<String> {
    let head = header(o, set);
    let mut p = String::new();
    match o.format {
        OffsetFormat::Json => return None,
        OffsetFormat::Fanuc => {
            // FANUC comments: parentheses, upper case, no parentheses or quotes inside.
            let c = |s: &str| s.to_uppercase().replace(['(', ')', '\''], "");
            let _ = writeln!(p, "%\nO{:04} (DRIFTWATCH OFFSETS)", opts.fanuc_program);
            for line in &head {
                let _ = writeln!(p, "({})", c(line));
            }
            let _ = writeln!(p, "G10 L52");
            for (v, l) in o.variables.iter().zip(labels) {
                let _ = writeln!(
                    p,
                    "N{} R{} ({}, {})",
                    v.name,
                    v.text,
                    c(l),
                    c(&step_text(v))
                );
            }
            let _ = writeln!(p, "G11\nM30\n%");
        }
        OffsetFormat::Siemens => {
            for line in &head {
                let _ = writeln!(p, "; {line}");
            }
            for (v, l) in o.variables.iter().zip(labels) {
                let _ = writeln!(p, "{}={} ; {l}, {}", v.name, v.text, step_text(v));
            }
            let _ = writeln!(p, "M30");
        }
        OffsetFormat::Heidenhain => {
            let mut n = 0;
            let mut block = |p: &mut String, s: &str| {
                let _ = writeln!(p, "{n} {s}");
                n += 1;
            };
            block(&mut p, "BEGIN PGM DWOFFSET MM");
            for line in &head {
                block(&mut p, &format!("; {line}"));
            }
            for (v, l) in o.variables.iter().zip(labels) {
                block(
                    &mut p,
                    &format!("FN 0: {} = {} ; {l}, {}", v.name, v.text, step_text(v)),
                );
            }
            block(&mut p, "END PGM DWOFFSET MM");
        }
        OffsetFormat::Linuxcnc => {
            // A halcmd script (`halcmd -f`): comments are whole lines starting with '#', one
            // `setp PIN VALUE` per pin.
            for line in &head {
                let _ = writeln!(p, "# {line}");
            }
            for (v, l) in o.variables.iter().zip(labels) {
                let _ = writeln!(p, "# {l}, {}", step_text(v));
                let _ = writeln!(p, "setp {} {}", v.name, v.text);
            }
        }
    }
    Some(p)
}

/// The `format=json` answer (API and `nc offsets --format json`): the set exactly as served,
/// plus the variables with their steps, what no variable carries, the notes, the datum shift
/// and the previous version.
pub fn json_body(set: &CompensationSet, o: &NcOffsets) -> serde_json::Value {
    let mut body = compensation_message(set);
    // `NcOffsets` is plain data with string keys: serialising it cannot fail.
    if let (Some(m), Ok(serde_json::Value::Object(extra))) =
        (body.as_object_mut(), serde_json::to_value(o))
    {
        for key in [
            "previous_version",
            "variables",
            "not_written",
            "notes",
            "datum_shift",
        ] {
            if let Some(v) = extra.get(key) {
                m.insert(key.to_string(), v.clone());
            }
        }
    }
    body
}

#[cfg(test)]
mod tests {
    use super::*;
    use driftwatch_core::geometry::rotation;
    use driftwatch_machine::compensation::Source;

    fn machine(name: &str) -> Kinematics {
        Kinematics::builtin(name).unwrap()
    }

    /// A set of `machine` with the given errors (um, urad), served at minute `min`.
    fn set(k: &Kinematics, version: u64, min: f64, values: &[(&str, f64)]) -> CompensationSet {
        let errors: BTreeMap<ErrorName, f64> = values
            .iter()
            .map(|(n, v)| (ErrorName::parse(n).unwrap(), *v))
            .collect();
        let layout = NcLayout::of(k);
        CompensationSet {
            version,
            valid_from_ns: (min * 60e9) as i64,
            source: Source::Measured,
            cycle: Some(version as i64),
            offsets: layout.offsets(&errors),
            sigma: errors.keys().map(|n| (*n, 0.5)).collect(),
            errors,
            reason: "test".into(),
        }
    }

    const BC: [(&str, f64); 6] = [
        ("EX0B", 12.3456),
        ("EZ0B", -31.26),
        ("EY0C", 4.44),
        ("EX0C", -7.05),
        ("EA0C", 21.0),
        ("EB0C", -13.0),
    ];

    fn value(o: &NcOffsets, name: &str) -> f64 {
        o.variables
            .iter()
            .find(|v| v.name == name)
            .unwrap_or_else(|| panic!("{name} not in {:?}", o.variables))
            .value
    }

    fn names(o: &NcOffsets) -> Vec<&str> {
        o.variables.iter().map(|v| v.name.as_str()).collect()
    }

    fn fanuc_opts(nominal: &[(u32, f64)]) -> NcOptions {
        NcOptions {
            fanuc_nominal_mm: nominal.iter().copied().collect(),
            ..NcOptions::default()
        }
    }

    fn run(
        f: OffsetFormat,
        k: &Kinematics,
        s: &CompensationSet,
        prev: Option<&CompensationSet>,
        opts: &NcOptions,
    ) -> Result<NcOffsets, OffsetsError> {
        nc_offsets(f, k, s, prev, &ValidationLimits::default(), opts)
    }

    /// table_bc on FANUC: the B line's move in the rotary table position, the C line's move
    /// relative to B in the intersection offset (EX0C, EY0C: docs/integrate-nc.md's C_pivot_x - B_pivot_x),
    /// nominal + offset in increments, rounded to the nearest; the tilts not written.
    #[test]
    fn table_bc_on_fanuc_writes_nominal_plus_offset_in_increments() {
        let k = machine("table_bc");
        let s = set(&k, 1, 0.0, &BC);
        let nominal = [
            (19700, -123.456),
            (19702, 50.0),
            (19703, 0.25),
            (19704, -0.125),
        ];
        let o = run(OffsetFormat::Fanuc, &k, &s, None, &fanuc_opts(&nominal)).unwrap();
        assert_eq!(names(&o), ["19700", "19702", "19703", "19704"]);
        assert_eq!(o.kinematic_type, "19680 = 12");
        // (-123.456 mm + 12.3456 um) / 0.001 mm = -123443.6544 -> -123444
        assert_eq!(value(&o, "19700"), -123444.0);
        assert!((o.variables[0].rounding - (-0.3456)).abs() < 1e-6);
        assert_eq!(value(&o, "19702"), 50000.0 - 31.0);
        assert_eq!(value(&o, "19703"), 250.0 - 7.0);
        assert_eq!(value(&o, "19704"), -125.0 + 4.0);
        assert_eq!(o.variables[0].unit, "0.001 mm");
        assert!(o.not_written.iter().any(|n| n.starts_with("EA0C")));
        assert!(o.not_written.iter().any(|n| n.starts_with("EB0C")));
        let p = o.program.as_deref().unwrap();
        assert!(p.contains("G10 L52\nN19700 R-123444 ("), "{p}");
        assert!(p.contains("\nG11\nM30\n"), "{p}");
        assert!(
            p.contains("G68.2"),
            "the pivot pitfall is in the program: {p}"
        );
        assert!(
            !p.lines()
                .any(|l| l.starts_with('(') && l[1..l.len() - 1].contains('('))
        );
        // IS-C: ten times finer.
        let mut opts = fanuc_opts(&nominal);
        opts.fanuc_increment_mm = 0.0001;
        let o = run(OffsetFormat::Fanuc, &k, &s, None, &opts).unwrap();
        assert_eq!(value(&o, "19700"), -1234437.0);
        assert_eq!(o.variables[0].unit, "0.0001 mm");
    }

    #[test]
    fn fanuc_without_the_commissioned_values_is_refused_naming_them() {
        let k = machine("table_bc");
        let s = set(&k, 1, 0.0, &BC);
        let e = run(
            OffsetFormat::Fanuc,
            &k,
            &s,
            None,
            &fanuc_opts(&[(19700, 1.0)]),
        )
        .unwrap_err();
        assert_eq!(
            e,
            OffsetsError::MissingNominal {
                params: vec![19702, 19703, 19704]
            }
        );
    }

    /// The mixed B head over a C table (19680 = 21): the C line in the rotary table position,
    /// the head's pivot in the tool axis to tool rotation axis offset.
    #[test]
    fn head_b_table_c_on_fanuc_is_the_mixed_type() {
        let k = machine("head_b_table_c");
        let s = set(&k, 1, 0.0, &BC);
        let nominal: Vec<(u32, f64)> = [19700, 19701, 19709, 19711]
            .iter()
            .map(|p| (*p, 0.0))
            .collect();
        let o = run(OffsetFormat::Fanuc, &k, &s, None, &fanuc_opts(&nominal)).unwrap();
        assert_eq!(o.kinematic_type, "19680 = 21");
        assert_eq!(names(&o), ["19700", "19701", "19709", "19711"]);
        assert_eq!(value(&o, "19700"), -7.0); // EX0C
        assert_eq!(value(&o, "19701"), 4.0); // EY0C
        assert_eq!(value(&o, "19709"), 12.0); // EX0B
        assert_eq!(value(&o, "19711"), -31.0); // EZ0B
    }

    /// table_bc on Siemens (type P): l2 the B line's move, l3 the C line's relative to it,
    /// l4 closing the chain, all as fine offsets in mm; v2 the tilted C direction.
    #[test]
    fn table_bc_on_siemens_fills_the_fine_offsets_of_the_part_chain() {
        let k = machine("table_bc");
        let s = set(&k, 1, 0.0, &BC);
        let o = run(OffsetFormat::Siemens, &k, &s, None, &NcOptions::default()).unwrap();
        assert_eq!(o.kinematic_type, "$TC_CARR23[1] = \"P\"");
        let c = |n: u32| value(&o, &format!("$TC_CARR{n}[1]"));
        assert_eq!(c(44), 0.0123); // EX0B 12.3456 um, 0.1 um resolution
        assert_eq!(c(46), -0.0313); // EZ0B
        assert_eq!(c(55), -0.0071); // EX0C
        assert_eq!(c(56), 0.0044); // EY0C
        assert_eq!(c(58), -0.0053); // -(EX0B + EX0C)
        assert_eq!(c(59), -0.0044);
        assert_eq!(c(60), 0.0313);
        // C direction (EB0C, -EA0C, 1) to first order; B has no identified tilt: v1 unwritten.
        assert!((c(10) - (-13e-6)).abs() < 1e-7 && (c(11) - (-21e-6)).abs() < 1e-7);
        assert_eq!(c(12), 1.0);
        let n = names(&o);
        for absent in [45, 57, 7, 8, 9] {
            assert!(
                !n.contains(&format!("$TC_CARR{absent}[1]").as_str()),
                "{n:?}"
            );
        }
        let p = o.program.unwrap();
        assert!(p.contains("\n$TC_CARR44[1]=0.0123 ; l2 fine x"), "{p}");
        assert!(p.ends_with("M30\n"));
    }

    /// The mixed machine on Siemens (type M): the head's pivot in l2 (and -l2 in l1), the C line
    /// in l3 (and -l3 in l4), into record 2 with the axis vectors against the machine file's.
    #[test]
    fn head_b_table_c_on_siemens_is_the_mixed_type() {
        let k = machine("head_b_table_c");
        let s = set(&k, 1, 0.0, &BC);
        let opts = NcOptions {
            siemens_carrier: 2,
            siemens_axis_sign: -1.0,
            ..NcOptions::default()
        };
        let o = run(OffsetFormat::Siemens, &k, &s, None, &opts).unwrap();
        assert_eq!(o.kinematic_type, "$TC_CARR23[2] = \"M\"");
        let c = |n: u32| value(&o, &format!("$TC_CARR{n}[2]"));
        assert_eq!((c(44), c(46)), (0.0123, -0.0313));
        assert_eq!((c(41), c(43)), (-0.0123, 0.0313));
        assert_eq!((c(55), c(56)), (-0.0071, 0.0044));
        assert_eq!((c(58), c(59)), (0.0071, -0.0044));
        assert_eq!(c(12), -1.0);
        assert!((c(10) - 13e-6).abs() < 1e-7);
    }

    /// HEIDENHAIN: each offset in its Q parameter, positions in mm, tilts in deg.
    #[test]
    fn table_bc_on_heidenhain_writes_q_parameters_in_mm_and_deg() {
        let k = machine("table_bc");
        let s = set(&k, 1, 0.0, &BC);
        let o = run(
            OffsetFormat::Heidenhain,
            &k,
            &s,
            None,
            &NcOptions::default(),
        )
        .unwrap();
        assert_eq!(
            names(&o),
            ["Q1600", "Q1601", "Q1602", "Q1603", "Q1604", "Q1605"]
        );
        assert_eq!(value(&o, "Q1602"), 0.0053); // C_pivot_x = EX0B + EX0C
        // C_tilt_a = 21 urad = 0.00120321 deg
        assert_eq!(value(&o, "Q1604"), 0.001203);
        assert_eq!(o.variables[4].text, "+0.001203");
        let p = o.program.unwrap();
        assert!(p.starts_with("0 BEGIN PGM DWOFFSET MM\n"), "{p}");
        assert!(p.contains(" FN 0: Q1600 = +0.0123 ; B_pivot_x_um"), "{p}");
        assert!(p.trim_end().ends_with("END PGM DWOFFSET MM"));
    }

    #[test]
    fn json_is_the_layouts_offsets() {
        let k = machine("trunnion_ac");
        let s = set(
            &k,
            1,
            0.0,
            &[
                ("EY0A", 3.0),
                ("EZ0A", -4.0),
                ("EX0C", 1.0),
                ("EY0C", 2.0),
                ("EA0C", 5.0),
                ("EB0C", 6.0),
            ],
        );
        let o = run(OffsetFormat::Json, &k, &s, None, &NcOptions::default()).unwrap();
        assert!(o.program.is_none());
        assert_eq!(o.variables.len(), s.offsets.len());
        for v in &o.variables {
            assert_eq!(v.value, s.offsets[&v.name], "{}", v.name);
        }
        assert_eq!(value(&o, "C_pivot_y_um"), 5.0); // EY0A + EY0C
    }

    /// The step from the previous served set per variable, and a step beyond the validation's
    /// limit (50 um + 4 um/min by default) refused: allowed once enough minutes passed.
    #[test]
    fn steps_are_stated_and_a_step_beyond_the_limit_is_refused() {
        let k = machine("table_bc");
        let prev = set(&k, 3, 0.0, &BC);
        let mut moved = BC;
        moved[1].1 += 10.0; // EZ0B
        let next = set(&k, 4, 1.0, &moved);
        let o = run(
            OffsetFormat::Siemens,
            &k,
            &next,
            Some(&prev),
            &NcOptions::default(),
        )
        .unwrap();
        let step = |n: &str| o.variables.iter().find(|v| v.name == n).unwrap().step;
        assert_eq!(step("$TC_CARR46[1]"), Some(0.01));
        assert_eq!(step("$TC_CARR60[1]"), Some(-0.01));
        assert_eq!(step("$TC_CARR44[1]"), Some(0.0));
        assert_eq!(o.previous_version, Some(3));

        moved[1].1 += 50.0; // 60 um in 1 min: over 54
        let far = set(&k, 4, 1.0, &moved);
        let e = run(
            OffsetFormat::Fanuc,
            &k,
            &far,
            Some(&prev),
            &NcOptions::default(),
        )
        .unwrap_err();
        match e {
            OffsetsError::StepBeyondLimit {
                steps,
                previous: 3,
                version: 4,
            } => {
                assert_eq!(steps.len(), 1);
                assert!(steps[0].starts_with("EZ0B"), "{steps:?}");
            }
            e => panic!("{e}"),
        }
        let later = set(&k, 4, 3.0, &moved); // 62 um allowed after 3 min
        assert!(
            run(
                OffsetFormat::Json,
                &k,
                &later,
                Some(&prev),
                &NcOptions::default()
            )
            .is_ok()
        );
        let e = run(
            OffsetFormat::Json,
            &k,
            &prev,
            Some(&later),
            &NcOptions::default(),
        );
        assert!(matches!(e, Err(OffsetsError::PreviousNotOlder { .. })));
    }

    #[test]
    fn a_set_that_does_not_look_validated_is_refused() {
        let k = machine("table_bc");
        let mut s = set(&k, 1, 0.0, &BC);
        s.errors.insert(ErrorName::from_static("EZ0B"), f64::NAN);
        s.errors.insert(ErrorName::from_static("EY0A"), 1.0);
        s.sigma.remove(&ErrorName::from_static("EX0B"));
        let e = run(OffsetFormat::Json, &k, &s, None, &NcOptions::default()).unwrap_err();
        let OffsetsError::NotValidated { reasons, .. } = e else {
            panic!("{e}");
        };
        assert_eq!(reasons.len(), 3, "{reasons:?}");
        let mut s = set(&k, 1, 0.0, &BC);
        s.errors.insert(ErrorName::from_static("EZ0B"), 250.0); // beyond 200 um
        assert!(run(OffsetFormat::Json, &k, &s, None, &NcOptions::default()).is_err());
    }

    /// The datum shift against a calculation of its own: on table_bc at B = -90 the table
    /// turns about the B line through q = (EX0B, 0, EZ0B) instead of the origin, so a table
    /// point moves by (I - R) q, R the rotation the pose makes (ISO 841: +90 deg about +Y).
    /// At the zero pose nothing moves. FANUC leaves the tilts out of it; Siemens does not.
    #[test]
    fn the_datum_shift_follows_the_kinematics() {
        let k = machine("table_bc");
        let s = set(&k, 1, 0.0, &BC);
        let opts = NcOptions {
            work_origin_mm: [40.0, -25.0, 60.0],
            poses_deg: vec![vec![0.0, 0.0], vec![-90.0, 0.0], vec![0.0, 90.0]],
            ..fanuc_opts(&[(19700, 0.0), (19702, 0.0), (19703, 0.0), (19704, 0.0)])
        };
        let o = run(OffsetFormat::Fanuc, &k, &s, None, &opts).unwrap();
        assert_eq!(o.datum_shift[0].norm_um, 0.0);
        assert_eq!(o.datum_shift[1].pose, "B-90C0");
        let q = Vec3::new(12.3456e-3, 0.0, -31.26e-3);
        let r = rotation(&Vec3::y(), 90f64.to_radians());
        let want = (q - r * q) * 1e3;
        let got = Vec3::from(o.datum_shift[1].shift_um);
        assert!((got - want).norm() < 1e-9, "{got} vs {want}");
        // C = 90 about the C line through (EX0B + EX0C, EY0C) (no tilt on FANUC): -90 about +Z.
        let qc = Vec3::new((12.3456 - 7.05) * 1e-3, 4.44e-3, 0.0);
        let rc = rotation(&Vec3::z(), -90f64.to_radians());
        let want = (qc - rc * qc) * 1e3;
        let got = Vec3::from(o.datum_shift[2].shift_um);
        assert!((got - want).norm() < 1e-9, "{got} vs {want}");
        // Siemens writes the tilts: at C = 90 the point 60 mm above the table moves more.
        let o = run(OffsetFormat::Siemens, &k, &s, None, &opts).unwrap();
        let tilted = Vec3::from(o.datum_shift[2].shift_um);
        assert!((tilted - want).norm() > 1.0, "{tilted} vs {want}");
        // Against the previous set only the difference moves it.
        let prev = set(&k, 0, 0.0, &BC);
        let o = run(OffsetFormat::Siemens, &k, &s, Some(&prev), &opts).unwrap();
        assert!(o.datum_shift.iter().all(|d| d.norm_um < 1e-9));
    }

    /// On the B head the part stays and the tool moves: at B = 90 (direct sense, +90 about +Y)
    /// the tip turns about the head line moved by (EX0B, 0, EZ0B), so the part zero moves by
    /// -(I - R) dq against it.
    #[test]
    fn the_datum_shift_of_a_head_axis_is_the_tools_move() {
        let k = machine("head_b_table_c");
        let s = set(&k, 1, 0.0, &BC);
        let opts = NcOptions {
            poses_deg: vec![vec![90.0, 0.0]],
            ..NcOptions::default()
        };
        let o = run(OffsetFormat::Siemens, &k, &s, None, &opts).unwrap();
        let dq = Vec3::new(12.3456e-3, 0.0, -31.26e-3);
        let r = rotation(&Vec3::y(), 90f64.to_radians());
        let want = -(dq - r * dq) * 1e3;
        let got = Vec3::from(o.datum_shift[0].shift_um);
        assert!((got - want).norm() < 1e-9, "{got} vs {want}");
    }

    /// A machine of `deploy/linuxcnc/machines` (the families LinuxCNC's trt kinematics take).
    fn deployed(name: &str) -> Kinematics {
        let path = format!(
            "{}/../../deploy/linuxcnc/machines/{name}.toml",
            env!("CARGO_MANIFEST_DIR")
        );
        Kinematics::load(&path).unwrap()
    }

    /// A fixed-seed sequence in [-1, 1).
    struct Draws(u64);

    impl Draws {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        }
    }

    /// LinuxCNC's trt inverse kinematics written from its equations (`trtfuncs.c`): the table
    /// point `pos` at the tilt (B on xyzbc, A on xyzac) and C angles (deg) goes to the joints
    /// `rp + D + R_T(tilt) (Rz(c) (pos - rp) - D)`, `rp` the rotation point, `D` (x-offset, 0,
    /// z-offset + tool-offset) on xyzbc, (0, y-offset, z-offset + tool-offset) on xyzac.
    fn trt_inverse(
        bc: bool,
        pin: &dyn Fn(&str) -> f64,
        tool_offset: f64,
        pos: Vec3,
        tilt_deg: f64,
        c_deg: f64,
    ) -> Vec3 {
        use driftwatch_core::geometry::Mat3;
        let rp = Vec3::new(pin("x-rot-point"), pin("y-rot-point"), pin("z-rot-point"));
        let (st, ct) = tilt_deg.to_radians().sin_cos();
        let (sc, cc) = c_deg.to_radians().sin_cos();
        let rz = Mat3::new(cc, -sc, 0.0, sc, cc, 0.0, 0.0, 0.0, 1.0);
        let (d, rt) = if bc {
            (
                Vec3::new(pin("x-offset"), 0.0, pin("z-offset") + tool_offset),
                Mat3::new(ct, 0.0, st, 0.0, 1.0, 0.0, -st, 0.0, ct),
            )
        } else {
            (
                Vec3::new(0.0, pin("y-offset"), pin("z-offset") + tool_offset),
                Mat3::new(1.0, 0.0, 0.0, 0.0, ct, -st, 0.0, st, ct),
            )
        };
        rp + d + rt * (rz * (pos - rp) - d)
    }

    /// The pins LinuxCNC's trt kinematics are given make its inverse kinematics driftwatch's
    /// table-to-machine transform with the set's errors, on both families, for random holdable
    /// errors (no tilt), commissioned values that are not zero (the tilting line off the C line
    /// by a commissioned offset, a tool offset) and random poses and table points: to 1e-9 mm.
    /// LinuxCNC's frame is driftwatch's moved by the nominal B/C (A/C) point: the rotation
    /// point (x, y), and z-rot-point + z-offset + tool-offset.
    #[test]
    fn linuxcnc_pins_make_its_trt_kinematics_the_kinematics_with_the_errors() {
        let mut draw = Draws(20261129);
        for (name, bc) in [("xyzbc-trt", true), ("xyzac-trt", false)] {
            let kins = if bc {
                "xyzbc-trt-kins"
            } else {
                "xyzac-trt-kins"
            };
            let (tilt_offset, pos_errors) = if bc {
                ("x-offset", ["EX0B", "EZ0B", "EY0C", "EX0C"])
            } else {
                ("y-offset", ["EY0A", "EZ0A", "EX0C", "EY0C"])
            };
            let written = ["x-rot-point", "y-rot-point", tilt_offset, "z-offset"];
            // Commissioned: rotation point (12.5, -7.25, 30), the tilting line 0.8 mm off the
            // C line across it and 45 mm under the rotation point, a 120 mm tool.
            let commissioned = BTreeMap::from([
                ("x-rot-point", 12.5),
                ("y-rot-point", -7.25),
                ("z-rot-point", 30.0),
                (tilt_offset, 0.8),
                ("z-offset", -45.0),
            ]);
            let tool = 120.0;
            let mut k = deployed(name);
            // driftwatch's nominal lines as commissioned: the tilting line 0.8 mm off C.
            k.rotary[0].q0 = if bc {
                Vec3::new(0.8, 0.0, 0.0)
            } else {
                Vec3::new(0.0, 0.8, 0.0)
            };
            let origin = Vec3::new(12.5, -7.25, 30.0 - 45.0 + tool);
            let opts = NcOptions {
                linuxcnc_nominal_mm: written
                    .iter()
                    .map(|p| (p.to_string(), commissioned[p]))
                    .collect(),
                ..NcOptions::default()
            };
            for version in 1..=4 {
                let mut values: Vec<(&str, f64)> = pos_errors
                    .iter()
                    .map(|n| (*n, 150.0 * draw.next()))
                    .collect();
                values.extend([("EA0C", 0.0), ("EB0C", 0.0)]);
                let s = set(&k, version, 0.0, &values);
                let o = run(OffsetFormat::Linuxcnc, &k, &s, None, &opts).unwrap();
                assert_eq!(o.kinematic_type, format!("KINEMATICS = {kins}"));
                let full: Vec<String> = written.iter().map(|p| format!("{kins}.{p}")).collect();
                assert_eq!(names(&o), full);
                for v in &o.variables {
                    assert_eq!(v.unit, "mm");
                    assert!(v.rounding.abs() <= 5e-7, "{v:?}");
                    assert_eq!(v.text, format!("{:.6}", v.value));
                }
                // The exact pins (written value less its rounding); the others as commissioned.
                let exact = |p: &str| {
                    o.variables
                        .iter()
                        .find(|v| v.name == format!("{kins}.{p}"))
                        .map_or(commissioned.get(p).copied().unwrap_or(0.0), |v| {
                            v.value - v.rounding
                        })
                };
                // The mapping in closed form (um -> mm).
                let e = |n: &str| s.errors[&ErrorName::parse(n).unwrap()] * 1e-3;
                let closed = if bc {
                    [
                        12.5 + e("EX0B") + e("EX0C"),
                        -7.25 + e("EY0C"),
                        0.8 - e("EX0C"),
                        -45.0 + e("EZ0B"),
                    ]
                } else {
                    [
                        12.5 + e("EX0C"),
                        -7.25 + e("EY0A") + e("EY0C"),
                        0.8 - e("EY0C"),
                        -45.0 + e("EZ0A"),
                    ]
                };
                for (p, want) in written.iter().zip(closed) {
                    assert!(
                        (exact(p) - want).abs() < 1e-12,
                        "{p}: {} vs {want}",
                        exact(p)
                    );
                }
                let state = state_of(&k, &s.errors, |_| true, true);
                let commissioned_pin = |p: &str| commissioned.get(p).copied().unwrap_or(0.0);
                let mut worst_uncompensated: f64 = 0.0;
                for _ in 0..12 {
                    let tilt = 90.0 * draw.next();
                    let c = 180.0 * draw.next();
                    let p = Vec3::new(draw.next(), draw.next(), draw.next()) * 300.0;
                    let got = k.pose_transform(&state, &[tilt, c]).point(&p);
                    let want = trt_inverse(bc, &exact, tool, p + origin, tilt, c) - origin;
                    assert!(
                        (got - want).norm() < 1e-9,
                        "{name} at {tilt}, {c}: {got} vs {want}"
                    );
                    let before =
                        trt_inverse(bc, &commissioned_pin, tool, p + origin, tilt, c) - origin;
                    worst_uncompensated = worst_uncompensated.max((got - before).norm());
                }
                // Not trivially equal: the commissioned pins alone miss the errors.
                assert!(worst_uncompensated > 1e-3, "{worst_uncompensated}");
                assert!(o.not_written.iter().any(|n| n.starts_with("EA0C")));
                // With tilts: the same pins, the tilts listed as not written and said why.
                let mut tilted = values.clone();
                tilted[4].1 = 35.0;
                tilted[5].1 = -20.0;
                let st = set(&k, version, 0.0, &tilted);
                let ot = run(OffsetFormat::Linuxcnc, &k, &st, None, &opts).unwrap();
                assert_eq!(ot.variables, o.variables);
                assert_eq!(
                    ot.not_written,
                    ["EA0C = 35.000 urad", "EB0C = -20.000 urad"]
                );
                assert!(ot.notes.iter().any(|n| n.contains("no pin for a tilt")));
            }
        }
    }

    /// The halcmd script: whole-line `#` comments (the header, then each pin's step on the
    /// line before it) and one `setp PIN VALUE` per variable, nothing else.
    #[test]
    fn the_linuxcnc_program_is_a_halcmd_script_of_setp_lines() {
        let k = deployed("xyzbc-trt");
        let prev = set(&k, 3, 0.0, &BC);
        let mut moved = BC;
        moved[1].1 += 10.0; // EZ0B
        moved[3].1 -= 5.0; // EX0C
        let next = set(&k, 4, 1.0, &moved);
        let opts = NcOptions {
            linuxcnc_nominal_mm: [
                ("x-rot-point", 0.0),
                ("y-rot-point", 0.0),
                ("x-offset", 0.0),
                ("z-offset", -50.0),
                ("z-rot-point", 0.0),
            ]
            .iter()
            .map(|(p, v)| (p.to_string(), *v))
            .collect(),
            ..NcOptions::default()
        };
        let o = run(OffsetFormat::Linuxcnc, &k, &next, Some(&prev), &opts).unwrap();
        let step = |n: &str| {
            o.variables
                .iter()
                .find(|v| v.name == format!("xyzbc-trt-kins.{n}"))
                .unwrap()
                .step
        };
        assert_eq!(step("z-offset"), Some(0.01));
        assert_eq!(step("x-offset"), Some(0.005));
        assert_eq!(step("x-rot-point"), Some(-0.005));
        assert_eq!(step("y-rot-point"), Some(0.0));
        assert!((value(&o, "xyzbc-trt-kins.z-offset") - -50.02126).abs() < 1e-9);
        assert!(
            o.notes.iter().any(|n| n.contains("(z-rot-point)")),
            "a commissioned value of a pin not written is said to be ignored: {:?}",
            o.notes
        );
        let p = o.program.unwrap();
        let lines: Vec<&str> = p.lines().collect();
        assert!(
            lines[0].starts_with("# driftwatch offsets: xyzbc-trt set 4"),
            "{p}"
        );
        assert!(
            p.contains("\n# kinematics: KINEMATICS = xyzbc-trt-kins\n"),
            "{p}"
        );
        let mut setp = 0;
        for (i, l) in lines.iter().enumerate() {
            if l.starts_with('#') {
                continue;
            }
            let words: Vec<&str> = l.split(' ').collect();
            assert_eq!(words.len(), 3, "{l}");
            assert_eq!(words[0], "setp", "{l}");
            let v = &o.variables[setp];
            assert_eq!((words[1], words[2]), (v.name.as_str(), v.text.as_str()));
            assert_eq!(words[2].parse::<f64>().unwrap(), v.value);
            let short = v.name.split_once('.').unwrap().1;
            assert!(
                lines[i - 1].starts_with(&format!("# {short}, step ")),
                "{p}"
            );
            setp += 1;
        }
        assert_eq!(setp, 4);
        assert!(
            p.contains("\nsetp xyzbc-trt-kins.z-offset -50.021260\n"),
            "{p}"
        );
    }

    /// The chains LinuxCNC's trt kinematics cannot take are refused, each saying why: the ISO
    /// 841 table sense of the shipped families, a head axis.
    #[test]
    fn linuxcnc_refuses_the_table_sense_and_other_chains() {
        let opts = NcOptions::default();
        let ac = [
            ("EY0A", 1.0),
            ("EZ0A", 1.0),
            ("EX0C", 1.0),
            ("EY0C", 1.0),
            ("EA0C", 1.0),
            ("EB0C", 1.0),
        ];
        for (name, errors) in [("table_bc", &BC), ("trunnion_ac", &ac)] {
            let k = machine(name);
            let s = set(&k, 1, 0.0, errors);
            let e = run(OffsetFormat::Linuxcnc, &k, &s, None, &opts).unwrap_err();
            let OffsetsError::Unsupported { machine, message } = &e else {
                panic!("{e}");
            };
            assert_eq!(machine, name);
            assert!(
                message.contains("ISO 841 table sense")
                    && message.contains("turn the table positively for a positive command")
                    && message.contains("sense = \"direct\"")
                    && message.contains("deploy/linuxcnc/machines"),
                "{message}"
            );
        }
        let k = machine("head_b_table_c");
        let s = set(&k, 1, 0.0, &BC);
        let e = run(OffsetFormat::Linuxcnc, &k, &s, None, &opts).unwrap_err();
        assert!(
            e.to_string().contains("two table axes and no head axis"),
            "{e}"
        );
    }

    #[test]
    fn linuxcnc_without_the_commissioned_values_or_with_an_unknown_pin_is_refused() {
        let k = deployed("xyzac-trt");
        let s = set(
            &k,
            1,
            0.0,
            &[
                ("EY0A", 3.0),
                ("EZ0A", -4.0),
                ("EX0C", 1.0),
                ("EY0C", 2.0),
                ("EA0C", 5.0),
                ("EB0C", 6.0),
            ],
        );
        let opts = |pins: &[&str]| NcOptions {
            linuxcnc_nominal_mm: pins.iter().map(|p| (p.to_string(), 0.0)).collect(),
            ..NcOptions::default()
        };
        let e = run(
            OffsetFormat::Linuxcnc,
            &k,
            &s,
            None,
            &opts(&["y-rot-point"]),
        )
        .unwrap_err();
        assert_eq!(
            e,
            OffsetsError::MissingPinNominal {
                kins: "xyzac-trt-kins".into(),
                pins: vec!["x-rot-point".into(), "y-offset".into(), "z-offset".into()]
            }
        );
        assert!(
            e.to_string().contains("x-rot-point, y-offset, z-offset"),
            "{e}"
        );
        let all = ["x-rot-point", "y-rot-point", "y-offset", "z-offset"];
        let o = run(OffsetFormat::Linuxcnc, &k, &s, None, &opts(&all)).unwrap();
        assert_eq!(value(&o, "xyzac-trt-kins.y-rot-point"), 0.005); // EY0A + EY0C
        assert_eq!(value(&o, "xyzac-trt-kins.y-offset"), -0.002); // -EY0C
        assert_eq!(value(&o, "xyzac-trt-kins.z-offset"), -0.004); // EZ0A
        let e = run(
            OffsetFormat::Linuxcnc,
            &k,
            &s,
            None,
            &opts(&[
                "x-rot-point",
                "y-rot-point",
                "y-offset",
                "z-offset",
                "tool-offset",
            ]),
        )
        .unwrap_err();
        assert!(
            matches!(&e, OffsetsError::BadOption(m) if m.contains("tool-offset")),
            "{e}"
        );
    }

    /// A step beyond the validation's limit is refused in the LinuxCNC form as in the others.
    #[test]
    fn linuxcnc_refuses_a_step_beyond_the_limit() {
        let k = deployed("xyzbc-trt");
        let prev = set(&k, 3, 0.0, &BC);
        let mut moved = BC;
        moved[1].1 += 60.0; // EZ0B: 60 um in 1 min, over 54
        let far = set(&k, 4, 1.0, &moved);
        let opts = NcOptions {
            linuxcnc_nominal_mm: ["x-rot-point", "y-rot-point", "x-offset", "z-offset"]
                .iter()
                .map(|p| (p.to_string(), 0.0))
                .collect(),
            ..NcOptions::default()
        };
        let e = run(OffsetFormat::Linuxcnc, &k, &far, Some(&prev), &opts).unwrap_err();
        let OffsetsError::StepBeyondLimit { steps, .. } = e else {
            panic!("{e}");
        };
        assert_eq!(steps.len(), 1);
        assert!(steps[0].starts_with("EZ0B"), "{steps:?}");
    }

    #[test]
    fn formats_parse_and_an_unknown_one_is_named() {
        for f in OffsetFormat::ALL {
            assert_eq!(OffsetFormat::parse(f.name()), Ok(f));
        }
        let e = OffsetFormat::parse("mazak").unwrap_err().to_string();
        assert!(e.contains("mazak") && e.contains("heidenhain"), "{e}");
    }
}
