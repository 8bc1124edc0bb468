//! A program checked against its plan on the truth simulator: the same virtual machine (same
//! thermal state, same noise draws) runs the plan's steps as the plan lays them out and the
//! program's moves as `reader::replay` times them; both cycles are solved as the service
//! solves a cycle. A program that measures what its plan measures gives the same errors and
//! the same run time.

use thiserror::Error;

use driftwatch_core::cycle::{CycleChecks, plan_measurements, process_cycle};
use driftwatch_core::geometry::Vec3;
use driftwatch_core::kinematics::Kinematics;
use driftwatch_core::measurement::Approach;
use driftwatch_core::plan::{Plan, Step};
use driftwatch_core::recording::{DetectionIssue, DetectionMsg, DetectionStatus, Timed};
use driftwatch_sim::scenario::Scenario;
use driftwatch_sim::simulator::{SimError, VirtualMachine};

use driftwatch_nc::dialect::Dialect;
use driftwatch_nc::reader::{ReadError, ReplayError, read, replay};

#[derive(Debug, Error)]
pub enum CheckError {
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error("reading the {0} program: {1}")]
    Read(Dialect, ReadError),
    #[error("replaying the {0} program: {1}")]
    Replay(Dialect, ReplayError),
    #[error("the {what} cycle was rejected: {reason}")]
    Rejected { what: &'static str, reason: String },
}

/// One identified error as the plan and as the program measured it.
#[derive(Debug, Clone, PartialEq)]
pub struct Compared {
    pub name: String,
    pub unit: String,
    pub plan: f64,
    pub program: f64,
    pub sigma: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    pub errors: Vec<Compared>,
    /// The plan's machine time (nominal trips).
    pub plan_time_s: f64,
    /// The same with each probing move as long as the program's trip made it: the time the
    /// program must take if it runs the plan's moves.
    pub plan_time_at_trips_s: f64,
    pub program_time_s: f64,
    pub approaches: usize,
}

impl Check {
    /// The largest difference, um for position errors and urad for the rest.
    pub fn worst(&self, unit: &str) -> f64 {
        self.errors
            .iter()
            .filter(|e| e.unit == unit)
            .map(|e| (e.plan - e.program).abs())
            .fold(0.0, f64::max)
    }
}

type Entry = Timed<Result<DetectionMsg, DetectionIssue>>;

/// Run `plan` and the `d` program `text` on the virtual machine of `scn` after `warm_min`
/// minutes at the plan's spindle speed, and solve both.
pub fn against_truth(
    k: &Kinematics,
    plan: &Plan,
    text: &str,
    d: Dialect,
    scn: &Scenario,
    warm_min: f64,
) -> Result<Check, CheckError> {
    let rpm = plan.config.spindle_rpm;
    let mut vm0 = VirtualMachine::new(k, scn)?;
    vm0.advance_to(vm0.start_ns() + (warm_min * 60e9) as i64, rpm);
    let t0 = vm0.now_ns();
    let at = |s: f64| t0 + (s * 1e9).round() as i64;

    let mut vm = vm0.clone();
    let mut by_plan: Vec<Entry> = Vec::new();
    for s in &plan.steps {
        vm.advance_to(at(s.t_start_s), rpm);
        let det = vm.probe(k, s, 1, rpm);
        by_plan.push(Timed {
            t_ns: det.t_ns,
            msg: Ok(det.msg),
        });
    }

    let program = read(text, d).map_err(|e| CheckError::Read(d, e))?;
    let mut vm = vm0;
    let mut by_program: Vec<Entry> = Vec::new();
    let replayed = replay(k, &program, |a| {
        vm.advance_to(at(a.t_start_s), a.spindle_rpm);
        let fields = k.fields_from_angles(&a.angles);
        let start = Vec3::new(a.start[0], a.start[1], a.start[2]);
        let step = Step {
            label: a.label.clone(),
            b_deg: fields.0,
            c_deg: fields.1,
            angles: a.angles,
            approach: Approach {
                axis: a.axis,
                direction: a.direction,
                feed_mm_min: a.feed_mm_min,
            },
            start,
            // The reader does not know where the beam is; the simulator finds the trip.
            expected: start[a.axis.index()],
            max_travel_mm: a.travel_mm,
            t_start_s: a.t_start_s,
        };
        let det = vm.probe(k, &step, 1, a.spindle_rpm);
        let v = match det.msg.status() {
            DetectionStatus::Ok => Some([det.msg.x_mm, det.msg.y_mm, det.msg.z_mm][a.axis.index()]),
            _ => None,
        };
        by_program.push(Timed {
            t_ns: det.t_ns,
            msg: Ok(det.msg),
        });
        v
    })
    .map_err(|e| CheckError::Replay(d, e))?;

    let mut checks = CycleChecks::new(k);
    checks.expected = Some(plan_measurements(plan));
    let solve = |what: &'static str, entries: &[Entry]| {
        let o = process_cycle(k, 1, entries, &checks);
        o.solution.ok_or(CheckError::Rejected {
            what,
            reason: o.reason.unwrap_or_default(),
        })
    };
    let a = solve("plan", &by_plan)?;
    let b = solve("program", &by_program)?;
    let errors = a
        .errors
        .iter()
        .filter_map(|e| {
            let p = b.errors.iter().find(|x| x.name == e.name)?;
            Some(Compared {
                name: e.name.clone(),
                unit: e.unit.clone(),
                plan: e.value,
                program: p.value,
                sigma: e.sigma,
            })
        })
        .collect();
    let longer: f64 = replayed
        .approaches
        .iter()
        .filter_map(|(a, v)| {
            let s = plan.steps.get(a.number.checked_sub(1)?)?;
            let ax = a.axis.index();
            Some(
                ((v - a.start[ax]).abs() - (s.expected - s.start[ax]).abs())
                    / (a.feed_mm_min / 60.0),
            )
        })
        .sum();
    Ok(Check {
        errors,
        plan_time_s: plan.machine_time_s,
        plan_time_at_trips_s: plan.machine_time_s + longer,
        program_time_s: replayed.run_time_s,
        approaches: replayed.approaches.len(),
    })
}
