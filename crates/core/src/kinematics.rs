//! Machine kinematics built from data: chains of rotary axes on the work side (tables,
//! swivels) and the tool side (swivel heads), each turning about its actual average line
//! (ISO 230-7 location errors), a linear tool side with scale and squareness errors, the laser
//! tool setter's beam and the tool.
//!
//! Conventions (pinned by tests; see the contract `kinematics-conventions.md`):
//! `p_machine = T_1(a_1) * T_2(a_2) * ... * p_table` over the table axes, outermost first, and
//! `tip = c - H_nom(a)(0) + H(a)(s)` over the head axes (outermost, nearest the ram, first),
//! with `T_i(a) = Tr(q_i) * Rot(u_i, sense * (a + zero_i + eps_i)) * Tr(-q_i)`; `sense = -1`
//! for table axes (ISO 841), `+1` for head axes. Every line is given as seen with all axes at
//! zero (head lines in the head frame: relative to the tool tip at the zero pose), so at the
//! zero pose the table frame is the machine frame and the tip is where the NC commands it,
//! whatever the position and orientation errors.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::error_name::{ErrorKind, ErrorName};
use crate::geometry::{Affine, Vec3, deg_to_rad, rotation};
use crate::linear_axes::LinearGeometry;

/// Most rotary axes a chain may have (keeps states on the stack).
pub const MAX_ROTARY: usize = 3;

/// The sense each rotary axis last moved in (-1, +1; 0 before its first move), followed
/// along a sequence of commanded poses: what backlash depends on.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RotarySense {
    last: Option<[f64; MAX_ROTARY]>,
    pub sense: [i8; MAX_ROTARY],
}

impl RotarySense {
    /// Move to `angles` (deg) and return the senses after the move.
    pub fn go_to(&mut self, angles: &[f64; MAX_ROTARY]) -> [i8; MAX_ROTARY] {
        if let Some(prev) = self.last {
            for (s, (a, p)) in self.sense.iter_mut().zip(angles.iter().zip(prev)) {
                if *a != p {
                    *s = if *a > p { 1 } else { -1 };
                }
            }
        }
        self.last = Some(*angles);
        self.sense
    }
}

/// Built-in machine descriptions, by name.
pub const BUILTIN_MACHINES: &[(&str, &str)] = &[
    (
        "table_bc",
        include_str!("../../../config/machines/table_bc.toml"),
    ),
    (
        "head_b_table_c",
        include_str!("../../../config/machines/head_b_table_c.toml"),
    ),
    (
        "table_d45_c",
        include_str!("../../../config/machines/table_d45_c.toml"),
    ),
    (
        "head_d45_table_c",
        include_str!("../../../config/machines/head_d45_table_c.toml"),
    ),
    (
        "trunnion_ac",
        include_str!("../../../config/machines/trunnion_ac.toml"),
    ),
];

#[derive(Debug, Error)]
pub enum MachineError {
    #[error(transparent)]
    Source(#[from] crate::source::SourceError),
    #[error("machine description {origin} is not valid TOML for a machine: {message}")]
    Parse { origin: String, message: String },
    #[error("machine '{machine}': {message}")]
    Invalid { machine: String, message: String },
}

/// Which part of the machine an axis turns: the table (work side; its lines are in the
/// machine frame) or the spindle head (tool side; its lines are in the head frame, relative
/// to the tool tip at the zero pose).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Side {
    #[default]
    Table,
    Head,
}

/// Whether a positive command turns the carried body positively (`direct`, the ISO 841 sense
/// of head axes) or negatively (`table`, the ISO 841 sense of work-side axes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sense {
    Table,
    Direct,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NamedDirection {
    /// The location error's ISO 230-7 name (`EX0B`): refused at parse when it is not one.
    pub name: ErrorName,
    pub direction: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotaryConfig {
    pub name: String,
    /// The table (work side, default) or the spindle head (tool side).
    #[serde(default)]
    pub side: Side,
    /// Nominal direction of the axis with all axes at zero.
    pub axis: [f64; 3],
    /// A point of the nominal axis line, mm: machine frame for a table axis, head frame
    /// (relative to the tool tip at the zero pose) for a head axis.
    #[serde(default)]
    pub point_mm: [f64; 3],
    pub sense: Sense,
    /// The two position errors: the line moves by `value * direction` (um).
    pub position_errors: [NamedDirection; 2],
    /// The two orientation errors: the axis direction is turned about `direction` by `value`
    /// (urad), the first one applied first.
    pub orientation_errors: [NamedDirection; 2],
    /// Name of the zero-angle error (urad), added to the commanded angle.
    pub zero_error: ErrorName,
    /// Position errors are measured from the carrying axis' line (the part of its offset
    /// perpendicular to this axis is inherited), as EX0C is measured from the B axis. The
    /// carrying axis is the one listed before on the same side.
    #[serde(default)]
    pub relative_to_parent: bool,
    /// Field of `/probe/detection` that carries this axis' commanded angle.
    pub message_field: AngleField,
    pub travel_deg: [f64; 2],
    /// Rotary speed for machine-time estimates, deg/min.
    pub speed_deg_min: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum AngleField {
    #[serde(rename = "b_deg")]
    B,
    #[serde(rename = "c_deg")]
    C,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetterConfig {
    /// A point of the beam line in the table frame, mm. For the patent layout `(d, -R, H)`.
    pub beam_point_mm: [f64; 3],
    /// Beam direction in the table frame.
    pub beam_direction: [f64; 3],
    /// One-reading standard uncertainty of the whole chain (setter, skip, runout), um.
    pub sigma_um: f64,
    /// Calibrated skip latency, ms: the latched position lies `feed * latency` further along.
    #[serde(default)]
    pub latency_ms: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolConfig {
    pub id: String,
    /// Calibrated effective radius (envelope of the turning cutter), mm.
    pub radius_mm: f64,
    /// Spindle (tool) axis at the zero pose, machine frame, pointing from the tip into the
    /// spindle.
    #[serde(default = "default_tool_axis")]
    pub axis: [f64; 3],
}

fn default_plan() -> String {
    "patent".into()
}

fn default_tool_axis() -> [f64; 3] {
    [0.0, 0.0, 1.0]
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionConfig {
    /// Linear rapid feed, mm/min.
    pub rapid_mm_min: f64,
    /// Z height (machine frame, mm) the tool retracts to before any rotary move.
    pub safe_z_mm: f64,
    /// Time to unclamp and clamp a rotary axis around a move, s.
    pub clamp_s: f64,
    /// Linear travel limits, mm: [[xmin, xmax], [ymin, ymax], [zmin, zmax]].
    pub travel_mm: [[f64; 2]; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineConfig {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub rotary: Vec<RotaryConfig>,
    pub setter: SetterConfig,
    pub tool: ToolConfig,
    pub motion: MotionConfig,
    /// The plan (built-in name or path) this machine's cycles run unless the service
    /// configuration or the command line names another.
    #[serde(default = "default_plan")]
    pub plan: String,
    /// The location errors a cycle identifies, in report order.
    pub identify: Vec<ErrorName>,
    /// Values held for the location errors that are not identified (um or urad), e.g. from a
    /// fuller calibration. Missing ones are 0.
    #[serde(default)]
    pub held: BTreeMap<ErrorName, f64>,
    /// What the machine can report; the NC door refuses anything outside.
    #[serde(default)]
    pub limits: Limits,
    /// The linear axes' measured geometry (e.g. from a laser step diagonal), used by every
    /// solve on this machine. Absent: the axes are taken as perfect.
    #[serde(default)]
    pub linear: Option<LinearGeometry>,
}

/// What a machine can report: an event outside is refused at the NC door (a gateway's unit
/// error or a broken sensor), so that the thermal model never takes it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// The spindle's rated maximum speed, min^-1 (either sense).
    pub spindle_max_rpm: f64,
    /// The range the machine's temperature sensors can read where it stands, deg C.
    pub celsius: [f64; 2],
}

impl Default for Limits {
    /// Wide enough for any machining centre's spindle and sensors; a machine file should
    /// narrow them to the machine's own.
    fn default() -> Self {
        Limits {
            spindle_max_rpm: 60_000.0,
            celsius: [-20.0, 100.0],
        }
    }
}

/// The longest name (sensor, program, tool, step) an event may carry, characters.
pub const MAX_NAME_CHARS: usize = 64;

/// Where an error lives in the chain: rotary axis index and slot
/// (0, 1 positions; 2, 3 orientations; 4 zero angle).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ErrorId {
    pub axis: usize,
    pub slot: usize,
}

impl ErrorId {
    pub fn is_position(&self) -> bool {
        self.slot < 2
    }
    /// Model units (mm or rad) per interface unit (um or urad).
    pub fn scale(&self) -> f64 {
        if self.is_position() { 1e-3 } else { 1e-6 }
    }
    pub fn unit(&self) -> &'static str {
        if self.is_position() { "um" } else { "urad" }
    }
}

#[derive(Debug, Clone)]
pub struct RotaryAxis {
    pub name: String,
    pub side: Side,
    pub u0: Vec3,
    pub q0: Vec3,
    pub sign: f64,
    pub position_dirs: [Vec3; 2],
    pub orientation_axes: [Vec3; 2],
    /// Names of the five errors by slot; each name's kind is its slot's (checked at load), so
    /// [`ErrorId::unit`] and the name's unit agree.
    pub error_names: [ErrorName; 5],
    pub relative_to_parent: bool,
    pub field: AngleField,
    pub travel_deg: [f64; 2],
    pub speed_deg_min: f64,
}

#[derive(Debug, Clone)]
pub struct Setter {
    pub point: Vec3,
    pub direction: Vec3,
    pub sigma_um: f64,
    pub latency_s: f64,
}

/// Offsets of the axis lines from their nominal points and their actual directions.
pub type AxisLines = ([Vec3; MAX_ROTARY], [Vec3; MAX_ROTARY]);

/// A validated machine description.
#[derive(Debug, Clone)]
pub struct Kinematics {
    pub name: String,
    pub description: String,
    pub rotary: Vec<RotaryAxis>,
    pub setter: Setter,
    pub tool_id: String,
    pub tool_radius: f64,
    pub tool_axis: Vec3,
    pub motion: MotionConfig,
    pub identify: Vec<ErrorId>,
    pub held: Vec<(ErrorId, f64)>,
    /// The linear axes' known geometry (scale, squareness, ISO 230-1 components): part of the
    /// state the NC's model and every solve start from. Zero unless the machine file's
    /// `[linear]` section or a stored geometry version gives it.
    pub linear: LinearErrors,
    /// Where `linear` came from ("machine file", or a stored version's label); `None` when
    /// the axes are taken as perfect. Every cycle result names it.
    pub linear_source: Option<String>,
    pub config: MachineConfig,
}

pub use crate::linear_axes::LinearErrors;

/// Everything a reading depends on, in model units (mm, rad, s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MachineState {
    /// Location errors per axis and slot: mm, mm, rad, rad, rad.
    pub loc: [[f64; 5]; MAX_ROTARY],
    /// Angular positioning error at the current pose (beyond the zero error), rad.
    pub angle_error: [f64; MAX_ROTARY],
    pub linear: LinearErrors,
    /// Tool-tip thermal displacement, mm, in the head frame (the machine frame as the head
    /// is at the zero pose; the machine frame itself when no axis turns the head).
    pub tool_tip: Vec3,
    /// Beam line in the table frame.
    pub beam_point: Vec3,
    pub beam_dir: Vec3,
    /// Effective tool radius, mm.
    pub radius: f64,
    /// Skip latency, s.
    pub latency_s: f64,
}

impl MachineConfig {
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, MachineError> {
        toml::from_str(text).map_err(|e| MachineError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })
    }
}

/// One rotary axis of a machine file, checked: unit directions perpendicular to the axis, a
/// positive speed and an ordered travel, error names of their slot's kind and axis.
fn rotary_axis(r: &RotaryConfig, m: &str) -> Result<RotaryAxis, MachineError> {
    let invalid = |message: String| MachineError::Invalid {
        machine: m.to_string(),
        message,
    };
    let u0 = unit(r.axis, &format!("axis of {}", r.name), m)?;
    let mut position_dirs = [Vec3::zeros(); 2];
    let mut orientation_axes = [Vec3::zeros(); 2];
    for k in 0..2 {
        let d = unit(
            r.position_errors[k].direction,
            &format!("direction of {}", r.position_errors[k].name),
            m,
        )?;
        let o = unit(
            r.orientation_errors[k].direction,
            &format!("direction of {}", r.orientation_errors[k].name),
            m,
        )?;
        if d.dot(&u0).abs() > 1e-9 || o.dot(&u0).abs() > 1e-9 {
            return Err(invalid(format!(
                "the error directions of axis {} must be perpendicular to it",
                r.name
            )));
        }
        position_dirs[k] = d;
        orientation_axes[k] = o;
    }
    if position_dirs[0].dot(&position_dirs[1]).abs() > 1e-9 {
        return Err(invalid(format!(
            "the two position error directions of axis {} must be perpendicular",
            r.name
        )));
    }
    if !crate::units::positive(r.speed_deg_min) || r.travel_deg[0] >= r.travel_deg[1] {
        return Err(invalid(format!(
            "axis {} needs a positive speed and travel_deg [min, max]",
            r.name
        )));
    }
    check_error_slots(r, &invalid)?;
    Ok(RotaryAxis {
        name: r.name.clone(),
        side: r.side,
        u0,
        q0: Vec3::from(r.point_mm),
        sign: match r.sense {
            Sense::Table => -1.0,
            Sense::Direct => 1.0,
        },
        position_dirs,
        orientation_axes,
        error_names: [
            r.position_errors[0].name,
            r.position_errors[1].name,
            r.orientation_errors[0].name,
            r.orientation_errors[1].name,
            r.zero_error,
        ],
        relative_to_parent: r.relative_to_parent,
        field: r.message_field,
        travel_deg: r.travel_deg,
        speed_deg_min: r.speed_deg_min,
    })
}

/// Each error name of an axis is of its slot's kind (position or orientation) and names the
/// axis it belongs to.
fn check_error_slots(
    r: &RotaryConfig,
    invalid: &dyn Fn(String) -> MachineError,
) -> Result<(), MachineError> {
    let slots = [
        (
            r.position_errors[0].name,
            ErrorKind::Position,
            "position_errors",
        ),
        (
            r.position_errors[1].name,
            ErrorKind::Position,
            "position_errors",
        ),
        (
            r.orientation_errors[0].name,
            ErrorKind::Orientation,
            "orientation_errors",
        ),
        (
            r.orientation_errors[1].name,
            ErrorKind::Orientation,
            "orientation_errors",
        ),
        (r.zero_error, ErrorKind::Orientation, "zero_error"),
    ];
    for (name, kind, key) in slots {
        if name.kind() != kind {
            return Err(invalid(format!(
                "{key} of axis {} names {name}, which is {} error ({}); it must be {} \
                 error ({})",
                r.name,
                kind_article(name.kind()),
                name.unit(),
                kind_article(kind),
                kind.unit()
            )));
        }
        if r.name.len() != 1 || !r.name.starts_with(name.axis()) {
            return Err(invalid(format!(
                "{key} of axis {} names {name}, an error of axis {}",
                r.name,
                name.axis()
            )));
        }
    }
    Ok(())
}

fn kind_article(kind: ErrorKind) -> &'static str {
    match kind {
        ErrorKind::Position => "a position",
        ErrorKind::Orientation => "an orientation",
    }
}

fn unit(v: [f64; 3], what: &str, machine: &str) -> Result<Vec3, MachineError> {
    let v = Vec3::from(v);
    let n = v.norm();
    if !n.is_finite() || n < 1e-9 {
        return Err(MachineError::Invalid {
            machine: machine.to_string(),
            message: format!("{what} must be a non-zero finite vector"),
        });
    }
    Ok(v / n)
}

impl Kinematics {
    /// A built-in machine by name, or a machine TOML file by path.
    pub fn load(name_or_path: &str) -> Result<Self, MachineError> {
        let text = crate::source::builtin_or_file("machine", name_or_path, BUILTIN_MACHINES)?;
        Self::from_config(MachineConfig::from_toml(&text, name_or_path)?)
    }

    /// A built-in machine by name (never a file).
    pub fn builtin(name: &str) -> Result<Self, MachineError> {
        match BUILTIN_MACHINES.iter().find(|(n, _)| *n == name) {
            Some((_, text)) => Self::from_config(MachineConfig::from_toml(text, name)?),
            None => Self::load(&format!("<no built-in machine {name}>")),
        }
    }

    pub fn from_config(cfg: MachineConfig) -> Result<Self, MachineError> {
        let m = cfg.name.clone();
        let invalid = |message: String| MachineError::Invalid {
            machine: m.clone(),
            message,
        };
        if cfg.rotary.is_empty() || cfg.rotary.len() > MAX_ROTARY {
            return Err(invalid(format!(
                "needs 1 to {MAX_ROTARY} rotary axes, has {}",
                cfg.rotary.len()
            )));
        }
        let rotary = cfg
            .rotary
            .iter()
            .map(|r| rotary_axis(r, &m))
            .collect::<Result<Vec<_>, _>>()?;
        let mut names: Vec<ErrorName> = rotary.iter().flat_map(|a| a.error_names).collect();
        names.sort_unstable();
        if names.windows(2).any(|w| w[0] == w[1]) {
            return Err(invalid("location error names must be unique".into()));
        }
        let s = &cfg.setter;
        if !crate::units::positive(s.sigma_um) || !crate::units::non_negative(s.latency_ms) {
            return Err(invalid(
                "setter.sigma_um must be > 0 and latency_ms >= 0".into(),
            ));
        }
        let setter = Setter {
            point: Vec3::from(s.beam_point_mm),
            direction: unit(s.beam_direction, "setter.beam_direction", &m)?,
            sigma_um: s.sigma_um,
            latency_s: s.latency_ms * 1e-3,
        };
        let l = &cfg.limits;
        let (lo, hi) = crate::units::PLAUSIBLE_CELSIUS;
        if !(crate::units::positive(l.spindle_max_rpm)
            && l.spindle_max_rpm <= crate::units::MAX_PLAUSIBLE_RPM
            && lo <= l.celsius[0]
            && l.celsius[0] < l.celsius[1]
            && l.celsius[1] <= hi)
        {
            return Err(invalid(format!(
                "limits: spindle_max_rpm must lie in (0, {}] and celsius = [min, max] within [{lo}, {hi}]",
                crate::units::MAX_PLAUSIBLE_RPM
            )));
        }
        if !crate::units::positive(cfg.tool.radius_mm) {
            return Err(invalid("tool.radius_mm must be > 0".into()));
        }
        let mut k = Kinematics {
            name: cfg.name.clone(),
            description: cfg.description.clone(),
            rotary,
            setter,
            tool_id: cfg.tool.id.clone(),
            tool_radius: cfg.tool.radius_mm,
            tool_axis: unit(cfg.tool.axis, "tool.axis", &m)?,
            motion: cfg.motion.clone(),
            identify: Vec::new(),
            held: Vec::new(),
            linear: match &cfg.linear {
                Some(g) => g.errors().map_err(|e| invalid(format!("[linear]: {e}")))?,
                None => LinearErrors::default(),
            },
            linear_source: cfg
                .linear
                .as_ref()
                .filter(|g| !g.is_zero())
                .map(|_| "machine file".to_string()),
            config: cfg.clone(),
        };
        for name in &cfg.identify {
            let id = k
                .error_id(name.as_str())
                .ok_or_else(|| invalid(format!("identify names unknown error '{name}'")))?;
            if k.identify.contains(&id) {
                return Err(invalid(format!("identify names '{name}' twice")));
            }
            k.identify.push(id);
        }
        for (name, v) in &cfg.held {
            let id = k
                .error_id(name.as_str())
                .ok_or_else(|| invalid(format!("held names unknown error '{name}'")))?;
            if k.identify.contains(&id) {
                return Err(invalid(format!("'{name}' is both identified and held")));
            }
            if !v.is_finite() {
                return Err(invalid(format!("held value of '{name}' is not finite")));
            }
            k.held.push((id, *v));
        }
        Ok(k)
    }

    /// This machine with another known linear-axis geometry (a stored geometry version):
    /// every solve from then on starts from it.
    /// `source` names it in every result ("version 3: step diagonal ...").
    pub fn with_geometry(mut self, g: &LinearGeometry, source: &str) -> Result<Self, MachineError> {
        self.linear = g.errors().map_err(|e| MachineError::Invalid {
            machine: self.name.clone(),
            message: format!("linear geometry: {e}"),
        })?;
        self.config.linear = (!g.is_zero()).then(|| g.clone());
        self.linear_source = (!g.is_zero()).then(|| source.to_string());
        Ok(self)
    }

    pub fn error_id(&self, name: &str) -> Option<ErrorId> {
        self.rotary.iter().enumerate().find_map(|(axis, a)| {
            a.error_names
                .iter()
                .position(|n| *n == name)
                .map(|slot| ErrorId { axis, slot })
        })
    }

    pub fn error_name(&self, id: ErrorId) -> &str {
        self.rotary[id.axis].error_names[id.slot].as_str()
    }

    /// Names of the identified errors, in report order.
    pub fn identify_names(&self) -> Vec<String> {
        self.identify
            .iter()
            .map(|id| self.error_name(*id).to_string())
            .collect()
    }

    /// The state the NC assumes: held errors, nominal setter, calibrated radius and latency.
    pub fn nominal_state(&self) -> MachineState {
        let mut s = MachineState {
            loc: [[0.0; 5]; MAX_ROTARY],
            angle_error: [0.0; MAX_ROTARY],
            linear: self.linear,
            tool_tip: Vec3::zeros(),
            beam_point: self.setter.point,
            beam_dir: self.setter.direction,
            radius: self.tool_radius,
            latency_s: self.setter.latency_s,
        };
        for (id, v) in &self.held {
            s.loc[id.axis][id.slot] = v * id.scale();
        }
        s
    }

    /// Commanded angles (deg) of the chain's axes from a detection's `b_deg` and `c_deg`.
    pub fn angles_from_fields(&self, b_deg: f64, c_deg: f64) -> [f64; MAX_ROTARY] {
        let mut a = [0.0; MAX_ROTARY];
        for (i, ax) in self.rotary.iter().enumerate() {
            a[i] = match ax.field {
                AngleField::B => b_deg,
                AngleField::C => c_deg,
            };
        }
        a
    }

    /// The message fields (`b_deg`, `c_deg`) of commanded angles: the inverse of
    /// [`Kinematics::angles_from_fields`] (a field no axis uses stays 0).
    pub fn fields_from_angles(&self, angles_deg: &[f64; MAX_ROTARY]) -> (f64, f64) {
        let mut fields = (0.0, 0.0);
        for (i, ax) in self.rotary.iter().enumerate() {
            match ax.field {
                AngleField::B => fields.0 = angles_deg[i],
                AngleField::C => fields.1 = angles_deg[i],
            }
        }
        fields
    }

    /// The work-side transform table -> machine at the commanded angles (deg).
    pub fn pose_transform(&self, state: &MachineState, angles_deg: &[f64]) -> Affine {
        self.pose_transform_on(&self.lines(state), state, angles_deg)
    }

    /// As [`Kinematics::pose_transform`], with the axis lines of `state` already computed
    /// (many poses of one state share them).
    pub fn pose_transform_on(
        &self,
        lines: &AxisLines,
        state: &MachineState,
        angles_deg: &[f64],
    ) -> Affine {
        self.chain(Side::Table, lines, state, angles_deg)
    }

    /// The transform of one side's axes at the commanded angles, outermost first.
    fn chain(
        &self,
        side: Side,
        (offsets, dirs): &AxisLines,
        state: &MachineState,
        angles_deg: &[f64],
    ) -> Affine {
        let mut total = Affine::identity();
        for (i, ax) in self.rotary.iter().enumerate() {
            if ax.side != side {
                continue;
            }
            let angle =
                ax.sign * (deg_to_rad(angles_deg[i]) + state.loc[i][4] + state.angle_error[i]);
            let t = Affine::about_line(&(ax.q0 + offsets[i]), &dirs[i], angle);
            total = total.then_inner(&t);
        }
        total
    }

    /// The head-side transform (head frame -> machine frame, before the linear axes) at the
    /// commanded angles; the identity on machines whose head does not turn.
    pub fn head_transform_on(
        &self,
        lines: &AxisLines,
        state: &MachineState,
        angles_deg: &[f64],
    ) -> Affine {
        self.chain(Side::Head, lines, state, angles_deg)
    }

    /// The axis that turns the table under the work (the innermost table axis, C on every
    /// built-in machine), if any: the one axis a pose may turn and stay "untilted".
    pub fn table_axis(&self) -> Option<usize> {
        self.rotary.iter().rposition(|a| a.side == Side::Table)
    }

    /// Whether a pose turns any axis but the table axis (the "tilted" poses of the patent,
    /// where the position of the tilting axis shows).
    pub fn is_tilted(&self, angles_deg: &[f64]) -> bool {
        let table = self.table_axis();
        (0..self.rotary.len())
            .filter(|i| Some(*i) != table)
            .any(|i| crate::geometry::wrap_deg(angles_deg[i]).abs() > 1e-9)
    }

    /// A pose as a label: each axis' name and angle, e.g. `B-90C-270`.
    pub fn pose_label(&self, angles_deg: &[f64]) -> String {
        self.rotary
            .iter()
            .zip(angles_deg)
            .map(|(ax, a)| {
                if a.fract() == 0.0 {
                    format!("{}{}", ax.name, *a as i64)
                } else {
                    format!("{}{a}", ax.name)
                }
            })
            .collect()
    }

    /// The axes that tilt (every axis but the table axis), by name.
    pub fn tilting_axes(&self) -> Vec<&str> {
        let table = self.table_axis();
        self.rotary
            .iter()
            .enumerate()
            .filter(|(i, _)| Some(*i) != table)
            .map(|(_, a)| a.name.as_str())
            .collect()
    }

    /// Whether any axis turns the spindle head.
    pub fn has_head_axes(&self) -> bool {
        self.rotary.iter().any(|a| a.side == Side::Head)
    }

    /// Where the tool is at a pose, relative to the commanded position (see [`ToolPose`]).
    pub fn tool_pose_on(
        &self,
        lines: &AxisLines,
        state: &MachineState,
        angles_deg: &[f64],
    ) -> ToolPose {
        if !self.has_head_axes() {
            return ToolPose {
                nominal: Vec3::zeros(),
                actual: state.tool_tip,
                axis: self.tool_axis,
            };
        }
        // The NC's model of the head: nominal lines, no zero-angle or positioning errors.
        let mut nominal = Affine::identity();
        for (i, ax) in self.rotary.iter().enumerate() {
            if ax.side == Side::Head {
                let angle = ax.sign * deg_to_rad(angles_deg[i]);
                nominal = nominal.then_inner(&Affine::about_line(&ax.q0, &ax.u0, angle));
            }
        }
        let actual = self.chain(Side::Head, lines, state, angles_deg);
        ToolPose {
            nominal: nominal.point(&Vec3::zeros()),
            actual: actual.point(&state.tool_tip),
            axis: actual.vector(&self.tool_axis),
        }
    }

    /// The beam and the tool at a pose, with the axis lines of `state` already computed.
    pub fn pose_geometry_on(
        &self,
        lines: &AxisLines,
        state: &MachineState,
        angles_deg: &[f64],
    ) -> PoseGeometry {
        let t = self.pose_transform_on(lines, state, angles_deg);
        PoseGeometry {
            beam_point: t.point(&state.beam_point),
            beam_dir: t.vector(&state.beam_dir),
            tool: self.tool_pose_on(lines, state, angles_deg),
        }
    }

    /// The beam and the tool at a pose.
    pub fn pose_geometry(&self, state: &MachineState, angles_deg: &[f64]) -> PoseGeometry {
        self.pose_geometry_on(&self.lines(state), state, angles_deg)
    }

    /// Absolute offsets of each axis line from its nominal point and the actual directions.
    /// A `relative_to_parent` axis inherits the offset of the axis listed before it on the
    /// same side.
    pub fn lines(&self, state: &MachineState) -> AxisLines {
        let mut offsets = [Vec3::zeros(); MAX_ROTARY];
        let mut dirs = [Vec3::zeros(); MAX_ROTARY];
        let mut parent = [Vec3::zeros(); 2];
        for (i, ax) in self.rotary.iter().enumerate() {
            let e = &state.loc[i];
            let side = ax.side as usize;
            let mut o = ax.position_dirs[0] * e[0] + ax.position_dirs[1] * e[1];
            if ax.relative_to_parent {
                o += parent[side] - ax.u0 * parent[side].dot(&ax.u0);
            }
            offsets[i] = o;
            dirs[i] = rotation(&ax.orientation_axes[1], e[3])
                * rotation(&ax.orientation_axes[0], e[2])
                * ax.u0;
            parent[side] = o;
        }
        (offsets, dirs)
    }

    /// The state a tool-setter cycle measures (the contract's apparent errors): the tool-tip
    /// displacement `s` moved into the axis lines (table lines and setter shifted by `-s` in
    /// the machine frame, head lines by `-s` in the head frame), with the tool tip at zero.
    /// Every reading is exactly the same as with `state`: a head chain `H` with its lines
    /// shifted by `-s` is `Tr(-s) H Tr(s)`, so the tip `H(s)` becomes `H'(0) + s`, and a tip
    /// moved by a constant `s` reads as table lines and setter moved by `-s`.
    pub fn apparent_state(&self, state: &MachineState) -> MachineState {
        let s = state.tool_tip;
        let (offsets, dirs) = self.lines(state);
        let mut out = *state;
        let mut parent = [Vec3::zeros(); 2];
        for (i, ax) in self.rotary.iter().enumerate() {
            let side = ax.side as usize;
            // Shift the line by -s, then name it by its point in the plane normal to u0.
            let q = offsets[i] - s;
            let lambda = q.dot(&ax.u0) / dirs[i].dot(&ax.u0);
            let o = q - dirs[i] * lambda;
            let mut own = o;
            if ax.relative_to_parent {
                own -= parent[side] - ax.u0 * parent[side].dot(&ax.u0);
            }
            out.loc[i][0] = own.dot(&ax.position_dirs[0]);
            out.loc[i][1] = own.dot(&ax.position_dirs[1]);
            parent[side] = o;
        }
        out.beam_point = state.beam_point - s;
        out.tool_tip = Vec3::zeros();
        out
    }

    /// The beam line in the machine frame at a pose: (point, unit direction).
    pub fn beam_in_machine(&self, state: &MachineState, angles_deg: &[f64]) -> (Vec3, Vec3) {
        let t = self.pose_transform(state, angles_deg);
        (t.point(&state.beam_point), t.vector(&state.beam_dir))
    }
}

/// Where the tool is at a pose, relative to the commanded position `c`: the NC places the
/// linear axes at `c - nominal`, so the actual tip is at `A (c - nominal) + actual`, its axis
/// along `axis`. Without head axes `nominal` is zero, `actual` the tool-tip displacement and
/// `axis` the configured spindle axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolPose {
    /// Tip displacement by the head chain as the NC's model has it (nominal lines), mm.
    pub nominal: Vec3,
    /// Actual tip displacement by the head chain, tool-tip displacement included, mm.
    pub actual: Vec3,
    /// Actual tool axis, from the tip into the spindle (unit).
    pub axis: Vec3,
}

/// The beam line (machine frame) and the tool at one pose: all a reading depends on besides
/// the approach.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseGeometry {
    pub beam_point: Vec3,
    pub beam_dir: Vec3,
    pub tool: ToolPose,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Mat3;

    fn table_bc() -> Kinematics {
        Kinematics::builtin("table_bc").unwrap()
    }

    #[test]
    fn c_minus_90_turns_the_table_counter_clockwise_seen_from_plus_z() {
        let k = table_bc();
        let s = k.nominal_state();
        let t = k.pose_transform(&s, &[0.0, -90.0]);
        // A table point on +X goes to +Y: counter-clockwise seen from +Z.
        let p = t.point(&Vec3::new(100.0, 0.0, 0.0));
        assert!((p - Vec3::new(0.0, 100.0, 0.0)).norm() < 1e-12, "{p}");
    }

    #[test]
    fn b_minus_90_makes_the_table_top_face_plus_x() {
        let k = table_bc();
        let s = k.nominal_state();
        let t = k.pose_transform(&s, &[-90.0, 0.0]);
        let normal = t.vector(&Vec3::z());
        assert!((normal - Vec3::x()).norm() < 1e-12, "{normal}");
    }

    #[test]
    fn c_minus_270_is_the_pose_of_c_plus_90() {
        let k = table_bc();
        let mut s = k.nominal_state();
        s.loc[1][2] = 50e-6;
        let a = k.pose_transform(&s, &[0.0, -270.0]);
        let b = k.pose_transform(&s, &[0.0, 90.0]);
        assert!((a.r - b.r).norm() < 1e-15 && (a.t - b.t).norm() < 1e-12);
    }

    #[test]
    fn zero_pose_is_identity_whatever_the_location_errors() {
        let k = table_bc();
        let mut s = k.nominal_state();
        for (i, v) in [0.1, -0.05, 1e-4, -2e-4].iter().enumerate() {
            s.loc[0][i] = *v;
            s.loc[1][i] = -*v;
        }
        let t = k.pose_transform(&s, &[0.0, 0.0]);
        assert!((t.r - Mat3::identity()).norm() < 1e-15 && t.t.norm() < 1e-15);
    }

    #[test]
    fn lines_pass_through_the_contract_points() {
        // B line through (EX0B, 0, EZ0B); C line (at b = 0) through (EX0B + EX0C, EY0C, 0).
        let k = table_bc();
        let mut s = k.nominal_state();
        let (ex0b, ez0b, ex0c, ey0c) = (0.030, -0.020, 0.011, 0.007);
        s.loc[0][0] = ex0b;
        s.loc[0][1] = ez0b;
        s.loc[1][0] = ex0c;
        s.loc[1][1] = ey0c;
        let qb = Vec3::new(ex0b, 0.0, ez0b);
        let tb = k.pose_transform(&s, &[37.0, 0.0]);
        assert!((tb.point(&qb) - qb).norm() < 1e-12);
        let qc = Vec3::new(ex0b + ex0c, ey0c, 0.0);
        let tc = k.pose_transform(&s, &[0.0, 123.0]);
        assert!((tc.point(&qc) - qc).norm() < 1e-12);
    }

    #[test]
    fn orientation_errors_tilt_the_lines_as_the_contract_says() {
        // First order: u_B = (-EC0B, 1, EA0B), u_C = (EB0C, -EA0C, 1).
        let k = table_bc();
        let mut s = k.nominal_state();
        let (ea0b, ec0b, ea0c, eb0c) = (3e-4, -2e-4, 1e-4, 4e-4);
        s.loc[0][2] = ea0b;
        s.loc[0][3] = ec0b;
        s.loc[1][2] = ea0c;
        s.loc[1][3] = eb0c;
        // A point on the tilted C line stays fixed by any C rotation (at b = 0).
        let uc = Vec3::new(eb0c, -ea0c, 1.0).normalize();
        let p = uc * 200.0;
        let t = k.pose_transform(&s, &[0.0, 77.0]);
        assert!((t.point(&p) - p).norm() < 1e-6 * 200.0 * 1e-3);
        let ub = Vec3::new(-ec0b, 1.0, ea0b).normalize();
        let p = ub * 200.0;
        let t = k.pose_transform(&s, &[33.0, 0.0]);
        assert!((t.point(&p) - p).norm() < 1e-4);
    }

    #[test]
    fn apparent_state_gives_the_same_readings_with_the_tool_tip_at_zero() {
        use crate::measurement::{Approach, Axis, latched};
        let k = table_bc();
        let mut s = k.nominal_state();
        s.loc[0] = [0.02, -0.03, 2e-4, -1e-4, 0.0];
        s.loc[1] = [0.01, 0.015, 3e-4, -2e-4, 0.0];
        s.tool_tip = Vec3::new(0.012, -0.007, -0.080);
        let a = k.apparent_state(&s);
        assert_eq!(a.tool_tip, Vec3::zeros());
        // The contract's rule to first order (second-order terms here are below 1 nm).
        assert!((a.loc[0][0] - (0.02 - 0.012)).abs() < 2e-6);
        assert!((a.loc[0][1] - (-0.03 + 0.080)).abs() < 2e-6);
        // EY0C also takes sz times the C tilt, where the shifted line is named at z = 0.
        assert!((a.loc[1][1] - (0.015 + 0.007 - (-0.080) * 3e-4)).abs() < 2e-6);
        assert!((a.loc[1][0] - (0.01 + (-0.080) * (-2e-4))).abs() < 2e-6);
        let probes = [
            ([0.0, -90.0, 0.0], Axis::X, -1, Vec3::new(0.0, 0.0, 65.0)),
            ([0.0, -180.0, 0.0], Axis::Z, -1, Vec3::new(0.0, 100.0, 0.0)),
            ([-90.0, -270.0, 0.0], Axis::X, -1, Vec3::new(0.0, 0.0, 95.0)),
            ([90.0, -90.0, 0.0], Axis::Z, -1, Vec3::new(-70.0, 0.0, 0.0)),
        ];
        for (angles, axis, direction, c) in probes {
            let ap = Approach {
                axis,
                direction,
                feed_mm_min: 100.0,
            };
            let v1 = latched(&k, &s, &angles, &ap, &c, None).unwrap();
            let v2 = latched(&k, &a, &angles, &ap, &c, None).unwrap();
            assert!((v1 - v2).abs() < 1e-12, "{angles:?}: {v1} vs {v2}");
        }
    }

    #[test]
    fn unknown_machine_is_named() {
        let e = Kinematics::load("no_such_machine").unwrap_err().to_string();
        assert!(
            e.contains("no_such_machine") && e.contains("table_bc"),
            "{e}"
        );
    }

    /// A machine file's location error names must be ISO 230-7 names, of the kind of their
    /// slot and of their axis: the unit of every error is read from its name.
    #[test]
    fn a_machine_file_with_a_bad_error_name_is_refused_naming_it() {
        let text = crate::source::builtin_or_file("machine", "table_bc", BUILTIN_MACHINES).unwrap();
        let load = |from: &str, to: &str| {
            assert!(text.contains(from), "{from}");
            let edited = text.replacen(from, to, 1);
            MachineConfig::from_toml(&edited, "edited.toml")
                .and_then(Kinematics::from_config)
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        assert!(load("EX0B", "EX0B").is_ok());
        for (from, to, says) in [
            (
                r#"{ name = "EX0B""#,
                r#"{ name = "EQ0B""#,
                r#"bad location error name "EQ0B""#,
            ),
            (
                r#"zero_error = "EB0B""#,
                r#"zero_error = "eb0b""#,
                r#""eb0b": it must begin"#,
            ),
            (
                r#"identify = ["EX0B""#,
                r#"identify = ["EX0B ""#,
                r#""EX0B ""#,
            ),
            ("EA0B = 0.0", "ch1 = 0.0", r#""ch1""#),
            (
                r#"{ name = "EA0C""#,
                r#"{ name = "EA0X""#,
                "rotary axis A, B, C or D",
            ),
        ] {
            let e = load(from, to).unwrap_err();
            assert!(e.contains("edited.toml") && e.contains(says), "{to}: {e}");
        }
        for (from, to, says) in [
            (
                r#"{ name = "EX0B""#,
                r#"{ name = "EB0B""#,
                "position_errors of axis B names EB0B, which is an orientation error (urad); \
                 it must be a position error (um)",
            ),
            (
                r#"zero_error = "EB0B""#,
                r#"zero_error = "EY0B""#,
                "zero_error of axis B names EY0B, which is a position error (um)",
            ),
            (
                r#"{ name = "EX0C""#,
                r#"{ name = "EX0A""#,
                "position_errors of axis C names EX0A, an error of axis A",
            ),
        ] {
            let e = load(from, to).unwrap_err();
            assert!(e.contains("table_bc") && e.contains(says), "{to}: {e}");
        }
    }

    /// The NC door's ranges come from the machine file; a file whose ranges no machine has,
    /// and a plan that runs the spindle faster than the file allows, are refused at load.
    #[test]
    fn the_limits_of_a_machine_file_are_checked_and_bind_its_plans() {
        let k = Kinematics::load("table_bc").unwrap();
        assert_eq!(k.config.limits.spindle_max_rpm, 30000.0);
        assert_eq!(k.config.limits.celsius, [-10.0, 100.0]);
        for (rpm, celsius) in [
            (0.0, [-10.0, 100.0]),
            (1e9, [-10.0, 100.0]),
            (30000.0, [50.0, 20.0]),
            (30000.0, [-10.0, 1e6]),
        ] {
            let mut cfg = k.config.clone();
            cfg.limits = Limits {
                spindle_max_rpm: rpm,
                celsius,
            };
            let e = Kinematics::from_config(cfg).unwrap_err().to_string();
            assert!(e.contains("limits:"), "{e}");
        }
        let mut cfg = k.config.clone();
        cfg.limits.spindle_max_rpm = 15000.0;
        let slow = Kinematics::from_config(cfg).unwrap();
        let plan = crate::plan::PlanConfig::load("patent").unwrap();
        let e = crate::plan::Plan::build(&slow, &plan)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("spindle_rpm 20000 is above the spindle_max_rpm 15000"),
            "{e}"
        );
    }
}
