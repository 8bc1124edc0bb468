//! The kinematic tests: one rotary axis turns while the linear axes keep the tool (the ball or
//! the nest on the spindle) on a point fixed to the table, as ISO 10791-6:2014 prescribes, and
//! the R-test reads at each angle.
//!
//! The standard itself was not available to us; the tests follow seed 002's description:
//! - `BK1` (seed: "ZXB simultaneous"): the tilting axis (B, D or A) sweeps, the table axis at
//!   zero, the ball off the tilting axis: the two linear axes across the tilting axis follow.
//! - `BK2` (seed: "XYZ simultaneous"): the table axis (C) turns a revolution with the tilting
//!   axis held at a tilt, the ball off the C axis: all three linear axes follow.
//! - `XYC`: the table axis turns a revolution at zero tilt, the ball 100 mm off it (the seed's
//!   radius): X and Y follow.
//!
//! The commanded positions are the NC's nominal inverse kinematics (what tool-centre-point
//! control or a CAM post-processor computes): the tool reference point at `T_nom(angles) P`,
//! the linear axes there minus the nominal head offset. The simulation is quasi-static (each
//! reading at standstill on the path): the seed's feed-dependent errors when two linear axes
//! move together are servo dynamics, not modelled here.

use driftwatch_core::geometry::{Mat3, Vec3};
use driftwatch_core::kinematics::{Kinematics, MAX_ROTARY, MachineState, Side};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::instrument::{Instrument, ReadingError, Setting};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum TestKind {
    Bk1,
    Bk2,
    Xyc,
}

impl TestKind {
    pub const ALL: [TestKind; 3] = [TestKind::Bk1, TestKind::Bk2, TestKind::Xyc];

    pub fn name(self) -> &'static str {
        match self {
            TestKind::Bk1 => "BK1",
            TestKind::Bk2 => "BK2",
            TestKind::Xyc => "XYC",
        }
    }

    pub fn parse(s: &str) -> Option<TestKind> {
        match s.to_ascii_lowercase().as_str() {
            "bk1" => Some(TestKind::Bk1),
            "bk2" => Some(TestKind::Bk2),
            "xyc" => Some(TestKind::Xyc),
            _ => None,
        }
    }
}

/// One test as it runs on a machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TestSpec {
    pub kind: TestKind,
    /// The rotary axis that turns (index in the machine's chain).
    pub axis: usize,
    /// The angles (deg) of every axis; the turning axis' entry is replaced along the sweep.
    pub fixed_deg: [f64; MAX_ROTARY],
    /// Sweep of the turning axis, deg: from, to, step.
    pub from_deg: f64,
    pub to_deg: f64,
    pub step_deg: f64,
    /// Out and back (reversal shows as a difference between the two).
    pub bidirectional: bool,
    /// The nominal ball (or nest) centre on the table, table frame, mm.
    pub ball_mm: Vec3,
    /// Feed along the path, mm/min (sets the time between readings).
    pub feed_mm_min: f64,
    /// Standstill at each reading, s.
    pub dwell_s: f64,
}

/// Why a test cannot run on a machine.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TestError {
    #[error("{machine} has no {what} axis for {test}")]
    NoAxis {
        machine: String,
        test: &'static str,
        what: &'static str,
    },
    #[error("{test}: the ball lies on the turning axis; radial and tangential are undefined")]
    BallOnAxis { test: &'static str },
    #[error("{test} at {angle_deg} deg: {source}")]
    Reading {
        test: &'static str,
        angle_deg: f64,
        source: ReadingError,
    },
    #[error(
        "{test}: the sweep {from} -> {to} deg in steps of {step} deg is empty or beyond the travel {travel:?}"
    )]
    Sweep {
        test: &'static str,
        from: f64,
        to: f64,
        step: f64,
        travel: [f64; 2],
    },
}

/// The ball 100 mm off the table axis, 50 mm above the machine origin, across the tilting axis.
fn default_ball(k: &Kinematics, tilt: Option<usize>, table: Option<usize>) -> Vec3 {
    let up = table.map(|t| k.rotary[t].u0).unwrap_or(Vec3::z());
    let across = tilt
        .map(|t| k.rotary[t].u0.cross(&up))
        .filter(|v| v.norm() > 1e-6)
        .map(|v| v.normalize())
        .unwrap_or(Vec3::x());
    // Point the offset towards +X or +Y where it can (the seed's sensor 1 along +X).
    let across = if across.x + across.y < 0.0 {
        -across
    } else {
        across
    };
    across * 100.0 + up * 50.0
}

impl TestSpec {
    /// The test on a built-in or configured machine, with the defaults above: BK1 sweeps the
    /// tilting axis over +-90 deg (or its travel, if shorter), BK2 turns the table axis at
    /// half the tilt's travel towards its negative end (at most 45 deg), XYC at zero tilt; 10
    /// deg steps, out and back, 500 mm/min (the seed's feed).
    pub fn default_for(k: &Kinematics, kind: TestKind) -> Result<TestSpec, TestError> {
        let table = k.table_axis().filter(|&t| k.rotary[t].side == Side::Table);
        let tilt = (0..k.rotary.len()).find(|&i| Some(i) != table);
        let ball = default_ball(k, tilt, table);
        let need = |axis: Option<usize>, what| {
            axis.ok_or(TestError::NoAxis {
                machine: k.name.clone(),
                test: kind.name(),
                what,
            })
        };
        let mut spec = TestSpec {
            kind,
            axis: 0,
            fixed_deg: [0.0; MAX_ROTARY],
            from_deg: 0.0,
            to_deg: 360.0,
            step_deg: 10.0,
            bidirectional: true,
            ball_mm: ball,
            feed_mm_min: 500.0,
            dwell_s: 1.0,
        };
        match kind {
            TestKind::Bk1 => {
                let t = need(tilt, "tilting")?;
                let [lo, hi] = k.rotary[t].travel_deg;
                spec.axis = t;
                spec.from_deg = lo.max(-90.0);
                spec.to_deg = hi.min(90.0);
            }
            TestKind::Bk2 | TestKind::Xyc => {
                let c = need(table, "table")?;
                spec.axis = c;
                if kind == TestKind::Bk2 {
                    let t = need(tilt, "tilting")?;
                    let [lo, _] = k.rotary[t].travel_deg;
                    spec.fixed_deg[t] = (lo / 2.0).max(-45.0);
                }
            }
        }
        Ok(spec)
    }

    /// The commanded angles of the sweep, in order (out, then back when bidirectional).
    pub fn angles(&self) -> Vec<[f64; MAX_ROTARY]> {
        let n = ((self.to_deg - self.from_deg) / self.step_deg)
            .round()
            .max(0.0) as usize;
        let out: Vec<f64> = (0..=n)
            .map(|i| self.from_deg + i as f64 * self.step_deg)
            .collect();
        let mut seq = out.clone();
        if self.bidirectional {
            seq.extend(out.iter().rev());
        }
        seq.into_iter()
            .map(|a| {
                let mut angles = self.fixed_deg;
                angles[self.axis] = a;
                angles
            })
            .collect()
    }

    fn check(&self, k: &Kinematics) -> Result<(), TestError> {
        let travel = k.rotary[self.axis].travel_deg;
        let inside = |a: f64| a >= travel[0] - 1e-9 && a <= travel[1] + 1e-9;
        if self.step_deg <= 0.0
            || self.to_deg <= self.from_deg
            || !inside(self.from_deg)
            || !inside(self.to_deg)
        {
            return Err(TestError::Sweep {
                test: self.kind.name(),
                from: self.from_deg,
                to: self.to_deg,
                step: self.step_deg,
                travel,
            });
        }
        let state = k.nominal_state();
        let (dir, q) = axis_line(k, &state, self.axis, &self.fixed_deg);
        let p = k
            .pose_transform(&state, &self.fixed_deg)
            .point(&self.ball_mm);
        let radial = (p - q) - dir * (p - q).dot(&dir);
        if radial.norm() < 1.0 {
            return Err(TestError::BallOnAxis {
                test: self.kind.name(),
            });
        }
        Ok(())
    }
}

/// The nominal line of axis `i` in the machine frame at these angles: (direction, a point).
/// An axis turns with every axis outside it on its side (the table axis with the tilt).
pub fn axis_line(
    k: &Kinematics,
    state: &MachineState,
    i: usize,
    angles: &[f64; MAX_ROTARY],
) -> (Vec3, Vec3) {
    let mut outer = *angles;
    for (j, a) in outer.iter_mut().enumerate() {
        // Only the axes before it on its side carry it.
        if j >= i || k.rotary[j].side != k.rotary[i].side {
            *a = 0.0;
        }
    }
    let ax = &k.rotary[i];
    let t = match ax.side {
        Side::Table => k.pose_transform(state, &outer),
        Side::Head => k.head_transform_on(&k.lines(state), state, &outer),
    };
    (t.vector(&ax.u0).normalize(), t.point(&ax.q0))
}

/// One reading along a test.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub index: usize,
    pub angles_deg: [f64; MAX_ROTARY],
    /// The commanded linear-axis position, mm.
    pub commanded_mm: Vec3,
    /// Sensor readings, um.
    pub readings_um: [f64; 3],
    pub t_ns: i64,
}

/// One test as recorded: what ran and what the device read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Run {
    pub spec: TestSpec,
    pub setting: Setting,
    pub points: Vec<Point>,
}

/// Where the tool and the nest stand at one pose: the geometry an instrument reads.
struct Pose {
    /// Tool reference point relative to the table point, machine frame, mm.
    tool_rel: Vec3,
    /// Table rotation (table frame -> machine) and head rotation (head frame -> machine).
    table: Mat3,
    head: Mat3,
}

fn pose(k: &Kinematics, state: &MachineState, angles: &[f64; MAX_ROTARY], p: &Vec3) -> Pose {
    let nominal = k.nominal_state();
    let nl = k.lines(&nominal);
    // The NC's command: the tool reference point at the nominal image of P.
    let target = k.pose_transform_on(&nl, &nominal, angles).point(p);
    let cmd = target - k.tool_pose_on(&nl, &nominal, angles).nominal;
    let lines = k.lines(state);
    let tool = k.tool_pose_on(&lines, state, angles);
    let tip = state.linear.tip(&cmd, &tool.actual) + tool.actual;
    let t = k.pose_transform_on(&lines, state, angles);
    Pose {
        tool_rel: tip - t.point(p),
        table: t.r,
        head: k.head_transform_on(&lines, state, angles).r,
    }
}

/// The commanded linear-axis position at a pose, mm.
pub fn commanded(k: &Kinematics, angles: &[f64; MAX_ROTARY], p: &Vec3) -> Vec3 {
    let nominal = k.nominal_state();
    let nl = k.lines(&nominal);
    k.pose_transform_on(&nl, &nominal, angles).point(p)
        - k.tool_pose_on(&nl, &nominal, angles).nominal
}

/// How the device sits on the machine: the table-side object (the nest in E and J, the ball in
/// Es) off its programmed centre `P` (table frame), and the spindle-side object (the ball in E
/// and J, the nest in Es) off the tool reference point (head frame), mm. The readings are
/// absolute: zero with the ball at the nest's calibrated centre.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Setup {
    pub table_object_mm: Vec3,
    pub head_object_mm: Vec3,
}

/// The deviation of the spindle-side object's centre from the table-side object's centre,
/// table frame, mm: what processing recovers from any setting.
fn deviation_table(pose: &Pose, setup: &Setup) -> Vec3 {
    pose.table.transpose() * (pose.tool_rel + pose.head * setup.head_object_mm)
        - setup.table_object_mm
}

/// The ball centre relative to the nest centre, nest frame (mm), and the rotation ball ->
/// nest: E and J have the ball on the spindle and the nest on the table, Es the reverse.
fn nest_view(setting: Setting, pose: &Pose, setup: &Setup) -> (Vec3, Mat3) {
    let d = deviation_table(pose, setup);
    if setting.nest_on_table() {
        (d, pose.table.transpose() * pose.head)
    } else {
        (
            -(pose.head.transpose() * pose.table * d),
            pose.head.transpose() * pose.table,
        )
    }
}

/// Runs a test on a machine whose true state at time `t_ns` and commanded angles `a` is
/// `state_at(t_ns, a)` (the pose lets a truth put in what depends on where the axes stand:
/// indexing errors, backlash); readings from
/// `start_ns` on, spaced by the path over the feed plus the dwell.
pub fn simulate(
    k: &Kinematics,
    spec: &TestSpec,
    inst: &Instrument,
    state_at: &mut dyn FnMut(i64, &[f64; MAX_ROTARY]) -> MachineState,
    start_ns: i64,
    setup: &Setup,
    rng: &mut impl Rng,
) -> Result<Run, TestError> {
    spec.check(k)?;
    let angles = spec.angles();
    let mut t_ns = start_ns;
    let mut last = commanded(k, &angles[0], &spec.ball_mm);
    let mut points = Vec::with_capacity(angles.len());
    for (index, a) in angles.iter().enumerate() {
        let cmd = commanded(k, a, &spec.ball_mm);
        // The path between readings: the linear move, at least the arc of a 100 mm radius.
        let arc = (a[spec.axis] - angles[index.saturating_sub(1)][spec.axis])
            .abs()
            .to_radians()
            * 100.0;
        let path = (cmd - last).norm().max(arc);
        if index > 0 {
            t_ns += (path / spec.feed_mm_min * 60e9 + spec.dwell_s * 1e9) as i64;
        }
        last = cmd;
        let state = state_at(t_ns, a);
        let p = pose(k, &state, a, &spec.ball_mm);
        let (b, rot) = nest_view(inst.setting, &p, setup);
        let readings_um = inst
            .read(&b, &rot, rng)
            .map_err(|source| TestError::Reading {
                test: spec.kind.name(),
                angle_deg: a[spec.axis],
                source,
            })?;
        points.push(Point {
            index,
            angles_deg: *a,
            commanded_mm: cmd,
            readings_um,
            t_ns,
        });
    }
    Ok(Run {
        spec: spec.clone(),
        setting: inst.setting,
        points,
    })
}

/// The deviation the model predicts (um, table frame) of the spindle-side object's centre
/// from the table-side object's at a pose, for a machine state and set-up.
pub fn deviation_table_um(
    k: &Kinematics,
    state: &MachineState,
    angles: &[f64; MAX_ROTARY],
    p: &Vec3,
    setup: &Setup,
) -> Vec3 {
    deviation_table(&pose(k, state, angles, p), setup) * 1e3
}

/// The nominal rotations at a pose: table frame -> machine, head frame -> machine.
pub fn nominal_rotations(k: &Kinematics, angles: &[f64; MAX_ROTARY]) -> (Mat3, Mat3) {
    let nominal = k.nominal_state();
    let nl = k.lines(&nominal);
    (
        k.pose_transform_on(&nl, &nominal, angles).r,
        k.head_transform_on(&nl, &nominal, angles).r,
    )
}
