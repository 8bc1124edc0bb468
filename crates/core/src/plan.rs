//! Measurement cycle plans: poses and approaches, their order, and the expansion into the full
//! list of moves with an estimate of machine time.
//!
//! The default order is time-symmetric: the B = 0 poses forward, the tilted poses in the
//! middle, then every approach again in reverse (a palindrome: the last tilted pose is probed
//! twice in a row). Every reading then has its mean time at the centre of the cycle, so a drift
//! that is linear over the cycle cancels in every estimate (docs/physics.md 5.2).
//! `as_listed` keeps the patent's sequential order.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::clearance::{
    BeamSegment, TOUCH_MM, ToolCylinder, closest_approach, crossing_height, pose_cylinder_and_beam,
};
use crate::geometry::{Vec3, wrap_deg};
use crate::identify::Observation;
use crate::kinematics::{Kinematics, MAX_ROTARY, MachineState};
use crate::measurement::{Approach, Axis, NoTrip, Travel, latched};

pub const BUILTIN_PLANS: &[(&str, &str)] = &[
    ("patent", include_str!("../../../config/plans/patent.toml")),
    (
        "patent_sequential",
        include_str!("../../../config/plans/patent_sequential.toml"),
    ),
    (
        "patent_both_sides",
        include_str!("../../../config/plans/patent_both_sides.toml"),
    ),
    (
        "table_bc_designed",
        include_str!("../../../config/plans/table_bc_designed.toml"),
    ),
    (
        "head_b_table_c",
        include_str!("../../../config/plans/head_b_table_c.toml"),
    ),
    (
        "head_b_table_c_patent",
        include_str!("../../../config/plans/head_b_table_c_patent.toml"),
    ),
    (
        "table_d45_c",
        include_str!("../../../config/plans/table_d45_c.toml"),
    ),
    (
        "table_d45_c_patent",
        include_str!("../../../config/plans/table_d45_c_patent.toml"),
    ),
    (
        "head_d45_table_c",
        include_str!("../../../config/plans/head_d45_table_c.toml"),
    ),
    (
        "head_d45_table_c_patent",
        include_str!("../../../config/plans/head_d45_table_c_patent.toml"),
    ),
    (
        "trunnion_ac",
        include_str!("../../../config/plans/trunnion_ac.toml"),
    ),
    (
        "trunnion_ac_patent",
        include_str!("../../../config/plans/trunnion_ac_patent.toml"),
    ),
];

#[derive(Debug, Error)]
pub enum PlanError {
    #[error(transparent)]
    Source(#[from] crate::source::SourceError),
    #[error("plan {origin} is not valid TOML for a plan: {message}")]
    Parse { origin: String, message: String },
    #[error("plan '{plan}': {message}")]
    Invalid { plan: String, message: String },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Order {
    #[default]
    TimeSymmetric,
    AsListed,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseConfig {
    /// The tilting axis' angle: B, or D or A on machines that have those (`d_deg` and
    /// `a_deg` are read as this field), as in the detection message.
    #[serde(alias = "a_deg", alias = "d_deg")]
    pub b_deg: f64,
    pub c_deg: f64,
    /// `"z"` (the end face, moving along the tool axis out of the spindle: -z for a vertical
    /// spindle), `"lateral"` (across the beam and the tool axis from outside, along the linear
    /// axis that lies so), or an explicit lateral `"x+"`, `"x-"`, `"y+"`, `"y-"`, `"z+"`,
    /// `"z-"` (axis and direction of motion).
    pub approaches: Vec<String>,
    /// Touches of each approach in a row.
    #[serde(default = "one")]
    pub repeats: u32,
}

fn one() -> u32 {
    1
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanConfig {
    pub name: String,
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub order: Order,
    /// Probing feed, mm/min.
    pub feed_mm_min: f64,
    /// Spindle speed during the cycle, min^-1 (the patent measures at machining speed).
    pub spindle_rpm: f64,
    /// Distance from the approach start to the nominal trip, mm.
    pub clearance_mm: f64,
    /// Travel beyond the nominal trip before the approach ends as `no_trip`, mm.
    pub overtravel_mm: f64,
    /// Depth of the tool end below the beam on lateral approaches, mm.
    pub lateral_depth_mm: f64,
    /// Air blast and settle time before each approach, s.
    pub dwell_s: f64,
    pub poses: Vec<PoseConfig>,
}

impl PlanConfig {
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, PlanError> {
        toml::from_str(text).map_err(|e| PlanError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })
    }

    pub fn load(name_or_path: &str) -> Result<Self, PlanError> {
        let text = crate::source::builtin_or_file("plan", name_or_path, BUILTIN_PLANS)?;
        Self::from_toml(&text, name_or_path)
    }
}

/// One approach of a cycle, ready to run.
#[derive(Debug, Clone)]
pub struct Step {
    pub label: String,
    pub b_deg: f64,
    pub c_deg: f64,
    pub angles: [f64; MAX_ROTARY],
    pub approach: Approach,
    /// Commanded start position of the approach, mm.
    pub start: Vec3,
    /// The nominal latched value of the moving coordinate, mm.
    pub expected: f64,
    pub max_travel_mm: f64,
    /// Time from the cycle start to the start of this approach, s.
    pub t_start_s: f64,
}

impl Step {
    pub fn travel(&self) -> Travel {
        Travel {
            start: self.start[self.approach.axis.index()],
            max_mm: self.max_travel_mm,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveKind {
    Rapid,
    Rotary,
    Dwell,
    Probe,
}

#[derive(Debug, Clone, Serialize)]
pub struct Move {
    pub kind: MoveKind,
    pub t_start_s: f64,
    pub duration_s: f64,
    /// Position (mm) and angles (deg) at the end of the move.
    pub to: [f64; 3],
    pub angles_deg: [f64; MAX_ROTARY],
    pub step: Option<usize>,
    pub note: String,
}

#[derive(Debug, Clone)]
pub struct Plan {
    pub name: String,
    pub description: String,
    pub config: PlanConfig,
    pub steps: Vec<Step>,
    pub moves: Vec<Move>,
    pub machine_time_s: f64,
}

/// An approach as a plan names it: the end face, or a lateral one along a given or derived
/// axis and direction.
enum ApproachSpec {
    EndFace,
    Lateral(Option<(Axis, i8)>),
}

fn parse_approach(s: &str) -> Option<ApproachSpec> {
    let lateral = |a, d| Some(ApproachSpec::Lateral(Some((a, d))));
    match s {
        "z" => Some(ApproachSpec::EndFace),
        "lateral" => Some(ApproachSpec::Lateral(None)),
        "x+" => lateral(Axis::X, 1),
        "x-" => lateral(Axis::X, -1),
        "y+" => lateral(Axis::Y, 1),
        "y-" => lateral(Axis::Y, -1),
        "z+" => lateral(Axis::Z, 1),
        "z-" => lateral(Axis::Z, -1),
        _ => None,
    }
}

/// The machine axis a unit vector lies along, with its sign, if it lies along one.
fn along_axis(v: &Vec3) -> Option<(Axis, i8)> {
    [Axis::X, Axis::Y, Axis::Z]
        .into_iter()
        .find(|a| v[a.index()].abs() > 1.0 - 1e-9)
        .map(|a| (a, v[a.index()].signum() as i8))
}

/// The commanded axis, direction and held position of one approach at a pose whose beam
/// passes through `p` along `e` with the tool axis `w` (nominal state).
fn approach_geometry(
    spec: &ApproachSpec,
    cfg: &PlanConfig,
    (p, e, w): (Vec3, Vec3, Vec3),
) -> Result<(Axis, i8, Vec3), String> {
    match spec {
        ApproachSpec::EndFace => {
            // Along the tool axis, out of the spindle, over the probed point of the beam.
            let (axis, sign) = along_axis(&w)
                .ok_or("the tool axis is not parallel to a linear axis; no end-face approach")?;
            Ok((axis, -sign, p))
        }
        ApproachSpec::Lateral(given) => {
            // Across both the beam and the tool axis, pointing away from the machine origin
            // (as seen along the tool axis); the tool end past the beam by the depth.
            let mut n = w.cross(&e);
            if n.norm() < 1e-9 {
                return Err("the beam is parallel to the tool axis; no lateral approach".into());
            }
            n /= n.norm();
            if n.dot(&(p - w * w.dot(&p))) < 0.0 {
                n = -n;
            }
            let (axis, direction) = match given {
                Some(g) => *g,
                None => {
                    let (axis, sign) = along_axis(&n).ok_or(
                        "the beam is not square to a linear axis across the tool; give the \
                         lateral approach explicitly (x+, x-, y+, y-, z+, z-)",
                    )?;
                    (axis, -sign)
                }
            };
            Ok((axis, direction, p - w * cfg.lateral_depth_mm))
        }
    }
}

/// A plan's moves as [`Plan::expand_moves`] lays them out: the moves so far, the machine time
/// at their end, and where the tool and the rotary axes are.
struct Layout {
    moves: Vec<Move>,
    t: f64,
    pos: Vec3,
    angles: [f64; MAX_ROTARY],
    /// Rapid and probing feeds, mm/s.
    rapid: f64,
    feed: f64,
}

impl Layout {
    fn new(k: &Kinematics, feed_mm_min: f64) -> Self {
        Layout {
            moves: Vec::new(),
            t: 0.0,
            pos: Vec3::new(0.0, 0.0, k.motion.safe_z_mm),
            angles: [0.0; MAX_ROTARY],
            rapid: k.motion.rapid_mm_min / 60.0,
            feed: feed_mm_min / 60.0,
        }
    }

    /// A move of `d` s to `to` in the current pose, after the last.
    fn push(&mut self, kind: MoveKind, d: f64, to: Vec3, step: Option<usize>, note: String) {
        self.moves.push(Move {
            kind,
            t_start_s: self.t,
            duration_s: d,
            to: [to.x, to.y, to.z],
            angles_deg: self.angles,
            step,
            note,
        });
        self.t += d;
    }

    /// Retract to the safe Z if below it, then index the rotary axes to `angles`.
    fn index_to(&mut self, k: &Kinematics, angles: [f64; MAX_ROTARY]) {
        if self.pos.z < k.motion.safe_z_mm {
            let to = Vec3::new(self.pos.x, self.pos.y, k.motion.safe_z_mm);
            let d = (k.motion.safe_z_mm - self.pos.z) / self.rapid;
            self.push(MoveKind::Rapid, d, to, None, "retract to safe Z".into());
            self.pos = to;
        }
        let dur = k
            .rotary
            .iter()
            .enumerate()
            .map(|(j, ax)| wrap_deg(angles[j] - self.angles[j]).abs() / (ax.speed_deg_min / 60.0))
            .fold(0.0, f64::max);
        self.angles = angles;
        self.push(
            MoveKind::Rotary,
            dur + k.motion.clamp_s,
            self.pos,
            None,
            "unclamp, index, clamp".into(),
        );
    }

    /// Step `i` in the current pose: over its start clear of the beam, down, dwell, probe and
    /// back off; sets the step's start time. `guard` is the tool and the beam at the pose.
    fn probe(
        &mut self,
        cfg: &PlanConfig,
        (i, step): (usize, &mut Step),
        same_pose: bool,
        guard: &(ToolCylinder, BeamSegment),
    ) {
        let rapid = self.rapid;
        // Over the start at a height clear of the beam, then down to the start.
        // Over the start clear of the beam: above the trip when the approach moves along z.
        let top = match step.approach.axis {
            Axis::Z => step.start.z.max(step.expected + cfg.clearance_mm),
            _ => step.start.z,
        };
        let clear_z = top + 5.0;
        let clear_z = if same_pose {
            clear_z
        } else {
            self.pos.z.max(clear_z)
        };
        // `top + 5` clears a level beam; a sloping one rises within the tool's radius of its
        // axis, and the move across passes over more of it than the approach does: at least
        // high enough that the tool grown by the crossing margin passes clear of it.
        let (tool, beam) = guard;
        let clear_z = crossing_height(tool, beam, &self.pos, &step.start, clear_z.max(self.pos.z))
            .max(clear_z);
        if self.pos.z < clear_z {
            let to = Vec3::new(self.pos.x, self.pos.y, clear_z);
            let d = (clear_z - self.pos.z) / rapid;
            self.push(
                MoveKind::Rapid,
                d,
                to,
                None,
                "up clear of the setter".into(),
            );
            self.pos = to;
        }
        let over = Vec3::new(step.start.x, step.start.y, self.pos.z);
        let dxy = (over - self.pos).norm();
        if dxy > 0.0 {
            self.push(
                MoveKind::Rapid,
                dxy / rapid,
                over,
                None,
                "to the approach".into(),
            );
        }
        let dz = (self.pos.z - step.start.z).abs();
        self.push(
            MoveKind::Rapid,
            dz / rapid,
            step.start,
            None,
            "down to the start".into(),
        );
        self.push(
            MoveKind::Dwell,
            cfg.dwell_s,
            step.start,
            Some(i),
            "air blast, settle".into(),
        );
        step.t_start_s = self.t;
        let probe_len = cfg.clearance_mm;
        let mut end = step.start;
        end[step.approach.axis.index()] = step.expected;
        self.push(
            MoveKind::Probe,
            probe_len / self.feed,
            end,
            Some(i),
            step.label.clone(),
        );
        self.push(
            MoveKind::Rapid,
            probe_len / rapid,
            step.start,
            Some(i),
            "back off".into(),
        );
        self.pos = step.start;
    }

    /// Back to the safe Z, and to the zero pose if the axes are not there.
    fn finish(&mut self, k: &Kinematics) {
        let to = Vec3::new(self.pos.x, self.pos.y, k.motion.safe_z_mm);
        let d = (k.motion.safe_z_mm - self.pos.z).max(0.0) / self.rapid;
        self.push(MoveKind::Rapid, d, to, None, "retract to safe Z".into());
        if self.angles.iter().any(|a| wrap_deg(*a).abs() > 1e-9) {
            let dur = k
                .rotary
                .iter()
                .enumerate()
                .map(|(j, ax)| wrap_deg(self.angles[j]).abs() / (ax.speed_deg_min / 60.0))
                .fold(0.0, f64::max);
            self.angles = [0.0; MAX_ROTARY];
            self.push(
                MoveKind::Rotary,
                dur + k.motion.clamp_s,
                to,
                None,
                "back to the zero pose".into(),
            );
        }
    }
}

impl Plan {
    pub fn build(k: &Kinematics, cfg: &PlanConfig) -> Result<Plan, PlanError> {
        let invalid = |message: String| PlanError::Invalid {
            plan: cfg.name.clone(),
            message,
        };
        let positive = [
            ("feed_mm_min", cfg.feed_mm_min),
            ("clearance_mm", cfg.clearance_mm),
            ("overtravel_mm", cfg.overtravel_mm),
            ("lateral_depth_mm", cfg.lateral_depth_mm),
        ];
        for (name, v) in positive {
            if !crate::units::positive(v) {
                return Err(invalid(format!("{name} must be a positive number")));
            }
        }
        if !(cfg.dwell_s >= 0.0 && cfg.spindle_rpm >= 0.0) {
            return Err(invalid("dwell_s and spindle_rpm must be >= 0".into()));
        }
        if cfg.spindle_rpm > k.config.limits.spindle_max_rpm {
            return Err(invalid(format!(
                "spindle_rpm {} is above the spindle_max_rpm {} of machine '{}'",
                cfg.spindle_rpm, k.config.limits.spindle_max_rpm, k.name
            )));
        }
        if cfg.poses.is_empty() {
            return Err(invalid("has no poses".into()));
        }
        let nominal = k.nominal_state();
        // Steps of each pose, in listed order.
        let mut per_pose: Vec<(bool, Vec<Step>)> = Vec::new();
        for pose in &cfg.poses {
            let angles = k.angles_from_fields(pose.b_deg, pose.c_deg);
            let label_pose = k.pose_label(&angles);
            for (i, ax) in k.rotary.iter().enumerate() {
                if angles[i] < ax.travel_deg[0] || angles[i] > ax.travel_deg[1] {
                    return Err(invalid(format!(
                        "pose {label_pose} is outside the travel of axis {}",
                        ax.name
                    )));
                }
            }
            let g = k.pose_geometry(&nominal, &angles);
            let mut steps = Vec::new();
            for spec_text in &pose.approaches {
                let spec = parse_approach(spec_text).ok_or_else(|| {
                    invalid(format!(
                        "approach '{spec_text}' is not one of z, lateral, x+, x-, y+, y-, z+, z-"
                    ))
                })?;
                let (axis, direction, held) =
                    approach_geometry(&spec, cfg, (g.beam_point, g.beam_dir, g.tool.axis))
                        .map_err(|m| invalid(format!("pose {label_pose}, {spec_text}: {m}")))?;
                let approach = Approach {
                    axis,
                    direction,
                    feed_mm_min: cfg.feed_mm_min,
                };
                let expected = latched(k, &nominal, &angles, &approach, &held, None)
                    .map_err(|e: NoTrip| invalid(format!("pose {label_pose}, {spec_text}: {e}")))?;
                let mut start = held;
                start[axis.index()] = expected - f64::from(direction) * cfg.clearance_mm;
                for rep in 0..pose.repeats.max(1) {
                    let mut label = format!("{label_pose}/{}", axis.name());
                    if pose.repeats > 1 {
                        label.push_str(&format!(".{}", rep + 1));
                    }
                    steps.push(Step {
                        label,
                        b_deg: pose.b_deg,
                        c_deg: pose.c_deg,
                        angles,
                        approach,
                        start,
                        expected,
                        max_travel_mm: cfg.clearance_mm + cfg.overtravel_mm,
                        t_start_s: 0.0,
                    });
                }
            }
            per_pose.push((k.is_tilted(&angles), steps));
        }
        let mut steps: Vec<Step> = Vec::new();
        match cfg.order {
            Order::AsListed => {
                for (_, s) in &per_pose {
                    steps.extend(s.iter().cloned());
                }
            }
            Order::TimeSymmetric => {
                let forward: Vec<&Step> = per_pose
                    .iter()
                    .filter(|(t, _)| !t)
                    .chain(per_pose.iter().filter(|(t, _)| *t))
                    .flat_map(|(_, s)| s.iter())
                    .collect();
                for (pass, seq) in [
                    (1, forward.clone()),
                    (2, forward.into_iter().rev().collect()),
                ] {
                    for s in seq {
                        let mut s = s.clone();
                        s.label.push_str(&format!("#{pass}"));
                        steps.push(s);
                    }
                }
            }
        }
        let mut plan = Plan {
            name: cfg.name.clone(),
            description: cfg.description.clone(),
            config: cfg.clone(),
            steps,
            moves: Vec::new(),
            machine_time_s: 0.0,
        };
        plan.expand_moves(k);
        Ok(plan)
    }

    /// Moves and times: retract to the safe Z before any rotary move, rapid to the approach
    /// start (over the beam, then down), dwell, probe to the nominal trip, back to the start.
    fn expand_moves(&mut self, k: &Kinematics) {
        let mut l = Layout::new(k, self.config.feed_mm_min);
        for (i, step) in self.steps.iter_mut().enumerate() {
            let same_pose = l
                .angles
                .iter()
                .zip(step.angles.iter())
                .all(|(a, b)| (wrap_deg(a - b)).abs() < 1e-9);
            if !same_pose {
                l.index_to(k, step.angles);
            }
            let guard = pose_cylinder_and_beam(k, &step.angles);
            l.probe(&self.config, (i, step), same_pose, &guard);
        }
        l.finish(k);
        self.moves = l.moves;
        self.machine_time_s = l.t;
    }

    /// The observations a machine in `state` gives for this plan, without noise, each at its
    /// approach's start time (a template for the solver, a noise-free test cycle).
    pub fn observations(
        &self,
        k: &Kinematics,
        state: &MachineState,
    ) -> Result<Vec<Observation>, PlanError> {
        self.steps
            .iter()
            .map(|s| {
                let v = latched(k, state, &s.angles, &s.approach, &s.start, None).map_err(|e| {
                    PlanError::Invalid {
                        plan: self.name.clone(),
                        message: format!("step {}: {e}", s.label),
                    }
                })?;
                let mut position = s.start;
                position[s.approach.axis.index()] = v;
                Ok(Observation {
                    label: s.label.clone(),
                    angles: s.angles,
                    approach: s.approach,
                    position,
                    t_ns: (s.t_start_s * 1e9) as i64,
                })
            })
            .collect()
    }

    pub fn step_index(&self, label: &str) -> Option<usize> {
        self.steps.iter().position(|s| s.label == label)
    }
}

/// A move of a plan that puts the beam inside the tool.
#[derive(Debug, Clone, Serialize)]
pub struct BeamContact {
    /// Index in `Plan::moves`.
    pub move_index: usize,
    pub note: String,
    /// The step the move belongs to or leads to (the next approach), if any.
    pub step_label: Option<String>,
    pub from: [f64; 3],
    pub to: [f64; 3],
    pub angles_deg: [f64; MAX_ROTARY],
    /// How far the beam comes inside the tool's surface, mm.
    pub depth_mm: f64,
}

impl std::fmt::Display for BeamContact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = |v: &[f64; 3]| format!("({:.3}, {:.3}, {:.3})", v[0], v[1], v[2]);
        write!(
            f,
            "move {} '{}' from {} to {}{}: the beam comes {:.3} mm inside the tool",
            self.move_index + 1,
            self.note,
            p(&self.from),
            p(&self.to),
            self.step_label
                .as_ref()
                .map(|l| format!(" (before step {l})"))
                .unwrap_or_default(),
            self.depth_mm
        )
    }
}

/// Every move of `plan` other than a probing move that puts the beam inside the tool, in the
/// machine's nominal state. A rotary index is taken as made with the tool where it stands (at
/// the safe Z) and is not checked.
pub fn beam_contacts(k: &Kinematics, plan: &Plan) -> Vec<BeamContact> {
    let mut out = Vec::new();
    let mut pos = Vec3::new(0.0, 0.0, k.motion.safe_z_mm);
    let mut cache: Vec<([f64; MAX_ROTARY], (ToolCylinder, BeamSegment))> = Vec::new();
    for (i, m) in plan.moves.iter().enumerate() {
        let to = Vec3::new(m.to[0], m.to[1], m.to[2]);
        // The back-off: the probing move's own path reversed, from where it latched (in the
        // beam by the latency's travel, `feed * latency_ms`, on a machine whose setter has one).
        let back_off = i > 0 && plan.moves[i - 1].kind == MoveKind::Probe;
        if m.kind == MoveKind::Rapid && !back_off {
            let (tool, beam) = match cache.iter().find(|(a, _)| *a == m.angles_deg) {
                Some((_, g)) => *g,
                None => {
                    let g = pose_cylinder_and_beam(k, &m.angles_deg);
                    cache.push((m.angles_deg, g));
                    g
                }
            };
            let gap = closest_approach(&tool, &beam, &(pos + tool.offset), &(to + tool.offset));
            if let Some(gap) = gap.filter(|g| *g < tool.radius - TOUCH_MM) {
                let step = m
                    .step
                    .or_else(|| plan.moves[i..].iter().find_map(|n| n.step))
                    .map(|s| plan.steps[s].label.clone());
                out.push(BeamContact {
                    move_index: i,
                    note: m.note.clone(),
                    step_label: step,
                    from: [pos.x, pos.y, pos.z],
                    to: m.to,
                    angles_deg: m.angles_deg,
                    depth_mm: tool.radius - gap,
                });
            }
        }
        pos = to;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patent_plan_expands_symmetrically() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let cfg = PlanConfig::load("patent").unwrap();
        let plan = Plan::build(&k, &cfg).unwrap();
        assert_eq!(plan.steps.len(), 24);
        let first: Vec<_> = plan.steps[..12].iter().map(|s| s.label.clone()).collect();
        let last: Vec<_> = plan.steps[12..]
            .iter()
            .rev()
            .map(|s| s.label.replace("#2", "#1"))
            .collect();
        assert_eq!(first, last);
        // The tilted poses sit in the middle.
        assert!(plan.steps[8..16].iter().all(|s| s.b_deg != 0.0));
        // Patent approach directions: C = 0 from -Y moving +Y; B = -90 from +X moving -X.
        let y1 = &plan.steps[1];
        assert_eq!((y1.approach.axis, y1.approach.direction), (Axis::Y, 1));
        let x5 = plan
            .steps
            .iter()
            .find(|s| s.label.starts_with("B-90C-270/x"))
            .unwrap();
        assert_eq!((x5.approach.axis, x5.approach.direction), (Axis::X, -1));
        assert!((x5.expected - 75.0).abs() < 1e-9);
        // Approach times increase, and their mean is the middle of the probing.
        assert!(
            plan.steps
                .windows(2)
                .all(|w| w[1].t_start_s > w[0].t_start_s)
        );
    }

    /// The both-sides plan meets each B = 0 pose's beam from both senses of its lateral axis,
    /// and only there (the tilted poses as in `patent`).
    #[test]
    fn both_sides_plan_touches_each_upright_pose_from_both_sides() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent_both_sides").unwrap()).unwrap();
        assert_eq!(plan.steps.len(), 32);
        let mut sides: std::collections::BTreeMap<(i64, i64), Vec<(Axis, i8)>> = Default::default();
        for s in plan.steps.iter().filter(|s| s.approach.axis != Axis::Z) {
            let v = sides
                .entry((s.b_deg.round() as i64, s.c_deg.round() as i64))
                .or_default();
            if !v.contains(&(s.approach.axis, s.approach.direction)) {
                v.push((s.approach.axis, s.approach.direction));
            }
        }
        for ((b, c), v) in &sides {
            let both = v.len() == 2 && v[0].0 == v[1].0 && v[0].1 == -v[1].1;
            assert_eq!(both, *b == 0, "B{b} C{c}: {v:?}");
        }
        assert_eq!(sides.len(), 6);
    }

    #[test]
    fn sequential_plan_keeps_the_listed_order() {
        let k = Kinematics::builtin("table_bc").unwrap();
        let plan = Plan::build(&k, &PlanConfig::load("patent_sequential").unwrap()).unwrap();
        let labels: Vec<_> = plan.steps.iter().map(|s| s.label.as_str()).collect();
        assert_eq!(
            labels,
            [
                "B0C0/z",
                "B0C0/y",
                "B0C-90/z",
                "B0C-90/x",
                "B0C-180/z",
                "B0C-180/y",
                "B0C-270/z",
                "B0C-270/x",
                "B-90C-270/z",
                "B-90C-270/x",
                "B90C-90/z",
                "B90C-90/x"
            ]
        );
    }

    /// No built-in plan, on any built-in machine it builds on, moves the tool into the beam
    /// outside a probing move: the tool a cylinder of its radius from its end up the tool axis,
    /// the beam 40 mm either side of the probed point. Also with a skip latency (LinuxCNC's
    /// half servo period), which puts every probing move's end, and its back-off's start,
    /// inside the beam by the latency's travel.
    #[test]
    fn no_builtin_plan_moves_the_tool_through_the_beam() {
        use crate::kinematics::BUILTIN_MACHINES;
        let mut built = 0;
        let mut contacts = Vec::new();
        for ((machine, _), latency_s) in BUILTIN_MACHINES
            .iter()
            .flat_map(|m| [(m, 0.0), (m, 0.5e-3)])
        {
            let mut k = Kinematics::builtin(machine).unwrap();
            k.setter.latency_s = latency_s;
            for (name, _) in BUILTIN_PLANS {
                let Ok(plan) = Plan::build(&k, &PlanConfig::load(name).unwrap()) else {
                    continue;
                };
                built += 1;
                for c in beam_contacts(&k, &plan) {
                    contacts.push(format!("{name} on {machine} (latency {latency_s} s): {c}"));
                }
            }
        }
        // Each machine's own plan at least.
        assert!(built >= BUILTIN_MACHINES.len(), "{built}");
        assert!(contacts.is_empty(), "{}", contacts.join("\n"));
    }
}
